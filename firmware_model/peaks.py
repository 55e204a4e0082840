"""The receive chain after the kernel: peak search, neighbours, noise floor and UID signs.

Vectorised over columns and channels; bit-identical to the streaming reference
(:mod:`cdma_lidar.firmware_model.reference`). Per channel: the peak is the largest
``|out|`` outside ghost windows, ties to the lowest gate index j; up to ``peaks``
peaks at least W+1 gate lags apart (W = ``peak_exclude``); the neighbours ``out`` at
peak_lag -+ 1; the noise floor (count, sum, sum of squares of ``out`` over the gate
minus peaks +-W and ghost lags); the per-period UID signs at each peak.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
from numpy.typing import NDArray

from cdma_lidar.firmware_model.correlators.chip_domain import correlate_at
from cdma_lidar.firmware_model.output import FIELDS, ReceiverOutput, saturated_flags
from cdma_lidar.firmware_model.receiver_config import ReceiverConfig, Widths

__all__ = ["PeakSearch"]


class PeakSearch:
    """The post passes of one configuration and code set (docs/firmware.md §4).

    ``bip`` (K, N) int8 are the codes as +-1 (chip bit 0 -> +1); ``widths`` the
    configuration's :class:`Widths` for N chips. ``lags`` (G + 2,) are the lags, in
    samples, of ``out[..., m]``: gate_start - 1 + m (mod N*S).
    """

    def __init__(self, cfg: ReceiverConfig, widths: Widths, bip: NDArray[np.int8]) -> None:
        self.cfg, self.widths, self.bip = cfg, widths, bip
        ns = bip.shape[1] * cfg.samples_per_chip
        g = cfg.gate_len
        lag_lo = (cfg.gate_start - 1) % ns
        self.lags = (lag_lo + np.arange(g + 2, dtype=np.int64)) % ns  # lags of out[m]
        gate_lags = self.lags[1:-1]
        ghost = np.zeros(g, dtype=bool)
        for start, length in cfg.ghost_windows:
            ghost |= (gate_lags - start) % ns < length
        self.ghost = ghost
        self.has_ghost = bool(ghost.any())  # tested twice per call
        # the peak exclusion |j - j_peak| <= W as rows of a table, when it is small
        w = cfg.peak_exclude
        jj = np.arange(g)
        self.window = (np.abs(jj[:, None] - jj[None, :]) <= w) if g <= 2048 else None
        #: (-1)^bit_p(uid) per period p
        self.despread = np.array(
            [-1 if (cfg.uid >> p) & 1 else 1 for p in range(cfg.uid_bits)], dtype=np.int64
        )

    def __call__(self, raw: NDArray[np.int64], out: NDArray[np.int64],
                 acc: NDArray[np.signedinteger], work: NDArray[np.int64],
                 own: Callable[[NDArray[np.int64]], NDArray[np.int64]] | None = None
                 ) -> list[ReceiverOutput]:
        """The outputs of C columns from the kernel's ``raw`` and the scaled ``out``
        (C, K, G + 2) int64 (lags gate_start - 1 .. gate_start + G), the accumulators
        ``acc`` (C, n, NS) and a (C, K, G) int64 ``work`` array (overwritten).

        ``own`` (a cancellation round): the per-period correlation each channel's own
        subtracted echo adds at gate indices j (C, K, P), before the UID sign of period p
        (times (-1)^bit_p(uid)); ``raw`` already holds it.

        ``corr`` of each output is a view of ``out``."""
        cfg = self.cfg
        c, k, _ = out.shape
        g, w, npk, n = cfg.gate_len, cfg.peak_exclude, cfg.peaks, cfg.uid_bits
        corr = out[:, :, 1:-1]  # the gate; the returned traces are views of it
        mag = np.abs(corr, out=work)  # |out| <= 2^31: no overflow
        if self.has_ghost:
            mag[..., self.ghost] = -1
        jj = np.arange(g)
        pk_j = np.full((c, k, npk), -1, dtype=np.int64)
        near_any = None
        for p in range(npk):
            j = np.argmax(mag, axis=-1)  # first (lowest j) among equal maxima
            ok = np.take_along_axis(mag, j[..., None], axis=-1)[..., 0] >= 0
            pk_j[..., p] = np.where(ok, j, -1)
            if self.window is not None:  # rows |jj - j| <= W of a precomputed table
                near = self.window[j]
                near &= ok[..., None]
            else:  # two comparisons straight to bool: no (C, K, G) integer temporaries
                jc = j[..., None]
                near = jj >= jc - w
                near &= jj <= jc + w
                near &= ok[..., None]
            if near_any is None:
                near_any = near
            else:
                near_any |= near
            if p + 1 < npk:  # the last peak's window only matters to the noise mask
                np.putmask(mag, near, -1)
        found = pk_j >= 0
        jsafe = np.where(found, pk_j, 0)
        pk_lag = np.where(found, self.lags[1:-1][jsafe], -1)
        pk_val = np.where(found, np.take_along_axis(corr, jsafe, axis=-1), 0)
        # neighbours of the first peak: out[m] with m = j (lag-1) and j + 2 (lag+1)
        j0 = jsafe[..., :1]
        nb = np.concatenate(
            [np.take_along_axis(out, j0, axis=-1), np.take_along_axis(out, j0 + 2, axis=-1)],
            axis=-1,
        )
        nb = np.where(found[..., :1], nb, 0)
        noise = np.logical_not(near_any, out=near_any)
        if self.has_ghost:
            noise &= ~self.ghost
        cnt = np.count_nonzero(noise, axis=-1).astype(np.int64)
        cz = np.multiply(corr, noise, out=mag)  # out over the noise lags, 0 elsewhere
        nsum = cz.sum(axis=-1, dtype=np.int64)
        if self.widths.wide_sumsq:
            np.multiply(cz, cz, out=cz)  # |out| <= 2^31: each square fits int64
            nsq = _sum_squares(cz, None, True)
        else:  # every square and their sum fit int64 (noise_sumsq <= 63 bits): one pass
            nsq = np.einsum("ckj,ckj->ck", cz, cz)
        signs = self._uid_signs(raw, acc, jsafe, found, own)  # (C, K, P, n)
        observed = ((signs[:, :, 0, :] < 0).astype(np.int64) << np.arange(n)).sum(axis=-1)
        match = found[..., 0] & np.all(signs[:, :, 0, :] != 0, axis=-1) & (observed == cfg.uid)
        uid0 = np.ascontiguousarray(signs[:, :, 0, :])
        extra_signs = np.ascontiguousarray(signs[:, :, 1:, :])
        lag0, val0 = np.ascontiguousarray(pk_lag[..., 0]), np.ascontiguousarray(pk_val[..., 0])
        lag1, val1 = np.ascontiguousarray(pk_lag[..., 1:]), np.ascontiguousarray(pk_val[..., 1:])
        sat = saturated_flags(lag0, val0, cfg.out_bits)
        batch = {"corr": corr, "peak_lag": lag0, "peak": val0, "neighbours": nb,
                 "noise_count": cnt, "noise_sum": nsum, "noise_sumsq": nsq, "uid_signs": uid0,
                 "uid_observed": observed, "uid_match": match, "saturated": sat,
                 "extra_lag": lag1, "extra_peak": val1, "extra_signs": extra_signs}
        # per-column views into the batch's arrays (``corr``: of the kernel's output),
        # positional in field order: list(a) makes the views faster than a[ci]
        return [ReceiverOutput(*v) for v in zip(*(list(batch[f]) for f in FIELDS), strict=True)]

    def _uid_signs(
        self,
        raw: NDArray[np.int64],
        acc: NDArray[np.int64],
        jsafe: NDArray[np.int64],
        found: NDArray[np.bool_],
        own: Callable[[NDArray[np.int64]], NDArray[np.int64]] | None = None,
    ) -> NDArray[np.int8]:
        """sign(sum_i ref_k[i] acc[p][(i + lag) mod NS]) at each peak lag -> (C, K, P, n) int8."""
        cfg = self.cfg
        if cfg.uid_bits == 1:
            # d = (-1)^uid * acc[0], so the period's correlation is (-1)^uid * raw at the lag.
            r = np.take_along_axis(raw, jsafe + 1, axis=-1) * self.despread[0]
            s = np.sign(r)[..., None]
        else:
            lags = self.lags[1:-1][jsafe]  # (C, K, P)
            v = correlate_at(self.bip, acc, lags, cfg.samples_per_chip)
            if own is not None:
                v += own(jsafe)[..., None] * self.despread
            s = np.sign(v)
        return np.where(found[..., None], s, 0).astype(np.int8)


def _sum_squares(sq: NDArray[np.int64], where: NDArray[np.bool_] | None, wide: bool) -> NDArray:
    """Exact ``sum(sq, axis=-1, where=where)`` of squares ``sq`` (each < 2^63).

    When ``wide`` (Widths.noise_sumsq > 63) the sum may not fit int64: the squares are
    split at bit 31, ``sq = hi 2^31 + lo``, both halves summed in int64 (at most 2^26
    lags of < 2^32: no overflow) and recombined as Python integers (object array).
    """
    kw = {} if where is None else {"where": where}
    if not wide:
        return sq.sum(axis=-1, dtype=np.int64, **kw)  # exact: noise_sumsq <= 63 bits
    lo = (sq & ((1 << 31) - 1)).sum(axis=-1, dtype=np.int64, **kw)
    hi = (sq >> 31).sum(axis=-1, dtype=np.int64, **kw)
    out = np.empty(lo.shape, dtype=object)
    flat = out.reshape(-1)
    for i, (h, v) in enumerate(zip(hi.ravel().tolist(), lo.ravel().tolist(), strict=True)):
        flat[i] = (h << 31) + v
    return out
