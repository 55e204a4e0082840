"""Fidelity levels: ``accumulated`` (the R-repetition sum drawn directly) against ``exact``
(every repetition drawn and quantised), statistically, with stated tolerances; and the
fallback to ``exact`` where the level's condition does not hold."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy import stats

from cdma_lidar.host.frame import FrameData
from cdma_lidar.host.ranging import RangingConfig, estimate_ranges
from cdma_lidar.host.scan import summarise
from cdma_lidar.protocol.messages import CaptureKind
from cdma_lidar.scene import load_scene
from cdma_lidar.scene.instrument import Instrument, RenderSettings
from cdma_lidar.scene.sums import (
    EXACT_SUM_MIN_NOISE_LSB,
    FRAC_BITS,
    ROUNDING_LSB,
    SUM_TYPE,
    draw_repetition_sum,
    split_sum,
)
from cdma_lidar.units import SPEED_OF_LIGHT_M_S
from cdma_lidar.virtual.board import VirtualFirmware


def _acc_exact(inst: Instrument, column: int, cfg: RenderSettings, frame: int) -> np.ndarray:
    raw = inst.render_exact(column, cfg, frame).astype(np.int64)
    return raw.reshape(cfg.averages, -1).sum(axis=0)


def test_accumulator_values_have_the_exact_levels_distribution():
    """Per sample: the same mean (R x) and variance R (sigma^2 + 1/12); pooled residuals
    have the same distribution (two-sample KS distance under 0.01 over 320 000 values)."""
    scene = load_scene("flat-wall?distance=5&instrument.wavelengths.count=6"
                       "&instrument.columns=1")
    exact = Instrument(scene, 3)
    acc = Instrument(load_scene("flat-wall?distance=5&instrument.wavelengths.count=6"
                                "&instrument.columns=1&fidelity=accumulated"), 3)
    cfg = RenderSettings.from_spec(exact.spec)
    frames = 40
    a = np.stack([_acc_exact(exact, 0, cfg, f) for f in range(frames)]).astype(np.float64)
    b = np.stack([acc.render_accumulated(0, cfg, f).reshape(-1)
                  for f in range(frames)]).astype(np.float64)
    echo, sigma_v = exact.column_model(0, cfg)
    scale = exact.adc.fine_scale()[0] / (1 << FRAC_BITS)  # LSB per volt
    mean = cfg.averages * echo * scale
    sigma = sigma_v * scale
    assert sigma > 20  # the preset's noise spans many LSB: the level applies
    var = cfg.averages * (sigma**2 + 1 / 12)
    for x in (a, b):
        resid = x - mean[None, :]
        # mean: within 4 standard errors of zero over all 327 520 values
        assert abs(resid.mean()) < 4 * np.sqrt(var / resid.size)
        # variance: within 1 % of R (sigma^2 + 1/12)
        assert resid.var() == pytest.approx(var, rel=0.01)
    # the per-sample means agree (the echo is reproduced sample by sample)
    diff = a.mean(axis=0) - b.mean(axis=0)
    assert np.abs(diff).max() < 5 * np.sqrt(2 * var / frames)
    d = stats.ks_2samp((a - mean).ravel(), (b - mean).ravel()).statistic
    assert d < 0.01


def _frame(scene_url: str, seed: int) -> dict[str, float]:
    scene = load_scene(scene_url)
    fw = VirtualFirmware(scene, seed)
    spec = scene.instrument
    c = fw.get_config()
    data = FrameData.from_columns(fw.scan(1, 0, fw.columns), fw.channels, fw.columns,
                                  uid_bits=c["uid_bits"], peaks=c["peaks"])
    rc = RangingConfig(samples_per_chip=c["samples_per_chip"], chip_rate_hz=spec.chip_rate_hz,
                       code_length=spec.code_length, uid=c["uid"],
                       offset_m=spec.system_delay_s * SPEED_OF_LIGHT_M_S / 2)
    return summarise(estimate_ranges(data, rc), fw.instrument.truth.range_m)


@pytest.mark.parametrize("scene", ["flat-wall?distance=13&instrument.columns=8",
                                   "paper-scene1?instrument.columns=48"])
def test_valid_fraction_and_range_error_match_exact_over_seeds(scene):
    """Over seeds 1..3: valid fraction within 3 points, median range error within 0.3 cm or
    10 % (at 13 m the error is noise-limited, about 8 cm, and scatters by seed)."""
    exact = [_frame(scene, s) for s in (1, 2, 3)]
    acc = [_frame(scene + "&fidelity=accumulated", s) for s in (1, 2, 3)]

    def mean(rows: list[dict[str, float]], key: str) -> float:
        return float(np.mean([r[key] for r in rows]))

    assert mean(acc, "valid_fraction") == pytest.approx(mean(exact, "valid_fraction"), abs=0.03)
    assert mean(acc, "median_error_m") == pytest.approx(mean(exact, "median_error_m"),
                                                        rel=0.1, abs=0.003)


def test_split_frames_sum_to_the_drawn_accumulator_and_are_valid_codes():
    inst = Instrument(load_scene("flat-wall?instrument.columns=2&fidelity=accumulated"), 5)
    cfg = RenderSettings.from_spec(inst.spec)
    raw = inst.render(1, cfg, 7)
    acc = inst.render_accumulated(1, cfg, 7)
    assert raw.dtype == np.int16 and raw.size == cfg.averages * cfg.frame_samples
    np.testing.assert_array_equal(raw.reshape(cfg.averages, -1).astype(np.int64).sum(axis=0),
                                  acc.reshape(-1))
    half = 1 << (inst.spec.adc_bits - 1)
    assert raw.min() >= -half and raw.max() < half


def test_under_one_lsb_of_noise_the_level_falls_back_to_exact():
    """The fallback renders exactly with the same seeds: bit-identical column results."""
    url = "flat-wall?instrument.columns=3&instrument.noise_rms_v=0.0002"
    inst = Instrument(load_scene(url + "&fidelity=accumulated"), 2)
    assert inst.render_accumulated(0, RenderSettings.from_spec(inst.spec), 0) is None
    exact = VirtualFirmware(load_scene(url), 2)
    acc = VirtualFirmware(load_scene(url + "&fidelity=accumulated"), 2)
    a = [r.records.tobytes() for r in exact.scan(4, 0, 3)]
    b = [r.records.tobytes() for r in acc.scan(4, 0, 3)]
    assert a == b


def test_near_the_clip_the_level_falls_back_to_exact():
    # a wall at 0.3 m: echoes of hundreds of mV, within 6 sigma of the 1 V full scale
    inst = Instrument(load_scene("flat-wall?distance=0.3&instrument.columns=1"
                                 "&fidelity=accumulated"), 0)
    cfg = RenderSettings.from_spec(inst.spec)
    echo, sigma = inst.column_model(0, cfg)
    assert np.abs(echo).max() + 6 * sigma > inst.spec.adc_full_scale_v
    assert inst.render_accumulated(0, cfg, 0) is None


def _loud_neighbour():
    """A far wall (faint echoes) beside another LiDAR on our code whose light dominates."""
    import tomllib
    from importlib import resources

    from cdma_lidar.scene.scenefile import parse_scene

    doc = tomllib.loads(resources.files("cdma_lidar.scene").joinpath(
        "presets", "flat-wall.toml").read_text("utf-8"))
    doc.pop("shortcuts")
    doc["fidelity"] = "accumulated"
    doc["objects"][0]["position_m"][0] = 60.0
    doc["instrument"]["other_users"] = [{"uid": 0, "code_index": 0, "distance_m": 9.0,
                                         "amplitude_v": 0.05}]
    return parse_scene(doc)


@pytest.mark.parametrize("url", ["near-far", "multi-user", "flat-wall?distance=0.6", None])
def test_accumulated_clip_check_looks_at_a_row_only_where_its_bound_does_not_settle_it(url):
    """_accumulated_means returns each row's largest |value| or, where that is within the
    row's limit, a bound on it: never below the value, and on the same side of every
    limit, so the clip decision is the value's. Scenes with echoes of every size, other
    users' light (their reach is in the bound: None, where it dominates) and echoes near
    the clip."""
    scene = _loud_neighbour() if url is None else load_scene(
        url + ("&" if "?" in url else "?") + "fidelity=accumulated")
    inst = Instrument(scene, 1)
    cfg = RenderSettings.from_spec(inst.spec)
    items = [(c, inst.default_power_w[:, c]) for c in range(inst.columns)]
    means, value = inst.plans._accumulated_means(cfg, items, False, [-np.inf] * len(items))
    value = np.array(value)
    rng = np.random.default_rng(0)
    bounded = 0
    for limits in (value, value * 2, np.nextafter(value, -np.inf), np.full(value.size, np.inf),
                   rng.uniform(0, 2 * value.max(), value.size)):
        again, got = inst.plans._accumulated_means(cfg, items, False, limits.tolist())
        got = np.array(got)
        assert np.all(got >= value)
        np.testing.assert_array_equal(got <= limits, value <= limits)
        np.testing.assert_array_equal(got[got > limits], value[got > limits])
        np.testing.assert_array_equal(np.stack(again), np.stack(means))
        bounded += int(np.sum(got != value))
    assert bounded > 0  # the bound did stand in for the pass over the row


def test_calibration_and_capture_at_accumulated_fidelity():
    """CALIBRATE draws each shot's sum too; CAPTURE RAW gives frames whose receive-chain
    result is exactly the scan's."""
    fw = VirtualFirmware(load_scene("paper-scene1?fidelity=accumulated"), 4)
    exact = VirtualFirmware(load_scene("paper-scene1"), 4)
    target = fw.scene.calibration.target_distance_m
    lags = []
    for dev in (fw, exact):
        shots = list(dev.calibrate(0, 8))
        lags.append(np.stack([s.peak_lag for s in shots]).astype(float))
    # the same target: every channel's peak at the same lag in both levels (+-1 lag)
    assert np.abs(np.median(lags[0], axis=0) - np.median(lags[1], axis=0)).max() <= 1
    want = (2 * target / SPEED_OF_LIGHT_M_S + fw.spec.system_delay_s) * 250e6
    assert abs(np.median(lags[0]) - want) <= 1
    (col,) = list(fw.scan(3, 17, 1))
    raw = fw.capture(CaptureKind.RAW, 17, 0)
    again = fw.receiver().column(raw)
    np.testing.assert_array_equal(again.peak_lag, col.peak_lag)
    np.testing.assert_array_equal(again.peak, col.peak)


