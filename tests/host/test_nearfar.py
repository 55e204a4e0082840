"""Near-far closed loop against a simulated single-detector plant."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from cdma_lidar.errors import ConfigError
from cdma_lidar.host.nearfar import NearFarController, PowerLimits, next_power

THRESHOLD_DB = 20.0


NS = 8188.0  # samples per symbol: the correlation's processing gain


def plant(power: np.ndarray, gain: np.ndarray, *, thermal: float = 1e-8):
    """(SNR_XC dB, |peak|) of a column-shared detector: every other channel's echo is noise.

    Echo amplitude a = power * gain; the correlation peak is N_s * a and the noise
    variance N_s * (thermal + other channels' a^2 in the same column), so
    SNR_XC = N_s * a_k^2 / (thermal + sum_others a^2). Where there is no echo the
    largest noise sample (about 3 sigma, 10 dB) is what the receiver reports.
    """
    a2 = (power * gain) ** 2
    var = NS * (thermal + a2.sum(axis=0, keepdims=True) - a2)
    peak = np.maximum(NS * power * gain, np.sqrt(10.0 * var))
    return 10 * np.log10(peak**2 / var), peak


def plant_snr_db(power: np.ndarray, gain: np.ndarray) -> np.ndarray:
    return plant(power, gain)[0]


def near_far_scene(k: int = 24, c: int = 12) -> np.ndarray:
    """Echo gains: far objects (gain 1e-3) with a bright near block in some columns."""
    gain = np.full((k, c), 1e-3)
    gain[:6, 4:9] = 1.0          # near white block: 1000x the far echo amplitude
    gain[18:, :] = 0.0           # sky: no object
    return gain


def test_plant_shows_near_far_problem():
    gain = near_far_scene()
    snr = plant_snr_db(np.full(gain.shape, 0.5), gain)
    far_in_block_cols = snr[6:18, 4:9]
    far_elsewhere = snr[6:18, :4]
    assert np.all(far_in_block_cols < THRESHOLD_DB) and np.all(far_elsewhere > THRESHOLD_DB)


def test_loop_reaches_95_percent_within_3_frames_within_limits():
    gain = near_far_scene()
    objects = gain > 0
    limits = PowerLimits(max_power=1.0, total_cap=0.5 * gain.shape[0])
    ctl = NearFarController(gain.shape, THRESHOLD_DB, limits)
    fractions = []
    for _ in range(4):
        snr, peak = plant(ctl.power, gain)
        fractions.append(float(np.mean(snr[objects] >= THRESHOLD_DB)))
        nxt = ctl.update(snr, peak)
        assert np.all(nxt <= 1.0)
        assert np.all(nxt.sum(axis=0) <= limits.total_cap * (1 + 1e-12))
    assert fractions[0] < 0.9
    assert max(fractions[1:4]) >= 0.95
    assert len(ctl.snr_maps) == 4 and len(ctl.powers) == 5


def test_without_peaks_the_loop_stalls_on_mutually_limited_strong_pixels():
    # The SNR-only law cannot tell how far to lower the near block: its pixels are
    # limited by each other, so their excess over the target stays small.
    gain = near_far_scene()
    ctl = NearFarController(gain.shape, THRESHOLD_DB)
    for _ in range(3):
        ctl.update(plant_snr_db(ctl.power, gain))
    snr = plant_snr_db(ctl.power, gain)
    assert np.mean(snr[gain > 0] >= THRESHOLD_DB) < 0.95


@given(st.floats(min_value=-10, max_value=80), st.floats(min_value=1e-3, max_value=1.0))
def test_dead_band_and_directions(snr: float, p: float):
    new = float(next_power(np.array([[p]]), np.array([[snr]]), THRESHOLD_DB)[0, 0])
    if snr < THRESHOLD_DB:
        assert new >= p or new == pytest.approx(1.0)
    elif snr > THRESHOLD_DB + 12.0:
        assert new < p or new == pytest.approx(1e-4)
    else:
        assert new == pytest.approx(p)


def test_caps_and_missing_columns():
    p = np.full((2, 3), 0.9)
    snr = np.array([[0.0, 0.0, np.nan], [0.0, 0.0, 0.0]])
    new = next_power(p, snr, THRESHOLD_DB, PowerLimits(max_power=1.0, total_cap=1.5))
    # Columns 0, 1 were raised to 1.0 + 1.0 and scaled to the per-column cap of 1.5.
    assert new[:, :2].sum(axis=0) == pytest.approx([1.5, 1.5])
    assert new.max() <= 1.0
    # Column 2: the missing pixel keeps 0.9; the raised one gives way first: 1.5 - 0.9.
    assert new[:, 2] == pytest.approx([0.9, 0.6])
    # Not enough to give: the whole column is scaled.
    held = next_power(np.array([[0.9], [0.9]]), np.array([[20.0], [np.nan]]), THRESHOLD_DB,
                      PowerLimits(max_power=1.0, total_cap=1.2))
    assert held[:, 0] == pytest.approx([0.6, 0.6])
    per_pixel = np.array([[0.2, 1.0, 1.0], [1.0, 1.0, 1.0]])
    assert next_power(p, np.zeros((2, 3)), THRESHOLD_DB, PowerLimits(per_pixel))[0, 0] <= 0.2


def test_limits_checked():
    with pytest.raises(ConfigError, match="max_power"):
        PowerLimits(max_power=0.0)
    with pytest.raises(ConfigError, match="total_cap"):
        PowerLimits(total_cap=-1.0)
    with pytest.raises(ConfigError, match="power shape"):
        next_power(np.ones((2, 2)), np.ones((2, 3)), 10.0)
