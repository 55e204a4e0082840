"""The simulated instrument: echoes at the true delay, noise at the stated SNR, 1/r^2,
ghosts and other users only when configured, and determinism."""

from __future__ import annotations

import tomllib
from importlib import resources

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from cdma_lidar.firmware_model.gold import gold_codes, gold_family
from cdma_lidar.firmware_model.receiver import FastReceiver, ReceiverConfig
from cdma_lidar.scene import load_scene
from cdma_lidar.scene.codebook import Codebook
from cdma_lidar.scene.instrument import Instrument, RenderSettings
from cdma_lidar.scene.scenefile import parse_scene
from cdma_lidar.units import SPEED_OF_LIGHT_M_S

FS = 62.5e6 * 4  # samples per second of the presets


def _wall(distance=5.0, count=4, columns=2, **over):
    opts = {"distance": distance, "instrument.wavelengths.count": count,
            "instrument.columns": columns}
    opts.update(over)
    return load_scene("flat-wall", overrides=opts)


def _receiver(inst, cfg=None, **kw):
    cfg = cfg or RenderSettings.from_spec(inst.spec)
    codes = gold_codes(cfg.poly_u, cfg.poly_v, cfg.code_index)
    start, length = inst.default_gate()
    kw.setdefault("out_bits", 24)
    rc = ReceiverConfig(adc_bits=inst.spec.adc_bits, samples_per_chip=cfg.samples_per_chip,
                        averages=cfg.averages, uid_bits=cfg.uid_bits, uid=cfg.uid,
                        gate_start=kw.pop("gate_start", start), gate_len=kw.pop("gate_len", length),
                        **kw)
    return FastReceiver(rc, codes)


def test_echo_peaks_at_the_true_delay_through_the_receive_chain():
    inst = Instrument(_wall(7.5, count=8, **{"instrument.snr_db": 0.0}), seed=3)
    out = _receiver(inst).column(inst.render(1))
    true_lag = inst.delay_s[:, 1] * FS
    assert np.all(np.abs(out.peak_lag - true_lag) <= 0.5 + 1e-9)
    # parabolic interpolation of the peak and its neighbours lands within a tenth of a sample
    y0, y2 = out.neighbours[:, 0].astype(float), out.neighbours[:, 1].astype(float)
    y1 = out.peak.astype(float)
    frac = 0.5 * (y0 - y2) / (y0 - 2 * y1 + y2)
    np.testing.assert_allclose(out.peak_lag + frac, true_lag, atol=0.1)


def _shell(radius_m):
    """A sphere around the sensor: every ray's range is exactly ``radius_m``."""
    return parse_scene({"instrument": {"wavelengths": {"count": 1}, "columns": 1,
                                       "noise_rms_v": 0.0},
                        "objects": [{"kind": "sphere", "position_m": [0.0, 0.0, 0.0],
                                     "radius_m": radius_m}]})


def test_fractional_delays_are_exact_one_sample_is_a_roll():
    ts_range = SPEED_OF_LIGHT_M_S / FS / 2  # one sample of round trip, in metres
    base = 5.0 + 0.37 * ts_range
    echoes = []
    for k in range(3):
        inst = Instrument(_shell(base + k * ts_range), seed=0)
        assert inst.truth.range_m[0, 0] == pytest.approx(base + k * ts_range, abs=1e-12)
        echoes.append(inst.echo(0, RenderSettings.from_spec(inst.spec))
                      / inst.gain_v_per_w[0, 0])  # 1/r^2 aside
    tol = 1e-9 * np.abs(echoes[0]).max()
    np.testing.assert_allclose(echoes[1], np.roll(echoes[0], 1), rtol=0, atol=tol)
    np.testing.assert_allclose(echoes[2], np.roll(echoes[0], 2), rtol=0, atol=tol)
    assert not np.allclose(echoes[0], np.roll(echoes[0], 1))
    # a half-sample step lands between its neighbours
    half = Instrument(_shell(base + 0.5 * ts_range), seed=0)
    mid = half.echo(0, RenderSettings.from_spec(half.spec)) / half.gain_v_per_w[0, 0]
    assert np.abs(mid - echoes[0]).max() < np.abs(echoes[1] - echoes[0]).max()


