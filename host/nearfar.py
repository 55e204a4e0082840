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
everybody, the strong pixels included, so their own SNR_XC does not show how strong
they are. Their *reference* SNR does: the peak against the noise floor of a typical
column with objects in it, ``sigma_ref``. Each pixel's effective floor is
``|peak| / 10^(SNR_XC/20)``; a column's floor is the median over its channels, and
``sigma_ref`` is the 25th percentile of the floors of the columns where something was
detected (above the threshold) -- columns that only have sky in them show the bare
thermal floor, which no object column can reach. With the target
``T = threshold + margin``::

    SNR_ref = 20 log10(|peak| / sigma_ref)
    strong: SNR >= threshold and SNR_ref > T + margin
            ->  P *= 10^((T + margin/2 - SNR_ref) / 20)   (down into the dead band)
    weak:   SNR < threshold and SNR_ref < T
            ->  P *= 10^(min(T - SNR, max_step) / 20)     (up, at most max_step)
    otherwise  ->  P unchanged

A pixel below the threshold whose peak is nevertheless large against the reference
floor is not weak: it is drowned by its column (its "peak" is interference) or was
just brought down from strong; raising it would only feed the interference back.

One step takes a strong pixel to the level of the echoes in ordinary columns. Without
peaks (``peak=None``) the pixel's own floor stands in for the reference one. Then ``P`` is
clipped to ``[min_power, max_power]`` per pixel. A column's channels are emitted at
once, so a column whose sum exceeds the eye-safety cap is brought down to it; the
raised pixels give way first (they may be empty sky that no power will light up),
then, if that is not enough, the whole column. The device enforces the same cap.
Powers are in one consistent unit (W on the device).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import ArrayLike, NDArray

from cdma_lidar.errors import out_of_range

__all__ = ["NearFarController", "PowerLimits", "next_power"]

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class PowerLimits:
    """Power bounds (one unit throughout, W on the device).

    Attributes:
        max_power: per-pixel maximum, scalar or (K, C).
        min_power: per-pixel minimum (keeps a pixel measurable), scalar; None for
            1e-4 of the smallest maximum.
        total_cap: eye-safety cap on each column's sum over channels (all channels of a
            column are emitted together); None for no cap beyond the per-pixel maxima.
    """

    max_power: float | NDArray = 1.0
    min_power: float | None = None
    total_cap: float | None = None

    def __post_init__(self) -> None:
        mx = np.asarray(self.max_power, dtype=np.float64)
        if not (np.all(np.isfinite(mx)) and np.all(mx > 0)):
            raise out_of_range("max_power", "finite and > 0", self.max_power)
        if self.min_power is None:
            object.__setattr__(self, "min_power", 1e-4 * float(mx.min()))
        elif not (np.isfinite(self.min_power) and 0 < self.min_power <= float(mx.min())):
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
    finite = np.isfinite(s)
    s_quiet = np.where(finite, s, -np.inf)
    if peak is not None:
        pk = np.abs(np.asarray(peak, dtype=np.float64))
        if pk.shape != s.shape:
            raise out_of_range("peak shape", f"equal to the SNR map's {s.shape}", pk.shape)
        with np.errstate(divide="ignore", invalid="ignore"):
            sigma = pk / 10.0 ** (np.where(finite, s, 0.0) / 20.0)
            usable = finite & (pk > 0) & np.isfinite(sigma)
            detected = np.any(usable & (s >= threshold_db), axis=0)
            if np.any(detected):
                col_floor = np.nanmedian(np.where(usable, sigma, np.nan)[:, detected], axis=0)
                ref = float(np.percentile(col_floor, 25))
                s_quiet = np.where(usable, 20.0 * np.log10(pk / ref), s_quiet)
    change = np.zeros_like(p)
    detected = finite & (s >= threshold_db)
    strong = detected & (s_quiet > target + margin_db)
    weak = finite & (s < threshold_db) & (s_quiet < target)
    change = np.where(strong, target + margin_db / 2 - s_quiet, change)
    change = np.where(weak, np.minimum(target - s, max_step_db), change)
    new = np.clip(p * 10.0 ** (change / 20.0), limits.min_power, limits.max_power)
    if limits.total_cap is not None:
        new = _apply_cap(new, change > 0, limits.total_cap)
    return new


def _apply_cap(power: NDArray[np.float64], raised: NDArray[np.bool_],
               cap: float) -> NDArray[np.float64]:
    """Scale each column to at most ``cap``: raised pixels first, then the whole column."""
    up = np.where(raised, power, 0.0).sum(axis=0)
    rest = power.sum(axis=0) - up
    with np.errstate(divide="ignore", invalid="ignore"):
        f_up = np.where(up > 0, np.clip((cap - rest) / up, 0.0, 1.0), 1.0)
    out = np.where(raised, power * f_up[None, :], power)
    total = out.sum(axis=0)
    with np.errstate(divide="ignore", invalid="ignore"):
        f_all = np.where(total > cap, cap / total, 1.0)
    return out * f_all[None, :]


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
        log.info("near-far frame %d: %.1f %% above threshold, power sum %.3g -> %.3g",
                 len(self.snr_maps) - 1, 100.0 * float(np.mean(s >= self.threshold_db)),
                 float(self.power.sum()), float(nxt.sum()))
        self.powers.append(nxt)
        return nxt
