"""User identification: keep our own returns, name everybody else's by their UID.

Supplementary Note 11 and Fig. 4b. Every user polarity-modulates its Gold code with
an n-bit UID (bit p set = period p inverted). The receiver reports, for the primary
peak and each extra peak, the sign of the per-period correlation at that lag; the
bits where the sign is negative are the *observed* UID. A return is ours when no sign
is zero and the observed UID equals our UID exactly (the receiver's ``uid_match``);
it belongs to another user when the signs are all non-zero but spell another UID.
Since the other user's periods are not aligned with ours, what we observe is a
rotation of its UID: we name it by the canonical necklace (the smallest rotation,
``cdma_lidar.firmware_model.uid.canonical_necklace``), which is the same for every rotation.

When the primary peak is foreign but an extra peak carries our UID, that extra peak
is our echo and is used instead (it has no neighbour samples, so its lag is an
integer). All functions are vectorised over the ``(K, C)`` pixels of a frame.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from functools import lru_cache

import numpy as np
from numpy.typing import NDArray

from cdma_lidar.errors import out_of_range
from cdma_lidar.firmware_model.snr import snr_xc_db
from cdma_lidar.firmware_model.uid import canonical_necklace
from cdma_lidar.host.frame import FrameData

__all__ = [
    "ForeignReturns",
    "OwnReturns",
    "canonical_uids",
    "find_foreign",
    "observed_uids",
    "select_own",
]

_MAX_UID_BITS = 16


@lru_cache(maxsize=16)
def _canonical_table(n: int) -> NDArray[np.int64]:

    return np.array([canonical_necklace(v, n) for v in range(1 << n)], dtype=np.int64)


def canonical_uids(values: NDArray, n: int) -> NDArray[np.int64]:
    """Canonical necklace (smallest rotation) of each n-bit UID value, vectorised."""
    if not 1 <= n <= _MAX_UID_BITS:
        raise out_of_range("uid_bits", f"from 1 to {_MAX_UID_BITS}", n)
    v = np.asarray(values, dtype=np.int64)
    if v.size and (v.min() < 0 or v.max() >= (1 << n)):
        raise out_of_range("uid", f"from 0 to {(1 << n) - 1}", v)
    return _canonical_table(n)[v]


def observed_uids(signs: NDArray) -> tuple[NDArray[np.int64], NDArray[np.bool_]]:
    """UID bits read from per-period signs (..., n): bit p set where sign < 0.

    Returns ``(observed, clear)``, where ``clear`` is False if any sign is zero (no
    identity can be read from that return).
    """
    s = np.asarray(signs)
    weights = np.left_shift(np.int64(1), np.arange(s.shape[-1], dtype=np.int64))
    observed = ((s < 0).astype(np.int64) * weights).sum(axis=-1)
    clear = np.all(s != 0, axis=-1)
    return observed, clear


@dataclass
class OwnReturns:
    """Our own return per pixel, chosen among the primary and the extra peaks.

    Attributes:
        lag: lag of the chosen peak (samples), (K, C).
        peak: correlator output at that lag, (K, C).
        neighbours: outputs at lag -/+ 1, (K, C, 2); only meaningful where ``has_neighbours``.
        has_neighbours: True where the chosen peak is the primary (neighbours were sent).
        source: 0 for the primary peak, j + 1 for extra peak j, -1 where none is ours.
        foreign: True where the primary peak has a clear foreign UID and no extra peak is ours.
        ghost: True where the primary peak is ours but in a ghost window, and no extra
            peak outside the windows is ours.
    """

    lag: NDArray[np.int64]
    peak: NDArray[np.int64]
    neighbours: NDArray[np.int64]
    has_neighbours: NDArray[np.bool_]
    source: NDArray[np.int64]
    foreign: NDArray[np.bool_]
    ghost: NDArray[np.bool_]


def select_own(frame: FrameData, uid: int,
               excluded: Callable[[NDArray[np.int64]], NDArray[np.bool_]] | None = None
               ) -> OwnReturns:
    """Pick our own return in every pixel (primary peak if it matches, else a matching extra).

    With a single UID period (no identity modulation) this is the primary peak
    wherever the receiver says ``uid_match``. ``excluded(lags) -> mask`` marks lags
    that cannot be ours (grating ghost windows); a primary peak there gives way to the
    strongest matching extra peak outside them, if any (else the pixel is a ghost). A
    primary with another user's clear UID gives way the same way. The complement of our
    UID counts as our own cross-talk, not as a user (see :func:`find_foreign`).
    """
    n = frame.uid_bits
    if not 0 <= uid < (1 << n):
        raise out_of_range("uid", f"from 0 to {(1 << n) - 1}", uid)
    if excluded is None:
        def excluded(lags: NDArray[np.int64]) -> NDArray[np.bool_]:
            return np.zeros(np.shape(lags), dtype=bool)
    primary_match = frame.uid_match.astype(bool)
    primary_ghost = primary_match & excluded(frame.peak_lag)
    primary_ours = primary_match & ~primary_ghost
    complement = ~uid & ((1 << n) - 1)
    p_obs, primary_clear = observed_uids(frame.uid_signs)
    primary_foreign = primary_clear & (p_obs != uid) & (p_obs != complement)
    source = np.where(primary_ours, 0, -1).astype(np.int64)
    lag = frame.peak_lag.copy()
    peak = frame.peak.copy()
    if frame.peaks > 1:
        obs, clear = observed_uids(frame.extra_signs)  # (K, C, P-1)
        extra_ours = (clear & (obs == uid) & (frame.extra_peak != 0)
                      & ~excluded(frame.extra_lag))
        mag = np.where(extra_ours, np.abs(frame.extra_peak), -1)
        best = np.argmax(mag, axis=-1)
        has_extra = np.take_along_axis(mag, best[..., None], -1)[..., 0] >= 0
        # Only a peak that is explained (another user's, or a ghost) gives way; a primary
        # that is just noise would otherwise hand the pixel to the next noise peak.
        use = ~primary_ours & has_extra & (primary_foreign | primary_ghost)
        lag = np.where(use, np.take_along_axis(frame.extra_lag, best[..., None], -1)[..., 0], lag)
        peak = np.where(use, np.take_along_axis(frame.extra_peak, best[..., None], -1)[..., 0],
                        peak)
        source = np.where(use, best + 1, source)
    foreign = (source < 0) & primary_foreign
    return OwnReturns(lag=lag, peak=peak, neighbours=frame.neighbours,
                      has_neighbours=source == 0, source=source, foreign=foreign,
                      ghost=(source < 0) & primary_ghost)


@dataclass
class ForeignReturns:
    """Other users' returns seen in a frame, one entry per detected peak (1-D arrays).

    ``user`` is the canonical necklace of the observed UID, ``observed`` the UID as
    read (a rotation of the user's UID), ``lag`` in samples, ``peak`` in correlator units.
    """

    channel: NDArray[np.int64]
    column: NDArray[np.int64]
    lag: NDArray[np.int64]
    peak: NDArray[np.int64]
    observed: NDArray[np.int64]
    user: NDArray[np.int64]
    snr_xc_db: NDArray[np.float64]

    def __len__(self) -> int:
        return int(self.channel.size)

    def users(self) -> dict[int, int]:
        """Detections per foreign user (canonical UID -> count)."""
        keys, counts = np.unique(self.user, return_counts=True)
        return {int(k): int(c) for k, c in zip(keys, counts, strict=True)}


def find_foreign(frame: FrameData, uid: int, snr_threshold_db: float, *,
                 column_support: bool = True, tol_samples: float = 1.5) -> ForeignReturns:
    """Every primary or extra peak above ``snr_threshold_db`` whose clear UID is not ours.

    With ``column_support`` a return counts only if the same user shows up in the same
    channel of an adjacent column within ``tol_samples`` of the same lag: another LiDAR
    stays put for the milliseconds between two columns, while a noise peak that happens
    to read as a UID does not repeat.

    A return whose canonical UID equals the canonical form of ours but is a different
    rotation is still foreign (a user with our necklace but other phase cannot be us:
    our own periods are aligned with our reference). A return that reads as the bitwise
    complement of our UID is *not* reported: our own echoes in the other channels leak
    into every channel through the Gold codes' cross-correlation, and where that
    sidelobe is negative their per-period signs spell exactly ``~uid``. (The price: a
    user whose UID is our complement at the same phase is not told apart from it.)
    """

    n = frame.uid_bits
    if not 0 <= uid < (1 << n):
        raise out_of_range("uid", f"from 0 to {(1 << n) - 1}", uid)
    k, c = frame.shape
    lags = [frame.peak_lag[..., None]]
    peaks = [frame.peak[..., None]]
    signs = [frame.uid_signs[:, :, None, :]]
    if frame.peaks > 1:
        lags.append(frame.extra_lag)
        peaks.append(frame.extra_peak)
        signs.append(frame.extra_signs)
    lag = np.concatenate(lags, axis=-1)
    peak = np.concatenate(peaks, axis=-1)
    obs, clear = observed_uids(np.concatenate(signs, axis=-2))
    p = lag.shape[-1]
    snr = snr_xc_db(peak, *(np.broadcast_to(a[..., None], (k, c, p))
                            for a in (frame.noise_count, frame.noise_sum, frame.noise_sumsq)))
    snr = np.asarray(snr, dtype=np.float64)
    done = np.broadcast_to(frame.done[None, :, None], (k, c, p))
    complement = ~uid & ((1 << n) - 1)
    hit = (done & clear & (obs != uid) & (obs != complement) & (peak != 0)
           & (snr >= snr_threshold_db))
    if column_support and c > 1:
        user = np.where(hit, _canonical_table(n)[obs], -1)
        fl = np.where(hit, lag, -(10**9)).astype(np.float64)
        seen = np.zeros_like(hit)
        for shift in (-1, 1):
            o_user = np.full_like(user, -2)
            o_lag = np.full_like(fl, np.nan)
            if shift < 0:
                o_user[:, 1:], o_lag[:, 1:] = user[:, :-1], fl[:, :-1]
            else:
                o_user[:, :-1], o_lag[:, :-1] = user[:, 1:], fl[:, 1:]
            same = ((user[..., :, None] == o_user[..., None, :])
                    & (np.abs(fl[..., :, None] - o_lag[..., None, :]) <= tol_samples))
            seen |= same.any(axis=-1)
        hit &= seen
    ch, col, _ = np.nonzero(hit)
    return ForeignReturns(channel=ch.astype(np.int64), column=col.astype(np.int64),
                          lag=lag[hit], peak=peak[hit], observed=obs[hit],
                          user=canonical_uids(obs[hit], n), snr_xc_db=snr[hit])
