"""SNR_XC (eq. 44) from the integer noise-floor statistics."""

from __future__ import annotations

import math
from fractions import Fraction

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from cdma_lidar.errors import ConfigError
from cdma_lidar.firmware_model.snr import snr_xc_db


@given(
    noise=st.lists(st.integers(-(2**31), 2**31 - 1), min_size=0, max_size=40),
    peak=st.integers(-(2**31), 2**31 - 1),
)
def test_matches_peak_power_over_population_variance(noise, peak):
    c, s, ss = len(noise), sum(noise), sum(v * v for v in noise)
    got = float(snr_xc_db(peak, c, s, ss))
    assert not math.isnan(got)
    if peak == 0:
        assert got == -math.inf
        return
    var = Fraction(c * ss - s * s, c * c) if c else Fraction(0)
    var = max(var, Fraction(1, 12))
    want = 10 * math.log10(Fraction(peak * peak) / var)
    assert got == pytest.approx(want, rel=1e-12, abs=1e-9)


def test_zero_noise_floor_gives_the_cap_and_zero_peak_gives_minus_inf():
    got = snr_xc_db([100, -100, 0, 5], [10, 0, 10, 4], [30, 0, 0, 8], [90, 0, 0, 16])
    cap = 10 * math.log10(12 * 100**2)
    assert got[0] == pytest.approx(cap)  # constant noise floor: variance 0
    assert got[1] == pytest.approx(cap)  # no noise lags at all
    assert got[2] == -math.inf
    assert got[3] == pytest.approx(10 * math.log10(12 * 25))
    assert got.dtype == np.float64 and got.shape == (4,)


def test_sub_lsb_variance_is_floored_and_large_variance_is_not():
    # values 0,0,0,1: variance 3/16 > 1/12 -> not floored; 0*11,1: 11/144 < 1/12 -> floored
    assert float(snr_xc_db(4, 4, 1, 1)) == pytest.approx(10 * math.log10(16 / (3 / 16)))
    assert float(snr_xc_db(4, 12, 1, 1)) == pytest.approx(10 * math.log10(16 * 12))


def test_huge_integers_stay_exact():
    # 2^20 noise lags of +-2^21 (sumsq = 2^62 fits int64, count * sumsq = 2^82 does not)
    c = 2**20
    got = snr_xc_db(np.int64(2**30), np.int64(c), np.int64(2), np.int64(2**62))
    var = Fraction(c * 2**62 - 4, c * c)
    assert float(got) == pytest.approx(10 * math.log10(Fraction(2**60) / var), rel=1e-13)


def test_broadcasting_and_impossible_statistics():
    assert snr_xc_db(np.array([[1, 2]]), 3, 0, 3).shape == (1, 2)
    with pytest.raises(ConfigError, match="noise_sumsq"):
        snr_xc_db(5, 2, 10, 1)  # sumsq < sum^2 / count
    with pytest.raises(ConfigError, match="noise_count"):
        snr_xc_db(5, -1, 0, 0)
    with pytest.raises(ConfigError, match="peak"):
        snr_xc_db(5.5, 1, 0, 0)
