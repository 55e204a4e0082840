"""ADC quantiser: round half up on the fine grid, clip to signed adc_bits."""

from __future__ import annotations

from fractions import Fraction

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from cdma_lidar.errors import ConfigError
from cdma_lidar.firmware_model.adc import adc_limits, quantise


@given(
    x=st.lists(st.integers(-(2**50), 2**50), min_size=1, max_size=20),
    frac_bits=st.integers(0, 40),
    adc_bits=st.integers(8, 16),
)
def test_matches_exact_rational_definition(x, frac_bits, adc_bits):
    got = quantise(np.array(x, dtype=np.int64), frac_bits, adc_bits)
    lo, hi = -(2 ** (adc_bits - 1)), 2 ** (adc_bits - 1) - 1
    for xi, gi in zip(x, got, strict=True):
        v = Fraction(xi, 2**frac_bits) + Fraction(1, 2)
        want = min(max(v.numerator // v.denominator, lo), hi)
        assert int(gi) == want
    assert got.dtype == np.int16


def test_ties_round_up_not_to_even():
    # 0.5, 1.5, -0.5, -1.5 LSB with one fractional bit
    got = quantise(np.array([1, 3, -1, -3]), 1, 12)
    assert got.tolist() == [1, 2, 0, -1]


@pytest.mark.parametrize("adc_bits", [8, 12, 16])
def test_beyond_full_scale_clips(adc_bits):
    lo, hi = adc_limits(adc_bits)
    f = 6
    x = np.array([(hi + 1000) << f, (lo - 1000) << f, 2**62, -(2**62), hi << f, lo << f])
    assert quantise(x, f, adc_bits).tolist() == [hi, lo, hi, lo, hi, lo]


def test_rejects_bad_parameters():
    with pytest.raises(ConfigError, match="adc_bits"):
        quantise(np.zeros(3, dtype=np.int64), 0, 17)
    with pytest.raises(ConfigError, match="frac_bits"):
        quantise(np.zeros(3, dtype=np.int64), -1, 12)
    with pytest.raises(ConfigError, match="analog_fine"):
        quantise(np.zeros(3), 0, 12)


@given(
    x=st.lists(st.floats(-(2.0**54), 2.0**54, allow_nan=False), min_size=1, max_size=20),
    frac_bits=st.integers(0, 40),
    adc_bits=st.integers(8, 16),
)
def test_float_input_is_rint_then_the_integer_quantiser(x, frac_bits, adc_bits):
    """float_input: the value is rounded to the fine grid (rint, ties to even) first;
    the float64 fast path and the int64 path (large frac_bits) give the same codes."""
    fine = np.array(x, dtype=np.float64)
    want = quantise(np.rint(fine).astype(np.int64), frac_bits, adc_bits)
    got = quantise(fine, frac_bits, adc_bits, float_input=True)
    assert got.dtype == np.int16
    np.testing.assert_array_equal(got, want)
    kept = fine.copy()
    assert np.array_equal(quantise(fine, frac_bits, adc_bits, float_input=True), want)
    assert np.array_equal(fine, kept)  # not overwritten unless asked


@pytest.mark.parametrize("adc_bits", [8, 12, 16])
@pytest.mark.parametrize("frac_bits", [0, 1, 8, 36, 37, 40])
def test_float_input_ties_edges_and_infinities(adc_bits, frac_bits):
    lo, hi = adc_limits(adc_bits)
    one = 2.0**frac_bits
    half = (np.arange(-40, 40) + 0.5) * one  # exactly between two codes
    top = (hi + 1) * one
    fine = np.concatenate([
        half, half - 0.5, half + 0.5, half - 1e-9 * one, [0.5, 1.5, 2.5, -0.5, -1.5],
        [top - one / 2 - 1, top - one / 2, -top - one / 2 - 1, -top - one / 2, 2.0**53 - 1,
         2.0**53, 2.0**60, -(2.0**60), np.inf, -np.inf],
    ])
    want = quantise(np.clip(np.rint(fine), -(2.0**62), 2.0**62).astype(np.int64), frac_bits,
                    adc_bits)
    got = quantise(fine.copy(), frac_bits, adc_bits, float_input=True, overwrite_input=True)
    np.testing.assert_array_equal(got, want)
    assert got[-2:].tolist() == [hi, lo]


def test_float_input_overwrites_only_when_asked_and_accepts_float32():
    fine = np.array([0.4, 300.6, -2.5e9], dtype=np.float64)
    buf = fine.copy()
    got = quantise(buf, 8, 12, float_input=True, overwrite_input=True)
    assert got.tolist() == [0, 1, -2048]
    assert not np.array_equal(buf, fine)  # used as the work buffer
    f32 = fine.astype(np.float32)
    assert quantise(f32, 8, 12, float_input=True).tolist() == [0, 1, -2048]
    with pytest.raises(ConfigError, match="analog_fine"):
        quantise(np.zeros(3, dtype=np.int64), 8, 12, float_input=True)
