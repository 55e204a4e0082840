"""SNR_XC (paper eq. 44) from the receive chain's integer noise-floor statistics.

``SNR_XC = peak^2 / sigma^2`` in dB, where sigma^2 is the population variance of
the noise floor (gate lags minus the peaks' +-W and the ghost windows)::

    var_num = count * sumsq - sum^2          exact, Python integers
    sigma^2 = max(var_num / count^2, 1/12)   floored at the output's quantisation noise
    SNR_XC  = 10 log10(peak^2 / sigma^2)     dB

Zero-noise rule: the 1/12 LSB^2 floor (also used when count == 0) makes a clean
peak give the finite cap ``10 log10(12 peak^2)`` and a zero peak give ``-inf``;
the result is never NaN. The floor comparison ``12 var_num < count^2`` is made
in integers. This is the only floating-point code in ``firmware_model``: it runs
off-FPGA (host, virtual device), never in the data path. See docs/firmware.md,
section 7.
"""

from __future__ import annotations

import logging
import math

import numpy as np
from numpy.typing import ArrayLike, NDArray

from cdma_lidar.errors import out_of_range

__all__ = ["snr_q8", "snr_xc_db"]

log = logging.getLogger(__name__)


def snr_xc_db(
    peak: ArrayLike, noise_count: ArrayLike, noise_sum: ArrayLike, noise_sumsq: ArrayLike
) -> NDArray[np.float64]:
    """Return SNR_XC in dB for each channel (float64 array, broadcast shape of the inputs).

    Parameters are integers in output LSBs, as produced by the receive chain:
    ``peak`` (signed peak value), ``noise_count`` (>= 0), ``noise_sum``,
    ``noise_sumsq`` (>= 0). Results are ``-inf`` for a zero peak, finite otherwise.
    """
    arrays = [np.asarray(a) for a in (peak, noise_count, noise_sum, noise_sumsq)]
    for name, a in zip(("peak", "noise_count", "noise_sum", "noise_sumsq"), arrays, strict=True):
        if a.dtype.kind not in "iu" and not (a.dtype == object or a.size == 0):
            raise out_of_range(name, "integers", f"dtype {a.dtype}")
    p, c, s, ss = np.broadcast_arrays(*arrays)
    out = np.empty(p.shape, dtype=np.float64)
    flat = out.reshape(-1)
    for idx, (pi, ci, si, ssi) in enumerate(
        zip(p.ravel().tolist(), c.ravel().tolist(), s.ravel().tolist(), ss.ravel().tolist(),
            strict=True)
    ):
        flat[idx] = _one(int(pi), int(ci), int(si), int(ssi))
    return out


def _one(peak: int, count: int, total: int, sumsq: int) -> float:
    if count < 0:
        raise out_of_range("noise_count", ">= 0", count)
    if sumsq < 0:
        raise out_of_range("noise_sumsq", ">= 0", sumsq)
    var_num = count * sumsq - total * total
    if var_num < 0:  # impossible for real statistics (Cauchy-Schwarz)
        raise out_of_range("noise_sumsq", f">= noise_sum^2 / noise_count = {total}^2/{count}",
                           sumsq)
    if peak == 0:
        return -math.inf
    p2 = peak * peak
    if count == 0 or 12 * var_num < count * count:
        return 10.0 * math.log10(12 * p2)
    # 10 log10(p2 * count^2 / var_num), each factor an exact integer (log10 takes big ints)
    return 10.0 * (math.log10(p2 * count * count) - math.log10(var_num))


def snr_q8(db: float) -> int:
    """The SNR_XC threshold ``db`` (dB) as the receive chain's cancellation register: the
    power ratio 10^(db/10) in Q8, rounded (``ReceiverConfig.cancel_snr_q8``; 16 dB -> 10192)."""
    if not math.isfinite(db) or not 0.0 <= db <= 72.0:
        raise out_of_range("cancel threshold (dB)", "0..72", db)
    return round(256 * 10.0 ** (db / 10.0))