@pytest.mark.parametrize("snr_db", [-20.0, 0.0])
def test_measured_noise_matches_the_configured_snr(snr_db):
    inst = Instrument(_wall(5.0, count=4, columns=1, **{"instrument.snr_db": snr_db}), seed=11)
    cfg = RenderSettings.from_spec(inst.spec)
    codes = inst.render(0, cfg).astype(float)
    lsb = inst.spec.adc_full_scale_v / 2 ** (inst.spec.adc_bits - 1)
    echo = np.tile(inst.echo(0, cfg), cfg.averages)
    noise = codes * lsb - echo
    noise_var = noise.var() - lsb**2 / 12  # remove the quantisation noise
    amp = inst.gain_v_per_w[:, 0] * inst.spec.laser_power_w
    signal = np.median(amp**2) * inst.unit_signal_power(cfg)
    assert 10 * np.log10(signal / noise_var) == pytest.approx(snr_db, abs=0.15)
    # and the signal power of one channel is what the model says
    one = Instrument(_wall(5.0, count=1, columns=1), seed=0)
    measured = np.mean(one.echo(0, RenderSettings.from_spec(one.spec)) ** 2)
    assert measured == pytest.approx(one.gain_v_per_w[0, 0] ** 2 * 2.5e-3**2
                                     * one.unit_signal_power(cfg), rel=1e-9)


def test_amplitude_follows_inverse_square_of_range():
    peaks = {}
    for d in (3.0, 6.0):
        inst = Instrument(_wall(d, count=2, columns=1, **{"instrument.snr_db": 40.0}), seed=1)
        out = _receiver(inst, gate_start=0, gate_len=128).column(inst.render(0))
        peaks[d] = out.peak.astype(float)
    np.testing.assert_allclose(peaks[3.0] / peaks[6.0], 4.0, rtol=0.03)


def _ghost_scene(with_ghost: bool):
    doc = tomllib.loads(resources.files("cdma_lidar.scene").joinpath("presets", "flat-wall.toml")
                        .read_text("utf-8"))
    doc.pop("shortcuts")
    doc["instrument"].update({"wavelengths": {"count": 4}, "columns": 2})
    if with_ghost:
        doc["instrument"]["ghosts"] = [{"distance_m": 40.0, "amplitude_v": 4e-3,
                                        "channels": [2], "columns": [0]}]
    return parse_scene(doc)


def test_ghosts_appear_only_where_configured():
    ghost_lag = (80.0 / SPEED_OF_LIGHT_M_S + 37.3e-9) * FS
    results = {}
    for flag in (False, True):
        inst = Instrument(_ghost_scene(flag), seed=2)
        rx = _receiver(inst, gate_start=0, gate_len=128)
        results[flag] = [rx.column(inst.render(c)) for c in range(2)]
    j = round(ghost_lag)

    def strength(out, k):
        corr = out.corr[k].astype(float)
        floor = np.delete(corr, np.r_[np.arange(j - 8, j + 9), np.arange(0, 40)])
        return abs(corr[j]) / floor.std()

    assert strength(results[True][0], 2) > 8.0          # ghost: channel 2, column 0
    assert strength(results[True][0], 1) < 5.0          # other channel: no ghost
    assert strength(results[True][1], 2) < 5.0          # other column: no ghost
    assert strength(results[False][0], 2) < 5.0         # not configured: no ghost


def _multi_user(with_users: bool):
    doc = tomllib.loads(resources.files("cdma_lidar.scene").joinpath("presets", "multi-user.toml")
                        .read_text("utf-8"))
    doc["instrument"].update({"wavelengths": {"count": 2}, "columns": 1})
    if not with_users:
        del doc["instrument"]["other_users"]
    return parse_scene(doc)


def test_other_users_appear_with_their_uids_only_when_configured():
    found = {}
    for flag in (True, False):
        inst = Instrument(_multi_user(flag), seed=4)
        rx = _receiver(Instrument(_multi_user(True), seed=4), RenderSettings.from_spec(inst.spec),
                       peaks=4, peak_exclude=3)
        out = rx.column(inst.render(0))
        lags = np.concatenate([out.peak_lag[:1], out.extra_lag[0]])
        peaks = np.concatenate([out.peak[:1], out.extra_peak[0]])
        signs = np.concatenate([out.uid_signs[:1], out.extra_signs[0]])
        observed = [int(sum(1 << p for p in range(3) if s[p] < 0)) for s in signs]
        found[flag] = (lags, peaks, observed)
    spec = _multi_user(True).instrument
    ours = (2 * 8.0 / SPEED_OF_LIGHT_M_S + spec.system_delay_s) * FS
    lags, peaks, observed = found[True]
    assert abs(lags[0] - ours) <= 1 and observed[0] == spec.uid
    for user in spec.other_users:
        lag = (user.delay_s + spec.system_delay_s * 0) * FS
        hit = [i for i in range(4) if abs(lags[i] - lag) <= 1]
        assert hit, f"user {user.uid} at lag {lag:.1f} not among {lags}"
        assert observed[hit[0]] == user.uid
    lags_alone, peaks_alone, _ = found[False]
    assert abs(lags_alone[0] - ours) <= 1
    # without other users the extra peaks are only noise: far weaker than with them
    assert np.abs(peaks_alone[1:]).max() < 0.5 * np.sort(np.abs(peaks[1:]))[-1]


