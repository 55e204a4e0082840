"""Interference cancellation (``cancel_rounds``): every fast path is bit-identical to the
streaming reference, the stage removes what it should, and its limits are clear errors.

Hypothesis draws configurations with one to three rounds and thresholds from "every
found peak" to "none", and signals whose echoes the first pass finds (so channels are
subtracted), full-scale ones (residual and amplitude saturate) and noise; the reference
is fed in random chunks. The deterministic cases show what the stage is for: a weak
echo that the first pass ranges on a strong one's cross-correlation is ranged right
after one round.
"""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import assume, given, settings
from hypothesis import strategies as st

from cdma_lidar.errors import ConfigError
from cdma_lidar.firmware_model.cancel import autocorrelation_table, subtracts
from cdma_lidar.firmware_model.gold import gold_codes
from cdma_lidar.firmware_model.receiver import (
    FastReceiver,
    ReceiverConfig,
    ReferenceReceiver,
    correlator_methods,
    reference,
)
from cdma_lidar.firmware_model.receiver_config import MAX_CANCEL_GATE
from cdma_lidar.firmware_model.snr import snr_q8


def echoes(rng, codes, cfg, amps, lags, noise=0):
    """A column of UID-modulated echoes amps[k] ref_k[i - lags[k]] (+ uniform noise),
    clipped like an ADC."""
    n, s = codes.shape[1], cfg.samples_per_chip
    ns = n * s
    period = np.zeros(ns, dtype=np.int64)
    for row, a, lag in zip(codes, amps, lags, strict=True):
        period += int(a) * np.roll(np.repeat(1 - 2 * row.astype(np.int64), s), int(lag))
    pol = [(-1) ** ((cfg.uid >> p) & 1) for p in range(cfg.uid_bits)]
    x = np.tile(np.concatenate([q * period for q in pol]), cfg.averages)
    if noise:
        x = x + rng.integers(-noise, noise + 1, x.size)
    lo, hi = -(1 << (cfg.adc_bits - 1)), (1 << (cfg.adc_bits - 1)) - 1
    return np.clip(x, lo, hi)