@given(st.integers(1, 1024), st.integers(8, 16), st.data())
@settings(max_examples=200, deadline=None)
def test_split_sum_gives_valid_codes_that_sum_exactly(r, bits, data):
    lo, hi = -(1 << (bits - 1)), (1 << (bits - 1)) - 1
    drawn = data.draw(st.lists(st.integers(r * lo, r * hi), min_size=1, max_size=50))
    acc = np.array([*drawn, r * lo, r * hi], dtype=np.int64)  # with both extremes
    frames = split_sum(acc, r)
    assert frames.shape == (r, acc.size) and frames.dtype == np.int16
    np.testing.assert_array_equal(frames.astype(np.int64).sum(axis=0), acc)
    assert frames.min() >= lo and frames.max() <= hi
    assert np.all(frames.max(axis=0).astype(np.int64) - frames.min(axis=0) <= 1)


# -- exact fidelity: the repetition sum drawn directly ----------------------------------


def _sum_pmf(x: float, sigma: float, r: int) -> tuple[np.ndarray, int]:
    """(probabilities, lowest value) of sum_r floor(x + ROUNDING_LSB + sigma z_r): the
    R-fold convolution of one repetition's exact probabilities."""
    lo, hi = int(np.floor(x - 12 * sigma)), int(np.ceil(x + 12 * sigma))
    k = np.arange(lo, hi + 1)
    y = x + ROUNDING_LSB
    one = stats.norm.cdf((k + 1 - y) / sigma) - stats.norm.cdf((k - y) / sigma)
    pmf = np.ones(1)
    for _ in range(r):
        pmf = np.convolve(pmf, one)
    return pmf, r * lo