def test_same_seed_same_bytes_any_column_order():
    scene = _wall(5.0, count=3, columns=3)
    a = Instrument(scene, seed=7)
    b = Instrument(scene, seed=7)
    first = [a.render(c, frame=2).tobytes() for c in range(3)]
    backwards = [b.render(c, frame=2).tobytes() for c in (2, 1, 0)][::-1]
    assert first == backwards
    assert Instrument(scene, seed=8).render(0, frame=2).tobytes() != first[0]
    assert a.render(0, frame=3).tobytes() != first[0]


def test_unlit_channels_cost_nothing_and_calibration_lights_all():
    scene = load_scene("paper-scene1")
    inst = Instrument(scene, seed=0)
    cfg = RenderSettings.from_spec(inst.spec)
    empty = int(np.flatnonzero(~inst.truth.hits.lit.any(axis=0))[0])
    assert inst.lit_channels(empty).size == 0
    assert not np.any(inst.echo(empty, cfg))
    cal = inst.echo(empty, cfg, calibration=True)
    assert np.abs(cal).max() > 0
    lag = (2 * scene.calibration.target_distance_m / SPEED_OF_LIGHT_M_S
           + inst.spec.system_delay_s) * FS
    out = _receiver(inst).column(inst.render(0, cfg, calibration=True, shot=0))
    assert np.all(np.abs(out.peak_lag - lag) <= 1)


def test_adc_clips_and_offsets():
    inst = Instrument(_wall(5.0, count=1, columns=1), seed=0)
    codes = inst.to_codes(np.array([-10.0, 10.0, 0.0, 0.5 / 2048]))
    assert codes.tolist() == [-2048, 2047, 0, 1]


@pytest.mark.parametrize("adc_bits", [8, 12, 16])
def test_fused_adc_is_the_firmware_quantiser(adc_bits):
    """The instrument's float ADC equals the firmware's integer quantise(rint(x)) bit for bit:
    random values, every half-way point of a range of codes, both clip edges, infinities."""
    from cdma_lidar.firmware_model.adc import quantise
    from cdma_lidar.scene.sums import FRAC_BITS

    inst = Instrument(_wall(5.0, count=1, columns=1, **{"instrument.adc_bits": adc_bits}), 0)
    one = float(1 << FRAC_BITS)
    top = float(1 << (adc_bits - 1)) * one
    rng = np.random.default_rng(adc_bits)
    half = (np.arange(-40, 40) + 0.5) * one  # exactly between two codes
    fine = np.concatenate([
        rng.normal(0.0, 0.4 * top, 20000), rng.uniform(-3 * top, 3 * top, 2000),
        half, half - 0.5, half + 0.5, half - 1e-9 * one,
        [top - one / 2 - 1, top - one / 2, -top - one / 2 - 1, -top - one / 2, 2.0**60, -2.0**60],
    ])
    want = quantise(np.clip(np.rint(fine), -2.0**62, 2.0**62).astype(np.int64), FRAC_BITS,
                    adc_bits)
    got = inst.adc.quantise_fine(fine.copy())
    assert got.dtype == np.int16
    np.testing.assert_array_equal(got, want)
    assert inst.adc.quantise_fine(np.array([np.inf, -np.inf])).tolist() == [
        (1 << (adc_bits - 1)) - 1, -(1 << (adc_bits - 1))]


def test_gold_codes_match_the_code_generator():
    fam = gold_family((11, 2), (11, 8, 5, 2))
    idx = (0, 5, 2046, 2047, 2048)
    np.testing.assert_array_equal(gold_codes((11, 2), (11, 8, 5, 2), idx), fam[list(idx)])


