"""Near-far closed loop against a simulated single-detector plant."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from cdma_lidar.errors import ConfigError
from cdma_lidar.host.nearfar import NearFarController, PowerLimits, apply_cap, next_power

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


def _run(gain: np.ndarray, frames: int, *, peaks: bool = True, cap: float | None = None,
         thermal: float = 1e-8) -> tuple[list[float], list[np.ndarray]]:
    objects = gain > 0
    limits = PowerLimits(max_power=1.0, total_cap=cap)
    ctl = NearFarController(gain.shape, THRESHOLD_DB, limits)
    fractions = []
    for _ in range(frames):
        snr, peak = plant(ctl.power, gain, thermal=thermal)
        fractions.append(float(np.mean(snr[objects] >= THRESHOLD_DB)))
        ctl.update(snr, peak if peaks else None)
    return fractions, ctl.powers


def test_loop_converges_and_stays_over_ten_frames_within_limits():
    gain = near_far_scene()
    cap = 0.5 * gain.shape[0]
    fractions, powers = _run(gain, 10, cap=cap)
    assert fractions[0] < 0.9
    # The block is 60 dB above the far echoes; one update moves at most 40 dB.
    assert min(fractions[2:]) >= 0.95
    for p in powers:
        assert np.all(p <= 1.0)
        assert np.all(p.sum(axis=0) <= cap * (1 + 1e-12))
    # The block was turned down and stays down; the far pixels were not starved.
    assert np.median(powers[-1][:6, 4:9]) < 0.01 * np.median(powers[0][:6, 4:9])


def test_mutually_limited_pixels_do_not_drift_down():
    # The regression: every pixel's floor is made by its column mates, so a reference
    # floor made of the same pixels fell with them and the power fell ~8 dB a frame.
    gain = np.full((24, 12), 1e-3)
    gain[16:] = 0.0
    fractions, powers = _run(gain, 10, thermal=1e-10)
    assert min(fractions) == 1.0
    assert np.median(powers[-1][gain > 0]) >= 0.3 * np.median(powers[0][gain > 0])


def test_without_peaks_the_loop_is_slower_but_never_runs_away():
    gain = near_far_scene()
    fractions, powers = _run(gain, 10, peaks=False)
    # Own SNR_XC only: the mutually limited block comes down 5 dB a frame, so the
    # far pixels appear late, but nothing ever gets worse than it was.
    assert all(b >= max(fractions[:i + 1]) - 0.02 for i, b in enumerate(fractions))
    assert fractions[-1] == 1.0
    assert all(np.all(p >= 1e-4 - 1e-12) for p in powers)


@given(st.floats(min_value=-10, max_value=80), st.floats(min_value=1e-3, max_value=1.0))
def test_band_and_directions(snr: float, p: float):
    new = float(next_power(np.array([[p]]), np.array([[snr]]), THRESHOLD_DB)[0, 0])
    if snr < THRESHOLD_DB + 4.0:
        assert new >= p or new == pytest.approx(1.0)
    elif snr > THRESHOLD_DB + 10.0:
        assert new < p or new == pytest.approx(1e-4)
    else:
        assert new == pytest.approx(p)


def test_caps_and_missing_columns():
    p = np.full((2, 3), 0.9)
    snr = np.array([[0.0, 0.0, np.nan], [0.0, 0.0, 0.0]])
    new = next_power(p, snr, THRESHOLD_DB, PowerLimits(max_power=1.0, total_cap=1.5))
    # Raised pixels give back their increment first, but the column still has to be cut
    # to the cap: 0.9 + 0.9 > 1.5, so the whole column goes to 1.5.
    assert new[:, :2].sum(axis=0) == pytest.approx([1.5, 1.5])
    assert new.max() <= 1.0
    # Column 2: the raised pixel gives back its increment, and 0.9 + 0.9 is still over the
    # cap, so the column (the missing pixel too) is scaled: a hard limit.
    assert new[:, 2] == pytest.approx([0.75, 0.75])
    ok = next_power(np.array([[0.5], [0.5]]), np.array([[0.0], [np.nan]]), THRESHOLD_DB,
                    PowerLimits(max_power=1.0, total_cap=1.2))
    assert ok[:, 0] == pytest.approx([0.7, 0.5])  # the raise is cut to what the cap leaves
    per_pixel = np.array([[0.2, 1.0, 1.0], [1.0, 1.0, 1.0]])
    assert next_power(p, np.zeros((2, 3)), THRESHOLD_DB, PowerLimits(per_pixel))[0, 0] <= 0.2


def test_apply_cap_order():
    prev = np.array([[0.2], [0.2], [0.2]])
    new = np.array([[0.6], [0.6], [0.2]])
    sky, obj = np.array([[True], [False], [False]]), np.array([[False], [True], [False]])
    out = apply_cap(new, 1.0, prev, (sky, obj))
    # Over by 0.4: the sky's increment (0.4) goes first, the object keeps its raise.
    assert out[:, 0] == pytest.approx([0.2, 0.6, 0.2])
    out = apply_cap(new, 0.5, prev, (sky, obj))
    assert out[:, 0] == pytest.approx([0.5 / 3] * 3)   # nothing left to give: all scaled
    assert out.sum() == pytest.approx(0.5)


def test_limits_checked():
    with pytest.raises(ConfigError, match="max_power"):
        PowerLimits(max_power=0.0)
    with pytest.raises(ConfigError, match="total_cap"):
        PowerLimits(total_cap=-1.0)
    with pytest.raises(ConfigError, match="power shape"):
        next_power(np.ones((2, 2)), np.ones((2, 3)), 10.0)
    with pytest.raises(ConfigError, match="band"):
        next_power(np.ones((2, 2)), np.ones((2, 2)), 10.0, band_low_db=5, band_high_db=3)


@given(st.integers(min_value=0, max_value=2**31 - 1), st.floats(min_value=0.5, max_value=8.0))
def test_limits_hold_for_any_frame(seed: int, cap: float):
    """Whatever the SNR map and peaks say (noise, NaN, zeros), the matrix stays legal."""
    rng = np.random.default_rng(seed)
    k, c = 8, 5
    p = rng.uniform(1e-4, 1.0, (k, c))
    p *= np.minimum(1.0, cap / p.sum(axis=0))[None, :]
    snr = rng.uniform(-20, 90, (k, c))
    snr[rng.random((k, c)) < 0.1] = np.nan
    peak = rng.integers(-10**7, 10**7, (k, c))
    peak[rng.random((k, c)) < 0.1] = 0
    limits = PowerLimits(max_power=1.0, total_cap=cap)
    new = next_power(p, snr, THRESHOLD_DB, limits, peak=peak)
    assert np.all(np.isfinite(new))
    assert np.all(new <= 1.0) and np.all(new >= 0.0)
    assert np.all(new.sum(axis=0) <= cap * (1 + 1e-9))