@st.composite
def cases(draw):
    n = draw(st.integers(3, 31))
    s = draw(st.integers(1, 3))
    k = draw(st.integers(1, 4))
    ns = n * s
    uid_bits = draw(st.sampled_from((1, 1, 2, 3)))
    b = draw(st.integers(8, 12))
    cfg = ReceiverConfig(
        adc_bits=b,
        samples_per_chip=s,
        averages=draw(st.integers(1, 3)),
        uid_bits=uid_bits,
        uid=draw(st.integers(0, (1 << uid_bits) - 1)),
        gate_start=draw(st.integers(0, ns - 1)),
        gate_len=draw(st.integers(1, ns)),
        peak_exclude=draw(st.integers(0, 3)),
        out_shift=draw(st.integers(0, 6)),
        rounding=draw(st.sampled_from(["truncate", "half_up", "convergent"])),
        out_bits=draw(st.integers(8, 32)),
        peaks=draw(st.integers(1, 2)),
        cancel_rounds=draw(st.integers(1, 3)),
        cancel_snr_q8=draw(st.sampled_from((0, 256, snr_q8(6.0), snr_q8(13.5), 2**32 - 1))),
    )
    try:
        cfg.widths(n)
    except ConfigError:
        assume(False)
    rng = np.random.default_rng(draw(st.integers(0, 2**32 - 1)))
    codes = rng.integers(0, 2, (k, n), dtype=np.uint8)
    kind = draw(st.sampled_from(["echo", "echo", "full", "noise"]))
    top = 1 << (b - 1)
    if kind == "echo":
        x = echoes(rng, codes, cfg, rng.integers(-top // 4, top // 4 + 1, k),
                   rng.integers(0, ns, k), noise=draw(st.integers(0, 8)))
    elif kind == "full":  # rails: amplitudes and residuals saturate
        x = rng.choice([-top, top - 1], cfg.column_samples(n))
    else:
        x = rng.integers(-top, top, cfg.column_samples(n))
    cuts = sorted(draw(st.lists(st.integers(0, x.size), max_size=4)))
    return cfg, codes, x.astype(draw(st.sampled_from([np.int16, np.int32, np.int64]))), cuts


@settings(max_examples=80, deadline=None)
@given(cases())
def test_every_kernel_with_cancellation_equals_the_chunked_reference(case):
    cfg, codes, x, cuts = case
    rx = ReferenceReceiver(cfg, codes)
    for chunk in np.split(x, cuts):
        rx.feed(chunk)
    want = rx.finish()
    for method in correlator_methods():
        fr = FastReceiver(cfg, codes, method=method)
        assert fr.column(x).mismatches(want) == [], method
        # a frame of two columns (the second a copy) and the accumulator entry point
        two = fr.frame(np.stack([x, x]))
        assert all(o.mismatches(want) == [] for o in two), method
        assert fr.from_accumulators(fr.accumulate(x[None, :]))[0].mismatches(want) == []


def _two_channel_case(rounds: int):
    """A weak echo (amplitude 2 at lag 40) beside a strong one (90 at lag 5) on degree-6
    Gold codes: the strong one's cross-correlation outweighs the weak one's peak."""
    codes = gold_codes((6, 1), (6, 5, 2, 1), (3, 17))
    cfg = ReceiverConfig(adc_bits=12, samples_per_chip=2, averages=1, gate_len=64,
                         cancel_rounds=rounds, cancel_snr_q8=snr_q8(10.0))
    x = echoes(np.random.default_rng(7), codes, cfg, (90, 2), (5, 40), noise=1)
    return cfg, codes, x


def test_one_round_ranges_the_weak_echo_the_first_pass_missed():
    cfg, codes, x = _two_channel_case(0)
    first = FastReceiver(cfg, codes).column(x)
    assert first.peak_lag[0] == 5 and first.peak_lag[1] != 40
    cfg, codes, x = _two_channel_case(1)
    got = FastReceiver(cfg, codes).column(x)
    assert got.peak_lag.tolist() == [5, 40]
    assert got.mismatches(reference(cfg, codes, x)) == []


def test_a_threshold_above_every_peak_subtracts_nothing():
    cfg, codes, x = _two_channel_case(2)
    none = cfg.replace(cancel_snr_q8=2**32 - 1)
    got = FastReceiver(none, codes).column(x)
    plain = FastReceiver(none.replace(cancel_rounds=0), codes).column(x)
    # the same integers, the output only one bit wider (nothing here reaches its rail)
    assert got.mismatches(plain) == []


@pytest.mark.parametrize("s", [1, 2, 3])
def test_autocorrelation_table_is_the_literal_sum(s):
    rng = np.random.default_rng(s)
    bip = (1 - 2 * rng.integers(0, 2, (3, 13))).astype(np.int8)
    g = 30  # offsets beyond the period wrap
    ref = np.repeat(bip.astype(np.int64), s, axis=1)
    ns = ref.shape[1]
    want = np.array([[int(np.dot(r, np.roll(r, -m))) for m in range(-g, g + 1)] for r in ref])
    assert np.array_equal(autocorrelation_table(bip, s, g), want)
    assert want[:, g].tolist() == [ns] * 3


def test_the_threshold_is_exact_at_its_boundary():
    cfg = ReceiverConfig(cancel_rounds=1, cancel_snr_q8=256 * 25)  # SNR_XC >= 25: 14 dB
    # noise: count 4, sum 0, sumsq 4 -> sigma^2 = 1; peak 5 -> SNR 25 exactly
    assert subtracts(cfg, 5, 4, 0, 4)
    assert not subtracts(cfg, 4, 4, 0, 4)
    assert subtracts(cfg, -5, 4, 0, 4)
    # no noise lags: the 1/12 LSB^2 floor, SNR = 12 peak^2
    assert subtracts(cfg.replace(cancel_snr_q8=256 * 12), 1, 0, 0, 0)
    assert not subtracts(cfg.replace(cancel_snr_q8=256 * 12 + 1), 1, 0, 0, 0)


def test_raw_is_one_bit_wider_with_cancellation():
    cfg = ReceiverConfig(samples_per_chip=2, averages=4, uid_bits=2, gate_len=16)
    plain, cancel = cfg.widths(31), cfg.replace(cancel_rounds=1).widths(31)
    assert (cancel.raw, cancel.uid) == (plain.raw + 1, plain.uid + 1)


@pytest.mark.parametrize(("field", "value"), [("cancel_rounds", 5), ("cancel_rounds", -1),
                                              ("cancel_snr_q8", 2**32)])
def test_out_of_range_settings_name_the_field(field, value):
    with pytest.raises(ConfigError, match=field):
        ReceiverConfig(**{field: value})


def test_a_gate_beyond_the_table_is_refused_with_cancellation_only():
    codes = np.zeros((1, 4095), np.uint8)
    cfg = ReceiverConfig(samples_per_chip=2, averages=1, gate_len=MAX_CANCEL_GATE + 1)
    FastReceiver(cfg, codes, prepare=False)
    with pytest.raises(ConfigError, match="gate_len"):
        FastReceiver(cfg.replace(cancel_rounds=1), codes, prepare=False)
    with pytest.raises(ConfigError, match="gate_len"):
        ReferenceReceiver(cfg.replace(cancel_rounds=1), codes)


def test_wide_sums_take_the_int64_path_and_stay_exact():
    """64 channels at 16 bits and R = 1024: the echo sum may pass 2^31, so the residual
    is built in int64; full-scale data saturates amplitudes and residuals."""
    rng = np.random.default_rng(3)
    codes = rng.integers(0, 2, (64, 7), dtype=np.uint8)
    cfg = ReceiverConfig(adc_bits=16, samples_per_chip=1, averages=1024, gate_len=7,
                         peak_exclude=0, cancel_rounds=2, cancel_snr_q8=0)
    rx = FastReceiver(cfg, codes)
    assert rx._cancel.work_type is np.int64
    x = rng.choice([-(1 << 15), (1 << 15) - 1], cfg.column_samples(7)).astype(np.int32)
    assert rx.column(x).mismatches(reference(cfg, codes, x)) == []
