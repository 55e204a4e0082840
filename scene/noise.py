"""Receiver noise: the link budget's, per column and per calibration shot.

::

    e : thermal, dark, shot, ambient, ASE of the link budget, per column   (white Gaussian)

The signal's own shot noise and the ASE beat depend on what a column receives; the other
sources do not (:meth:`cdma_lidar.scene.linkbudget.LinkBudget.noise_variance_v2`). A scene
may fix the noise instead (``noise_rms_v``, ``snr_db``: :func:`fixed_noise_v`). Speckle
fades each pixel's received power (:func:`speckle_factors`). :class:`Noise` keeps the link
budget's coefficients per samples-per-chip (its own cache).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from numpy.typing import NDArray

from cdma_lidar.scene.codebook import RenderSettings
from cdma_lidar.scene.linkbudget import LinkBudget
from cdma_lidar.scene.model import InstrumentSpec

__all__ = ["STREAM_CALIBRATE", "STREAM_SCAN", "Noise", "fixed_noise_v", "speckle_factors"]

#: Noise streams of a scene seed: scan columns, calibration shots, the speckle pattern.
STREAM_SCAN = 0
STREAM_CALIBRATE = 1
_STREAM_SPECKLE = 2


def speckle_factors(cells: float, shape: tuple[int, ...], seed: int) -> NDArray[np.float64]:
    """Per-pixel speckle power fading: Gamma(cells, 1/cells) (mean 1, variance 1/cells).

    Fully developed speckle integrated over ``cells`` correlation cells of the aperture;
    fixed for a static scene (seeded by the noise seed only, not the frame), so averaging
    frames does not remove it.
    """
    rng = np.random.default_rng([seed, _STREAM_SPECKLE])
    return rng.gamma(cells, 1.0 / cells, size=shape)


def fixed_noise_v(spec: InstrumentSpec, amplitude_v: NDArray[np.float64],
                  lit: NDArray[np.bool_], calibration_amplitude_v: NDArray[np.float64],
                  unit_signal_power: float) -> float | None:
    """The noise rms (V) a scene fixes (``noise_rms_v``; ``snr_db`` against the median lit
    pixel's signal power, or the calibration echo's where nothing is lit), None: physical.
    ``amplitude_v`` (K, C) every pixel's echo amplitude at the default power."""
    if spec.noise_rms_v is not None:
        return float(spec.noise_rms_v)
    if spec.snr_db is None:
        return None
    if not np.any(lit):
        mean_a2 = float(np.mean(calibration_amplitude_v ** 2))
    else:
        mean_a2 = float(np.median(amplitude_v[lit] ** 2))
    return float(np.sqrt(mean_a2 * unit_signal_power / 10 ** (spec.snr_db / 10)))


class Noise:
    """Per-sample noise rms (V) of columns and calibration shots.

    ``budget``: the pixels' link budget; ``default_power_w`` (K, C) W; ``calibration_rx_w``
    the received power per watt of one channel's calibration echo; ``fixed_v`` a noise
    the scene fixes (:func:`fixed_noise_v`, None: the link budget's).
    """

    def __init__(self, budget: LinkBudget, default_power_w: NDArray[np.float64],
                 calibration_rx_per_w: float, fixed_v: float | None) -> None:
        self.budget = budget
        self.default_power_w = default_power_w
        self.channels, self.columns = default_power_w.shape
        self.calibration_rx_per_w = calibration_rx_per_w
        self.fixed_v = fixed_v
        self._coefficients: dict[int, dict[str, float]] = {}

    def rms_columns_v(self, cfg: RenderSettings | None = None,
                            power_w: NDArray[np.float64] | None = None) -> NDArray[np.float64]:
        """(C,) per-sample noise rms (V) of every column at laser power ``power_w`` (K, C)."""
        cfg = cfg or RenderSettings.from_spec(self.spec)
        if self.fixed_v is not None:
            return np.full(self.columns, self.fixed_v)
        p = self.default_power_w if power_w is None else np.asarray(power_w, dtype=np.float64)
        return np.sqrt(self.budget.noise_variance_v2(p, self.budget.rx_per_w,
                                                     cfg.samples_per_chip))

    def rms_v_at(self, column: int, cfg: RenderSettings,
                       power_w: NDArray[np.float64] | None = None,
                       calibration: bool = False) -> float:
        """Per-sample noise rms (V) of one column (or calibration shot) at power ``power_w`` (K,).

        The signal's own shot noise and the ASE beat depend on what the column receives;
        the other sources do not. A fixed ``noise_rms_v`` or ``snr_db`` replaces all.
        """
        if self.fixed_v is not None:
            return self.fixed_v
        p = self.default_power_w[:, column] if power_w is None else np.asarray(power_w)
        if calibration:
            rx = np.full(self.channels, self.calibration_rx_per_w)
        else:
            rx = self.budget.rx_per_w[:, column]
        return float(np.sqrt(self.budget.noise_variance_v2(p, rx, cfg.samples_per_chip,
                                                           self.coefficients(cfg))))

    def coefficients(self, cfg: RenderSettings) -> dict[str, float]:
        coef = self._coefficients.get(cfg.samples_per_chip)
        if coef is None:
            coef = self._coefficients[cfg.samples_per_chip] = self.budget.coefficients(
                cfg.samples_per_chip)
        return coef

    def rms_items(self, cfg: RenderSettings,
                         items: Sequence[tuple[int, NDArray[np.float64] | None]],
                         calibration: bool) -> NDArray[np.float64]:
        """(B,) :meth:`rms_v_at` of each (column, power), for the batch at once: the
        same values (each column's sums over its channels run along one contiguous row,
        as a column's alone does; tests/scene/test_noise_blocks.py)."""
        if self.fixed_v is not None:
            return np.full(len(items), self.fixed_v)
        p = np.stack([self.default_power_w[:, col] if pw is None else np.asarray(pw)
                      for col, pw in items])
        if calibration:
            rx = np.full(p.shape, self.calibration_rx_per_w)
        else:
            rx = np.ascontiguousarray(self.budget.rx_per_w[:, [col for col, _ in items]].T)
        return np.sqrt(self.budget.noise_variance_v2(p, rx, cfg.samples_per_chip,
                                                     self.coefficients(cfg), axis=1))