@pytest.mark.parametrize("r", [2, 3])
@pytest.mark.parametrize("x", [0.0, 0.3, 0.77])
def test_the_drawn_sums_formula_is_the_convolution_of_the_repetitions(x, r):
    """P(floor(R (x + c) + sqrt(R) sigma z - IH_{R-1}) = k), integrated numerically over the
    Irwin-Hall density (uniform for R = 2, triangle for R = 3), equals the convolution of
    the R repetitions' probabilities to 1e-12 at sigma = EXACT_SUM_MIN_NOISE_LSB."""
    from scipy import integrate
    sigma = EXACT_SUM_MIN_NOISE_LSB
    pmf, lo = _sum_pmf(x, sigma, r)
    m, s = r * (x + ROUNDING_LSB), np.sqrt(r) * sigma
    density = (lambda u: 1.0) if r == 2 else (lambda u: 1 - abs(u - 1))
    for k in range(lo + pmf.size // 2 - 12, lo + pmf.size // 2 + 12):
        def p(u: float, k: int = k) -> float:
            return density(u) * (stats.norm.cdf((k + 1 - m + u) / s)
                                 - stats.norm.cdf((k - m + u) / s))
        got = integrate.quad(p, 0, r - 1, epsabs=1e-15, epsrel=1e-13,
                             points=[1] if r == 3 else None)[0]
        assert got == pytest.approx(pmf[k - lo], abs=1e-12)


@pytest.mark.parametrize("x, r", [(0.0, 2), (0.3, 10), (-7.77, 3)])
def test_draw_repetition_sum_has_the_sums_distribution(x, r):
    """2 million sums against the exact probabilities (chi-square, p > 1e-3, seeded); the
    same test rejects the sum drawn without the uniforms (variance short by (R-1)/12)."""
    sigma = EXACT_SUM_MIN_NOISE_LSB
    pmf, lo = _sum_pmf(x, sigma, r)
    mean = np.full(2_000_000, r * (x + ROUNDING_LSB))

    def pvalue(values: np.ndarray) -> float:
        counts = np.bincount(values - lo, minlength=pmf.size)[:pmf.size]
        expected = pmf * values.size
        keep = expected > 20
        obs, exp = counts[keep], expected[keep]
        exp = exp * obs.sum() / exp.sum()
        return float(stats.chisquare(obs, exp).pvalue)

    drawn = draw_repetition_sum(np.random.default_rng(11), mean, sigma, r)
    assert drawn.dtype == SUM_TYPE
    assert pvalue(drawn) > 1e-3
    if r > 2:
        z = np.random.default_rng(12).standard_normal(mean.size)
        naive = np.floor(mean + np.sqrt(r) * sigma * z).astype(np.int64)
        assert pvalue(naive) < 1e-6


def test_exact_scan_sums_match_repetition_by_repetition_rendering():
    """render_sum at exact against the sum of render_exact's repetitions over 40 frames of a
    6-channel wall column: per-sample means within 5 standard errors, pooled variance
    within 1 %, two-sample KS distance of the residuals under 0.01."""
    url = "flat-wall?distance=5&instrument.wavelengths.count=6&instrument.columns=1"
    inst = Instrument(load_scene(url), 3)
    cfg = RenderSettings.from_spec(inst.spec)
    frames = 40
    a = np.stack([_acc_exact(inst, 0, cfg, f) for f in range(frames)]).astype(np.float64)
    b = np.stack([inst.render_sum(0, cfg, f).reshape(-1) for f in range(frames)]
                 ).astype(np.float64)
    echo, sigma_v = inst.column_model(0, cfg)
    scale = inst.adc.fine_scale()[0] / (1 << FRAC_BITS)
    mean = cfg.averages * (echo * scale + ROUNDING_LSB - 0.5)
    var = cfg.averages * ((sigma_v * scale) ** 2 + 1 / 12)
    for x in (a, b):
        assert (x - mean).var() == pytest.approx(var, rel=0.01)
    assert np.abs(a.mean(axis=0) - b.mean(axis=0)).max() < 5 * np.sqrt(2 * var / frames)
    assert stats.ks_2samp((a - mean).ravel(), (b - mean).ravel()).statistic < 0.01


def test_exact_sum_falls_back_under_three_lsb_of_noise_and_near_the_clip():
    quiet = Instrument(load_scene("flat-wall?instrument.columns=1"
                                  "&instrument.noise_rms_v=0.001"), 0)  # about 2 LSB
    assert quiet.render_sum(0) is None
    near = Instrument(load_scene("flat-wall?distance=0.3&instrument.columns=1"), 0)
    assert near.render_sum(0) is None
    assert Instrument(load_scene("flat-wall?instrument.columns=1"), 0).render_sum(0) is not None


def test_exact_sums_carry_the_other_users_light_repetition_by_repetition():
    """multi-user (three other LiDARs, not periodic in our frame): the drawn sums' per-sample
    means match the sums of render_exact's repetitions within 5 standard errors over 12
    frames, and both carry the users' summed light: regressed on it, slope 1 within 0.05
    (0 would mean the users were left out)."""
    inst = Instrument(load_scene("multi-user"), 1)
    cfg = RenderSettings.from_spec(inst.spec)
    frames = 12
    a = np.stack([_acc_exact(inst, 2, cfg, f) for f in range(frames)]).astype(np.float64)
    b = np.stack([inst.render_sum(2, cfg, f).reshape(-1) for f in range(frames)]
                 ).astype(np.float64)
    scale = inst.adc.fine_scale()[0] / (1 << FRAC_BITS)
    var = cfg.averages * ((inst.noise_rms_v_at(2, cfg) * scale) ** 2 + 1 / 12)
    assert np.abs(a.mean(axis=0) - b.mean(axis=0)).max() < 5 * np.sqrt(2 * var / frames)
    users = inst.other_users_signal(2, cfg, cfg.averages * cfg.frame_samples)
    u = users.reshape(cfg.averages, -1).sum(axis=0) * scale
    own = cfg.averages * (inst.column_model(2, cfg)[0] * scale + ROUNDING_LSB - 0.5)
    for x in (a, b):
        slope = np.dot(x.mean(axis=0) - own, u) / np.dot(u, u)
        assert slope == pytest.approx(1.0, abs=0.05)


@pytest.mark.parametrize("compensated", [True, False])
@pytest.mark.parametrize("r", [2, 3])
def test_the_byte_grid_uniforms_keep_the_sums_law_only_with_their_variance(r, compensated):
    """draw_repetition_sum's law, summed exactly over its byte-grid uniforms (256 values for
    R = 2, 65536 pairs for R = 3), equals the R-fold convolution of the repetitions'
    probabilities to 1e-12 with the Gaussian's variance raised by (R - 1) / (12 * 256^2);
    without that variance the same comparison fails (errors near 1e-8)."""
    from cdma_lidar.scene import sums
    sigma, x = EXACT_SUM_MIN_NOISE_LSB, 0.3
    pmf, lo = _sum_pmf(x, sigma, r)
    u = (np.arange(256) + 0.5) / 256
    grid = u if r == 2 else (u[:, None] + u[None, :]).ravel()
    var = r * sigma**2 + (r - 1) * (sums._BYTE_VARIANCE if compensated else 0.0)
    m, s = r * (x + ROUNDING_LSB), np.sqrt(var)
    k = np.arange(lo + pmf.size // 2 - 12, lo + pmf.size // 2 + 12)
    got = (stats.norm.cdf((k[:, None] + 1 - m + grid) / s)
           - stats.norm.cdf((k[:, None] - m + grid) / s)).mean(axis=1)
    err = np.abs(got - pmf[k - lo]).max()
    assert (err < 1e-12) == compensated, err


# -- accumulated fidelity: tabulated echoes and table Gaussians ---------------------------


def test_the_normal_table_is_a_unit_normal_to_two_to_the_minus_sixteen():
    """accumulated's Gaussians: symmetric, mean 0, variance 1 (to float32), within
    2^-16 of the normal distribution function (Kolmogorov), cut near 4.3 sigma."""
    from cdma_lidar.scene.sums import _normal_table
    t = _normal_table().astype(np.float64)
    assert t.size == 1 << 16 and np.all(np.diff(t) > 0)
    np.testing.assert_array_equal(t, -t[::-1])
    assert abs(t.mean()) < 1e-9 and t.var() == pytest.approx(1.0, abs=1e-6)
    cdf = stats.norm.cdf(t)
    i = np.arange(t.size)
    assert max(np.abs(cdf - i / t.size).max(), np.abs(cdf - (i + 1) / t.size).max()) \
        < 1.01 * 2.0**-16
    assert 4.2 < t.max() < 4.4


def test_tabulated_echo_matches_the_fourier_synthesis():
    """accumulated's echo (waveforms tabulated at 1/8 sample, interpolated) against
    Instrument.echo on paper-scene1's columns and a calibration shot: within 0.6 % of
    each column's peak, and not merely shaped alike: a table read one step off errs by
    over 5 %."""
    from cdma_lidar.scene import codebook
    inst = Instrument(load_scene("paper-scene1"), 0)
    cfg = RenderSettings.from_spec(inst.spec)

    cols = [(c, False) for c in range(0, 160, 7)] + [(0, True)]
    ref = [inst.echo(c, cfg, calibration=cal) for c, cal in cols]
    got = [inst.tabulated_echo(c, cfg, calibration=cal) for c, cal in cols]
    assert all(g.dtype == np.float32 for g in got)

    def worst(ref: list) -> float:
        return max(float(np.abs(g - r).max() / np.abs(r).max())
                   for g, r in zip(got, ref, strict=True) if np.any(r))

    assert worst(ref) < 0.006
    shift = codebook.Codebook.sample_shift_s
    step = 1 / (inst.spec.chip_rate_hz * cfg.samples_per_chip * codebook.TABLE_PHASES)
    try:  # the reference one table step later
        codebook.Codebook.sample_shift_s = lambda self, c: shift(self, c) + step
        assert worst([inst.echo(c, cfg, calibration=cal) for c, cal in cols]) > 0.05
    finally:
        codebook.Codebook.sample_shift_s = shift


def test_accumulated_uses_the_fourier_echo_where_the_table_would_not_fit(monkeypatch):
    """A table of every member larger than ECHO_CACHE_BYTES: the plan's echo is
    Instrument.echo in single precision instead (same noise, sums within the table's
    0.6 % of the echo)."""
    from cdma_lidar.scene import echoes
    url = "flat-wall?distance=5&instrument.wavelengths.count=6&instrument.columns=1"
    inst = Instrument(load_scene(url + "&fidelity=accumulated"), 3)
    cfg = RenderSettings.from_spec(inst.spec)
    table = inst.render_sum(0, cfg, 1)
    monkeypatch.setattr(echoes, "ECHO_CACHE_BYTES", 1 << 16)
    inst.forget()
    called = []
    echo = echoes.Echoes.echo
    monkeypatch.setattr(echoes.Echoes, "echo",
                        lambda self, *a, **k: called.append(k) or echo(self, *a, **k))
    fourier = inst.render_sum(0, cfg, 1)
    assert called and called[0].get("single") is True
    assert 0 < np.abs(fourier - table).max() <= 0.006 * np.abs(table).max()


@pytest.mark.parametrize("level", ["exact", "accumulated"])
def test_a_batch_of_columns_draws_what_each_column_draws_alone(level):
    """render_sums (the board's path) against render_sum column by column, bit for bit,
    on paper-scene1 columns in a scrambled order with repeats, lit and empty, one with
    its own laser power; and the exact echoes' batched inverse FFT equals echo()'s."""
    inst = Instrument(load_scene(f"paper-scene1?fidelity={level}"), 4)
    cfg = RenderSettings.from_spec(inst.spec)
    cols = [77, 3, 150, 77, 41, 0, 120]
    powers = [inst.default_power_w[:, c] for c in cols]
    powers[4] = powers[4] * 0.5
    sums, drawn = inst.render_sums(cols, cfg, 9, powers)
    assert drawn.all() and sums.shape == (len(cols), 1, cfg.frame_samples)
    inst.forget()
    for c, p, got in zip(cols, powers, sums, strict=True):
        np.testing.assert_array_equal(inst.render_sum(c, cfg, 9, p), got)
    assert not np.array_equal(sums[0], sums[1])
    np.testing.assert_array_equal(sums[0], sums[3])
    items = [(c, inst.default_power_w[:, c]) for c in cols]
    batch = inst.echoes.batch(cfg, items, False)[0]
    for (c, p), row in zip(items, batch, strict=True):
        np.testing.assert_array_equal(inst.echo(c, cfg, p), row)
    lit = int(np.argmax(inst.truth.hits.lit.sum(axis=0)))  # near the clip at 1000x power
    mixed, ok = inst.render_sums([lit, 41], cfg, 9, [inst.default_power_w[:, lit] * 1000,
                                                    powers[4]])
    assert ok.tolist() == [False, True] and not np.any(mixed[0])
    np.testing.assert_array_equal(mixed[1], sums[4])
    # complete: the column it cannot draw is rendered repetition by repetition and summed
    full, ok = inst.render_sums([lit, 41], cfg, 9, [inst.default_power_w[:, lit] * 1000,
                                                   powers[4]], complete=True)
    raw = inst.render_exact(lit, cfg, 9, inst.default_power_w[:, lit] * 1000)
    assert ok.tolist() == [False, True] and full.dtype == SUM_TYPE
    np.testing.assert_array_equal(full[0, 0], raw.reshape(cfg.averages, -1).astype(
        np.int64).sum(axis=0))
    np.testing.assert_array_equal(full[1], sums[4])
    cal, ok = inst.render_sums([2, 5], cfg, 9, calibration=True)
    assert ok.all() and not np.array_equal(cal[0], cal[1])
    np.testing.assert_array_equal(inst.render_sum(0, cfg, 9, calibration=True, shot=5), cal[1])
    # into a given array (the scan's, reused): the same sums, written over whatever it held
    into = np.full((2, 1, cfg.frame_samples), -7, dtype=SUM_TYPE)
    for args, kwargs, want in (([lit, 41], {"complete": True}, full), ([lit, 41], {}, mixed)):
        got, _ = inst.render_sums(args, cfg, 9, [inst.default_power_w[:, lit] * 1000,
                                                 powers[4]], out=into, **kwargs)
        assert got is into
        np.testing.assert_array_equal(into, want)


@pytest.mark.parametrize("bad", [np.zeros((2, 1, 8), dtype=SUM_TYPE),
                                 np.zeros((3, 1, 8188), dtype=SUM_TYPE),
                                 np.zeros((2, 1, 8188), dtype=np.int64),
                                 np.zeros((2, 1, 16376), dtype=SUM_TYPE)[:, :, ::2]])
def test_render_sums_refuses_an_out_array_of_another_shape_type_or_layout(bad):
    inst = _SMALL["accumulated"] if bad.shape[-1] == 8 else Instrument(
        load_scene("paper-scene1?fidelity=accumulated"), 4)
    cfg = RenderSettings.from_spec(inst.spec)
    with pytest.raises(ValueError, match="out"):
        inst.render_sums([0, 1], cfg, 0, out=bad)


#: a small scene at both levels for the batching property (5 channels, 6 columns, N = 127)
_SMALL = {level: Instrument(load_scene(
    "flat-wall?distance=6&instrument.wavelengths.count=5&instrument.columns=6"
    f"&instrument.samples_per_chip=2&code_degree=7&fidelity={level}"), 2)
    for level in ("exact", "accumulated")}


@settings(max_examples=25, deadline=None)
@given(data=st.data(), level=st.sampled_from(["exact", "accumulated"]))
def test_any_batching_of_columns_draws_the_same_sums(data, level):
    """render_sums over arbitrary batches (any order, repeats, one to all columns, own
    powers) equals render_sum column by column, bit for bit, at both levels."""
    inst = _SMALL[level]
    cfg = RenderSettings.from_spec(inst.spec)
    cols = data.draw(st.lists(st.integers(0, inst.columns - 1), min_size=1, max_size=9))
    scale = data.draw(st.lists(st.sampled_from([0.5, 1.0, 2.0]), min_size=len(cols),
                               max_size=len(cols)))
    frame = data.draw(st.integers(0, 2**32 - 1))
    powers = [inst.default_power_w[:, c] * k for c, k in zip(cols, scale, strict=True)]
    sums, drawn = inst.render_sums(cols, cfg, frame, powers)
    assert drawn.all()
    for c, p, got in zip(cols, powers, sums, strict=True):
        np.testing.assert_array_equal(inst.render_sum(c, cfg, frame, p), got)