def test_our_uid_polarity_matches_the_code_generator():
    from cdma_lidar.firmware_model.uid import polarity_modulate

    inst = Instrument(_shell(6.0), seed=0)
    base = RenderSettings.from_spec(inst.spec)
    cfg = RenderSettings(base.samples_per_chip, 1, 3, 0b101, base.code_index, base.poly_u,
                         base.poly_v)
    echo = inst.echo(0, cfg)
    lag = round(inst.delay_s[0, 0] * FS)
    bits = polarity_modulate(gold_codes(cfg.poly_u, cfg.poly_v, (0,))[0], 0b101, 3)
    ref = np.repeat(1.0 - 2.0 * bits, cfg.samples_per_chip)  # what the device emits
    aligned = np.roll(echo, -lag)
    # the echo is the emitted sequence (all three periods, each with its polarity), delayed
    per_period = (aligned * ref).reshape(3, -1).sum(axis=1)
    flipped = (aligned * -ref).reshape(3, -1).sum(axis=1)
    assert np.all(per_period > 0) and np.all(flipped < 0)
    plain = np.repeat(1.0 - 2.0 * gold_codes(cfg.poly_u, cfg.poly_v, (0,))[0], 4)
    signs = np.sign((aligned.reshape(3, -1) * plain).sum(axis=1))
    assert signs.tolist() == [-1.0, 1.0, -1.0]  # bit p of 0b101 set -> period p inverted


@settings(max_examples=40, deadline=None)
@given(s=st.integers(1, 16), uid_bits=st.integers(1, 3), uid=st.integers(0, 7),
       taus=st.lists(st.floats(0.0, 2e-6), min_size=1, max_size=5), seed=st.integers(0, 99))
def test_the_periodic_synthesis_equals_the_spectrum_summed_bin_by_bin(s, uid_bits, uid, taus,
                                                                      seed):
    """_sum_delayed (a period of bins per term, then one scaled add per further period)
    against its definition, weight[q] sum_k A_k dft_k[q % nN] exp(-2j pi q f0 tau_k), at
    every S (odd frame lengths and S = 1, where the bins end inside the first period),
    UID length and delay, to a few units in the last place; rows and the order of terms
    as the batch gives them."""
    inst = Instrument(_wall(count=3), 0)
    base = RenderSettings.from_spec(inst.spec)
    cfg = RenderSettings(s, 1, uid_bits, uid % (1 << uid_bits), base.code_index, base.poly_u,
                         base.poly_v)
    members = [int(cfg.code_index[k % 3]) for k in range(len(taus))]
    amps = np.random.default_rng(seed).uniform(-1.0, 1.0, len(taus))
    dfts, period = inst.codebook.chip_spectra(cfg, tuple(set(members)), cfg.uid, cfg.uid_bits)
    weight = inst.codebook.spectral_weight(cfg, period)
    f0 = inst.spec.chip_rate_hz / cfg.frame_chips
    rows = [k % 2 for k in range(len(taus))]
    got = np.empty((2, weight.size), dtype=np.complex128)
    Codebook.sum_delayed(f0, amps, np.asarray(taus), *Codebook.stack(dfts, members),
                            period, weight, out=got, rows=rows)
    q = np.arange(weight.size)
    want = np.zeros_like(got)
    for a, tau, i, r in zip(amps, taus, members, rows, strict=True):
        want[r] += a * dfts[i].reshape(-1)[q % period] * np.exp(-2j * np.pi * q * f0 * tau)
    want *= weight
    scale = np.abs(want).max()
    assert np.abs(got - want).max() <= 1e-12 * scale
    assert period == uid_bits * ((1 << cfg.poly_u[0]) - 1) and weight.size == period * s // 2 + 1


@settings(max_examples=40, deadline=None)
@given(s=st.integers(1, 8), r=st.integers(1, 100), uid_bits=st.integers(1, 4),
       codes=st.lists(st.integers(0, 2048), min_size=1, max_size=48))
def test_render_settings_hash_once_and_as_their_fields(s, r, uid_bits, codes):
    """The settings' cached hash is the hash of their fields, equal settings hash alike
    whatever was hashed before, and a pickled copy carries no stale hash."""
    import dataclasses
    import pickle

    cfg = RenderSettings(s, r, uid_bits, 0, tuple(codes), (11, 2, 0), (11, 8, 5, 2, 0))
    fields = tuple(getattr(cfg, f.name) for f in dataclasses.fields(cfg))
    assert hash(cfg) == hash(fields) == hash(cfg)
    copy = pickle.loads(pickle.dumps(cfg))
    assert "_hash" not in copy.__dict__ and copy == cfg and hash(copy) == hash(cfg)
    other = dataclasses.replace(cfg, averages=r + 1)
    assert other != cfg and hash(other) == hash((s, r + 1, *fields[2:]))
