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
