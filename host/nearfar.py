r"""Near-far closed loop: frame n's SNR_XC heatmap sets frame n+1's power matrix.

Supplementary Note 12 and Fig. 4c-e. In one column every channel shares the single
detector, so a strong near echo raises the correlation noise floor of all the other
channels and drowns the weak far ones. The remedy is per-pixel laser power: lower it
where SNR_XC is far above the threshold, raise it where SNR_XC is below, and so give
the weak pixels a lower noise floor without raising the total power.

Control law (pure function, :func:`next_power`). SNR_XC = peak^2 / sigma^2 and the
peak is proportional to the pixel's power, so scaling a pixel's power by ``g`` moves
its SNR_XC by ``20 log10 g`` dB for a given noise floor. What makes a near-far column
bad is its noise floor: the strong channels' cross-correlation raises sigma for
everybody, and the strong pixels themselves stay far above the threshold (they are
limited only by each other). So a strong pixel is brought down to the peak that
would give the target ``T = threshold + margin`` on a *quiet* noise floor -- the 10th
percentile of the effective floors ``sigma = |peak| / 10^(SNR_XC / 20)`` across the
frame -- which one step takes it to the level of the weak echoes::

    SNR > T + margin      ->  P *= min(1, sigma_quiet * 10^(T / 20) / |peak|)
    SNR < threshold       ->  P *= 10^(min(T - SNR, max_step) / 20)  (up, at most max_step)
    otherwise             ->  P unchanged                              (dead band)

Without peaks (``peak=None``) a strong pixel's own floor stands in for the quiet one,
i.e. ``P *= 10^((T - SNR) / 20)``. Then ``P`` is clipped to ``[min_power,
max_power]`` per pixel, and if the sum exceeds the eye-safety cap the whole matrix is
scaled down to it (the device enforces the same cap). Powers are relative (1.0 = the
device's full channel power).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import ArrayLike, NDArray

from cdma_lidar.errors import out_of_range

__all__ = ["NearFarController", "PowerLimits", "next_power"]

log = logging.getLogger("cdma_lidar." + __name__)


@dataclass(frozen=True)
class PowerLimits:
    """Power bounds (relative units; 1.0 is a channel's full power).

    Attributes:
        max_power: per-pixel maximum, scalar or (K, C).
        min_power: per-pixel minimum (keeps a pixel measurable), scalar.
        total_cap: eye-safety cap on the sum over the matrix; None for K * C * max.
    """

    max_power: float | NDArray = 1.0
    min_power: float = 1e-3
    total_cap: float | None = None

    def __post_init__(self) -> None:
        mx = np.asarray(self.max_power, dtype=np.float64)
        if not (np.all(np.isfinite(mx)) and np.all(mx > 0)):
            raise out_of_range("max_power", "finite and > 0", self.max_power)
        if not (np.isfinite(self.min_power) and 0 < self.min_power <= float(mx.min())):
            raise out_of_range("min_power", f"in (0, {float(mx.min())}]", self.min_power)
        if self.total_cap is not None and not (np.isfinite(self.total_cap)
                                               and self.total_cap > 0):
            raise out_of_range("total_cap", "finite and > 0, or None", self.total_cap)


def next_power(power: ArrayLike, snr_db: ArrayLike, threshold_db: float,
               limits: PowerLimits = PowerLimits(), *, peak: ArrayLike | None = None,
               margin_db: float = 6.0, max_step_db: float = 12.0) -> NDArray[np.float64]:
    """Power matrix for the next frame from this frame's power and SNR_XC (dB), both (K, C).

    ``peak`` (K, C) are the correlation peaks (any consistent unit) measured with
    ``power``. Pixels whose SNR_XC is not finite (column missing) keep their power.
    """
    p = np.asarray(power, dtype=np.float64)
    s = np.asarray(snr_db, dtype=np.float64)
    if p.shape != s.shape:
        raise out_of_range("power shape", f"equal to the SNR map's {s.shape}", p.shape)
    if margin_db < 0:
        raise out_of_range("margin_db", ">= 0 dB", margin_db)
    if max_step_db <= 0:
        raise out_of_range("max_step_db", "> 0 dB", max_step_db)
    target = threshold_db + margin_db
    err = target - s
    finite = np.isfinite(s)
    change = np.zeros_like(p)
    strong = finite & (s > target + margin_db)
    change = np.where(strong, err, change)
    if peak is not None:
        pk = np.abs(np.asarray(peak, dtype=np.float64))
        if pk.shape != s.shape:
            raise out_of_range("peak shape", f"equal to the SNR map's {s.shape}", pk.shape)
        with np.errstate(divide="ignore", invalid="ignore"):
            sigma = pk / 10.0 ** (np.where(finite, s, 0.0) / 20.0)
            usable = finite & (pk > 0) & np.isfinite(sigma)
            if np.any(usable):
                quiet = float(np.percentile(sigma[usable], 10))
                to_target = 20.0 * np.log10(quiet * 10.0 ** (target / 20.0) / pk)
                change = np.where(strong & usable, np.minimum(to_target, 0.0), change)
    change = np.where(finite & (s < threshold_db), np.minimum(err, max_step_db), change)
    new = p * 10.0 ** (change / 20.0)
    new = np.clip(new, limits.min_power, limits.max_power)
    cap = limits.total_cap
    if cap is None:
        cap = float(np.sum(np.broadcast_to(limits.max_power, p.shape)))
    total = float(new.sum())
    if total > cap:
        new *= cap / total
    return new


@dataclass
class NearFarController:
    """Closed loop over frames: feed each frame's SNR_XC map, get the next power matrix.

    Keeps the history of SNR maps and power matrices so a report can show the heatmaps
    before and after.
    """

    shape: tuple[int, int]
    threshold_db: float
    limits: PowerLimits = field(default_factory=PowerLimits)
    margin_db: float = 6.0
    max_step_db: float = 12.0
    initial_power: float = 0.5
    powers: list[NDArray[np.float64]] = field(default_factory=list)
    snr_maps: list[NDArray[np.float64]] = field(default_factory=list)

    def __post_init__(self) -> None:
        if not self.powers:
            start = np.minimum(np.full(self.shape, self.initial_power), self.limits.max_power)
            self.powers.append(start)

    @property
    def power(self) -> NDArray[np.float64]:
        """Power matrix for the frame about to be scanned."""
        return self.powers[-1]

    def update(self, snr_db: ArrayLike, peak: ArrayLike | None = None) -> NDArray[np.float64]:
        """Record the frame just scanned (with :attr:`power`) and return the next matrix."""
        s = np.asarray(snr_db, dtype=np.float64)
        self.snr_maps.append(s.copy())
        nxt = next_power(self.power, s, self.threshold_db, self.limits, peak=peak,
                         margin_db=self.margin_db, max_step_db=self.max_step_db)
        log.info("near-far frame %d: %.1f %% above threshold, power sum %.2f -> %.2f",
                 len(self.snr_maps) - 1, 100.0 * float(np.mean(s >= self.threshold_db)),
                 float(self.power.sum()), float(nxt.sum()))
        self.powers.append(nxt)
        return nxt
