r"""Combining the frames of a scan: ``--combine {last,mean,median}``.

The frames of one scan see the same scene, so their ranges can be averaged pixel by
pixel. A pixel counts as valid in the combination when it was valid (flag 0) in
more than half of the frames: a noise peak that got through in one frame does not.

* ``last``: the last frame only (what a single-frame scan gives).
* ``mean``: the inverse-variance (SNR-weighted) mean of the valid ranges. By eq. 27
  the range variance of a frame is proportional to ``1 / SNR_XC``, so the weights are
  ``10^(SNR_XC/10)``; frames at lower power (early near-far frames) count less. Its
  SNR_XC is that of the sum, ``10 log10(sum 10^(SNR/10))``: N equal frames gain
  ``10 log10 N`` dB, and the random part of the error falls as ``1/sqrt(N)``.
* ``median``: the median of the valid ranges (for N >= 3 it ignores a frame that
  locked on a wrong peak); about 1.25 times the spread of the mean for Gaussian noise.

What averaging cannot remove: the *deterministic* part of a pixel's error. The
cross-talk of the other channels' codes in the same column, the sub-sample
interpolation bias and the calibration offset are the same in every frame (same
codes, same lags), so they survive any number of frames. ``bench/bench_host.py``
measures both parts against N on flat-wall (docs/host.md has the table).
"""

from __future__ import annotations

import logging
from collections.abc import Sequence

import numpy as np
from numpy.typing import NDArray

from cdma_lidar.errors import out_of_range
from cdma_lidar.host.ranging import FLAG_REJECTED, RangeImage
from cdma_lidar.host.settings import COMBINE_MODES

__all__ = ["COMBINE_MODES", "combine", "nan_median"]

log = logging.getLogger(__name__)



def nan_median(stack: NDArray[np.float64]) -> NDArray[np.float64]:
    """Median over axis 0 ignoring NaN; NaN where a pixel has no finite value (no warning)."""
    some = np.isfinite(stack).any(axis=0)
    filled = np.where(some[None], stack, 0.0)
    return np.where(some, np.nanmedian(filled, axis=0), np.nan)


def combine(images: Sequence[RangeImage], mode: str = "last") -> RangeImage:
    """One RangeImage from the frames ``images`` (all (K, C), same configuration)."""
    if mode not in COMBINE_MODES:
        raise out_of_range("combine", f"one of {COMBINE_MODES}", mode)
    if not images:
        raise out_of_range("images", "at least one frame", 0)
    last = images[-1]
    if mode == "last" or len(images) == 1:
        return last
    shape = last.range_m.shape
    if any(im.range_m.shape != shape for im in images):
        raise out_of_range("frame shape", f"all {shape}", [im.range_m.shape for im in images])
    r = np.stack([im.range_m for im in images])
    s = np.stack([im.snr_xc_db for im in images])
    ok = np.stack([im.flags == 0 for im in images]) & np.isfinite(r)
    n = len(images)
    keep = ok.sum(axis=0) * 2 > n
    with np.errstate(invalid="ignore", over="ignore", divide="ignore"):
        w = np.where(ok, 10.0 ** (np.where(ok, s, 0.0) / 10.0), 0.0)
        if mode == "mean":
            rng = (np.where(ok, r, 0.0) * w).sum(axis=0) / w.sum(axis=0)
            snr = 10.0 * np.log10(w.sum(axis=0))
        else:
            rng = nan_median(np.where(ok, r, np.nan))
            snr = nan_median(np.where(ok, s, np.nan))
    rng = np.where(keep, rng, np.nan)
    snr = np.where(keep, snr, last.snr_xc_db)
    peak = np.where(keep, np.rint(np.mean(np.abs(np.stack([im.peak for im in images])),
                                          axis=0)).astype(np.int64), last.peak)
    flags = np.where(keep, 0, last.flags | FLAG_REJECTED).astype(last.flags.dtype)
    log.info("combined %d frames (%s): %d pixels valid in more than half of them", n, mode,
             int(keep.sum()))
    return RangeImage(range_m=rng, lag=last.lag, snr_xc_db=snr, peak=peak, flags=flags,
                      foreign=last.foreign, config=last.config)
