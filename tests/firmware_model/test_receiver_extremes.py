"""Numerical extremes of the receive chain (issue 3, section 4), each its own test.

Every case checks the fast path against the reference (or, where the reference
would be too slow, against an independent int64 evaluation of the definition)
and against the value the definition gives by hand.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from cdma_lidar.firmware_model.adc import adc_limits, quantise
from cdma_lidar.firmware_model.gold import gold_family
from cdma_lidar.firmware_model.lfsr import mseq
from cdma_lidar.firmware_model.pairs import preferred_pairs
from cdma_lidar.firmware_model.receiver import (
    FastReceiver,
    ReceiverConfig,
    correlator_methods,
    fast,
    fast_from_accumulators,
    reference,
)

RNG = np.random.default_rng(20261121)


def _bip(bits):
    return 1 - 2 * np.asarray(bits, dtype=np.int64)


def _raw_definition(codes, s, d, lags):
    """raw_k[l] = sum_i ref_k[i] d[(i + l) mod NS] in int64, straight from the definition."""
    ref = np.repeat(_bip(codes), s, axis=1)
    return np.array([[int(np.dot(r, np.roll(d, -lag))) for lag in lags] for r in ref])


def _both(cfg, codes, x):
    want = reference(cfg, codes, x)
    for method in correlator_methods()[1:]:
        got = FastReceiver(cfg, codes, method=method).column(x)
        assert got.mismatches(want) == [], method
    return want


@pytest.mark.parametrize("b", [8, 16])
@pytest.mark.parametrize("end", ["min", "max"])
def test_full_scale_codes_of_both_signs(b, end):
    lo, hi = adc_limits(b)
    v = lo if end == "min" else hi
    codes = RNG.integers(0, 2, (3, 13))
    s, r, n_uid = 3, 4, 2
    cfg = ReceiverConfig(adc_bits=b, samples_per_chip=s, averages=r, uid_bits=n_uid, uid=0,
                         gate_start=30, gate_len=20)
    x = np.full(cfg.column_samples(13), v, dtype=np.int16)
    out = _both(cfg, codes, x)
    # constant input: every lag gives v * R * n * S * sum(bip)
    want = v * r * n_uid * s * _bip(codes).sum(axis=1)
    assert (out.corr == want[:, None]).all()


def test_analog_beyond_full_scale_clips():
    b, f = 10, 8
    lo, hi = adc_limits(b)
    codes = RNG.integers(0, 2, (2, 11))
    s = 2
    cfg = ReceiverConfig(adc_bits=b, samples_per_chip=s, averages=3, gate_len=22)
    ref = np.repeat(_bip(codes[0]), s)
    # an echo 4x beyond full scale, delayed by 9 samples, on the fine grid
    analog = np.tile(np.roll(ref, 9) * (4 * hi << f), 3)
    x = quantise(analog, f, b)
    assert set(np.unique(x).tolist()) == {lo, hi}
    out = _both(cfg, codes, x)
    assert out.peak_lag[0] == 9
    assert out.peak[0] == 3 * (hi * ref.clip(0).sum() - lo * (-ref).clip(0).sum())


def test_maximum_averages_with_a_long_code():
    # R = 1024 at degree 15 (S = 1): 33.5 M samples through the fast path, full scale.
    n, r = 2**15 - 1, 1024
    codes = np.stack([mseq((15, 1)), mseq((15, 4))])
    lo, _ = adc_limits(16)
    cfg = ReceiverConfig(adc_bits=16, samples_per_chip=1, averages=r, gate_start=n - 2,
                         gate_len=5, out_bits=32, out_shift=12)  # 2^25 >> 12, sumsq fits int64
    x = np.full(cfg.column_samples(n), lo, dtype=np.int16)
    out = fast(cfg, codes, x)
    # an m-sequence has one more 1 than 0s: sum(bip) = -1, raw = 2^25 at every lag
    assert (out.corr == (lo * r * -1) >> 12).all()


@pytest.mark.parametrize("method", ["matmul", "fft", "direct"])
def test_largest_degree_at_maximum_averages_and_width(method):
    # Degree 20 (N = 2^20 - 1), R = 1024 and 16-bit full-scale data in the accumulators,
    # gate wrapping past the end; float limit lowered so the operands must be split.
    n, r, b = 2**20 - 1, 1024, 16
    lo, hi = adc_limits(b)
    codes = mseq((20, 3))[None, :]
    cfg = ReceiverConfig(adc_bits=b, samples_per_chip=1, averages=r, gate_start=n - 2,
                         gate_len=4, out_bits=32, out_shift=16, rounding="convergent")
    # a full-scale echo at lag n - 1 (inside the wrapping gate) with 5% of the chips flipped
    echo = np.roll(_bip(codes[0]), n - 1) * np.where(RNG.random(n) < 0.05, -1, 1)
    acc = np.where(echo > 0, hi * r, lo * r).astype(np.int64)[None, None, :]
    lags = [(n - 3 + m) % n for m in range(6)]
    raw = _raw_definition(codes, 1, acc[0, 0], lags)
    assert np.abs(raw).max() > 2**44  # the operands really are wide
    for fb in (53, 50 if method == "fft" else 28):
        out = FastReceiver(cfg, codes, method=method, float_bits=fb).from_accumulators(acc)[0]
        want = np.array([round(v / 2**16) for v in raw[0].tolist()])  # exact: |v| < 2^53
        assert out.corr[0].tolist() == want[1:5].tolist()
        assert out.peak_lag[0] == n - 1
        at = lags.index(int(out.peak_lag[0]))
        assert out.neighbours[0].tolist() == [want[at - 1], want[at + 1]]


def test_gate_wrapping_past_the_end_of_the_period():
    codes = RNG.integers(0, 2, (2, 17))
    s = 3
    ns = 17 * s
    cfg = ReceiverConfig(samples_per_chip=s, averages=2, gate_start=ns - 4, gate_len=10,
                         peak_exclude=1)
    echo = np.roll(np.repeat(_bip(codes[1]), s), 2) * 30  # delay 2: after the wrap
    x = np.tile(echo, 2) + RNG.integers(-2, 3, 2 * ns)
    out = _both(cfg, codes, x)
    assert out.peak_lag[1] == 2
    lags = [(ns - 4 + j) % ns for j in range(10)]
    d = x.reshape(2, ns).sum(axis=0)
    assert out.corr.tolist() == _raw_definition(codes, s, d, lags).tolist()


def test_one_lag_gate():
    codes = RNG.integers(0, 2, (2, 9))
    cfg = ReceiverConfig(samples_per_chip=2, averages=1, gate_start=5, gate_len=1)
    x = RNG.integers(-100, 100, 18)
    out = _both(cfg, codes, x)
    assert out.peak_lag.tolist() == [5, 5]
    assert out.noise_count.tolist() == [0, 0]
    snr = out.snr_db()
    assert np.isfinite(snr[out.peak != 0]).all()
    assert np.allclose(snr[out.peak != 0], 10 * np.log10(12.0 * out.peak[out.peak != 0] ** 2))


def test_all_zero_input():
    codes = RNG.integers(0, 2, (3, 7))
    cfg = ReceiverConfig(samples_per_chip=2, averages=3, gate_start=3, gate_len=9, peaks=2,
                         peak_exclude=2)
    out = _both(cfg, codes, np.zeros(cfg.column_samples(7), dtype=np.int16))
    assert not out.corr.any()
    assert out.peak_lag.tolist() == [3, 3, 3]  # ties on |0|: the lowest j wins
    assert out.extra_lag.tolist() == [[6], [6], [6]]
    assert out.noise_sum.tolist() == [0, 0, 0] and out.noise_sumsq.tolist() == [0, 0, 0]
    assert out.uid_signs.tolist() == [[0], [0], [0]] and not out.uid_match.any()
    snr = out.snr_db()
    assert not np.isnan(snr).any() and (snr == -math.inf).all()


def test_clean_peak_over_zero_noise_is_the_documented_cap():
    # a code whose circular autocorrelation (S = 1) is zero off the peak: [0, 0, 0, 1]
    codes = np.array([[0, 0, 0, 1]])
    cfg = ReceiverConfig(samples_per_chip=1, averages=1, gate_len=4, peak_exclude=0)
    x = np.roll(_bip(codes[0]), 1) * 7
    out = _both(cfg, codes, x)
    assert out.peak_lag[0] == 1 and out.peak[0] == 28
    assert (out.noise_count[0], out.noise_sum[0], out.noise_sumsq[0]) == (3, 0, 0)
    assert out.snr_db()[0] == pytest.approx(10 * math.log10(12 * 28**2))


@pytest.mark.parametrize("where", ["first", "last"])
def test_peak_on_the_first_or_last_lag_of_the_gate(where):
    codes = gold_family(*preferred_pairs(5)[0])[:3]
    s = 2
    ns = 31 * s
    cfg = ReceiverConfig(samples_per_chip=s, averages=1, gate_start=20, gate_len=12)
    delay = 20 if where == "first" else 31
    x = np.roll(np.repeat(_bip(codes[2]), s), delay) * 40
    out = _both(cfg, codes, x)
    assert out.peak_lag[2] == delay
    full = _raw_definition(codes[2:], s, x, range(ns))[0]
    assert out.neighbours[2].tolist() == [full[delay - 1], full[(delay + 1) % ns]]
    j = delay - 20
    inside = out.corr[2, j - 1] if where == "last" else out.corr[2, j + 1]
    assert inside in out.neighbours[2]


@pytest.mark.parametrize("gate_start", [0, 50])
def test_two_equal_peaks_tie_to_the_lowest_gate_index(gate_start):
    codes = mseq((5, 2))[None, :]  # two-valued autocorrelation keeps both echoes on top
    s = 3
    ns = 93
    ref = np.repeat(_bip(codes[0]), s)
    # two equal echoes; circular autocorrelation is symmetric, so both peaks are equal
    d1, d2 = 10, 55
    x = (np.roll(ref, d1) + np.roll(ref, d2)) * 20
    cfg = ReceiverConfig(samples_per_chip=s, averages=1, gate_start=gate_start, gate_len=ns,
                         peak_exclude=2, peaks=2)
    out = _both(cfg, codes, x)
    lags = [(gate_start + j) % ns for j in range(ns)]
    assert out.corr[0, lags.index(d1)] == out.corr[0, lags.index(d2)]
    first = d1 if lags.index(d1) < lags.index(d2) else d2
    assert out.peak_lag[0] == first  # gate_start=50 puts lag 55 before lag 10
    assert out.extra_lag[0, 0] == (d2 if first == d1 else d1)


@pytest.mark.parametrize("rounding", ["truncate", "half_up", "convergent"])
def test_narrow_output_width_saturates(rounding):
    codes = RNG.integers(0, 2, (2, 15))
    cfg = ReceiverConfig(adc_bits=12, samples_per_chip=2, averages=4, gate_len=30,
                         out_bits=8, out_shift=3, rounding=rounding, peaks=2, peak_exclude=0)
    ref = np.repeat(_bip(codes[0]), 2)
    x = np.tile(np.roll(ref, 4) * 1500, 4)
    out = _both(cfg, codes, x)
    assert out.corr.max() == 127 or out.corr.min() == -128
    assert out.corr.min() >= -128 and out.corr.max() <= 127
    # saturated lags tie on |out|: the peak is the lowest j among them
    mag = np.abs(out.corr[0])
    assert out.peak_lag[0] == int(np.argmax(mag))


def test_from_accumulators_checks_its_input():
    cfg = ReceiverConfig(samples_per_chip=1, averages=2, gate_len=3)
    codes = np.zeros((1, 3), dtype=np.uint8)
    with pytest.raises(ValueError, match="acc"):
        fast_from_accumulators(cfg, codes, np.full((1, 1, 3), 2 * 2048))
    with pytest.raises(ValueError, match="acc"):
        fast_from_accumulators(cfg, codes, np.zeros((1, 2, 3), dtype=np.int64))
