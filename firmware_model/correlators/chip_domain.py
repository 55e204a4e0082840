"""Integrate-and-dump into the chip domain, and the per-period dots of the UID signs.

With ``W[i] = sum_{s<S} d[(i + s) mod NS]`` and ``Y_r[m] = W[m S + r]`` (r = 0..S-1,
m = 0..N-1), a sample lag ``l = q S + r`` gives::

    raw[l] = sum_i ref[i] d[(i + l) mod NS] = sum_c bip[c] Y_r[(c + q) mod N]

so the correlation over N*S samples becomes S chip-rate correlations of length N,
which the registered kernels (:mod:`cdma_lidar.firmware_model.correlators`) evaluate.
"""

from __future__ import annotations

import numpy as np
from numpy.lib.stride_tricks import sliding_window_view
from numpy.typing import NDArray

from cdma_lidar.firmware_model.correlators.base import BLOCK_BYTES

__all__ = ["chip_sums", "correlate_at", "int_type"]


def int_type(bits: int) -> type[np.signedinteger]:
    """The narrowest of int16, int32, int64 holding a signed ``bits``-bit word (bits <= 64)."""
    return np.int16 if bits <= 16 else np.int32 if bits <= 32 else np.int64


def chip_sums(d: NDArray[np.integer], s: int, sign: int = 1,
              dtype: type[np.signedinteger] = np.int64,
              out: NDArray[np.signedinteger] | None = None,
              scratch: NDArray[np.signedinteger] | None = None) -> NDArray[np.signedinteger]:
    """Integrate-and-dump (C, N*S) -> (C, S, N): ``Y[c,r,m] = sign sum_{t<S} d[(mS+r+t) mod NS]``.

    First the circular window sums ``W[i] = sum_{t<S} d[(i + t) mod NS]`` at every
    sample (for small S by doubling: windows of 1, 2, 4 samples, each the sum of two
    of the previous, combined along the bits of S: 2 passes for S = 4 instead of 4;
    a prefix sum otherwise), then
    ``Y[c, r, m] = W[c, m S + r]``, returned as a strided view of W (the kernels copy
    each phase once, into their float operands, anyway). ``sign`` (+1 or -1)
    is the despread of a one-period UID, folded into the first pass (S > 1 and +1:
    the first pass reads ``d`` directly). ``dtype`` is the
    integer type of the work and the result: the caller makes it wide enough for
    ``S max|d|`` (and for ``S NS max|d|`` when S > 8, the prefix sums). ``out``, if
    given, is a (C, N*S) array of ``dtype`` that receives W (the result is its view);
    ``scratch``, if given, another one (sharing memory with neither ``d`` nor ``out``)
    that holds the first intermediate window sums (S <= 8): a caller that keeps it
    saves faulting in a fresh array's pages on every call (4 ms of a paper frame).
    """
    c, ns = d.shape
    n = ns // s
    if s <= 8:
        w = np.empty((c, ns), dtype=dtype) if out is None else out
        _window_sums(d, s, sign, w, [] if scratch is None else [scratch])
    else:
        ext = np.empty((c, ns + s), dtype=dtype)
        ext[:, 0] = 0
        ext[:, 1 : ns + 1] = d
        ext[:, ns + 1 :] = d[:, : s - 1]
        cs = np.cumsum(ext, axis=1, out=ext)
        w = np.subtract(cs[:, s : s + ns], cs[:, :ns], out=out)
        if sign < 0:
            np.negative(w, out=w)
    return w.reshape(c, n, s).transpose(0, 2, 1)  # a strided view: no transpose copy


def _shifted_add(a: NDArray[np.integer], b: NDArray[np.integer], t: int,
                 out: NDArray[np.signedinteger]) -> None:
    """``out[:, i] = a[:, i] + b[:, (i + t) mod NS]`` in ``out``'s type (out may be a, not b)."""
    np.add(a[:, :-t], b[:, t:], out=out[:, :-t], dtype=out.dtype, casting="unsafe")
    np.add(a[:, -t:], b[:, :t], out=out[:, -t:], dtype=out.dtype, casting="unsafe")


def _window_sums(d: NDArray[np.integer], s: int, sign: int,
                 w: NDArray[np.signedinteger], spare: list[NDArray] | None = None) -> None:
    """``w[:, i] = sign sum_{t<s} d[:, (i + t) mod NS]`` by doubling (s <= 8).

    ``p`` holds windows of 1, 2, 4, ... samples (each two of the previous, one pass;
    the window of 1 is ``d`` itself when ``sign`` is +1, so no pass is spent on it);
    the windows of the set bits of s, from the largest down, are added into ``w`` at
    the offsets that tile s samples. Every partial sum is a sum of at most s samples,
    computed in ``w``'s type, so ``dtype`` wide enough for ``S max|d|`` holds them all.
    ``spare``: arrays like ``w`` taken (each once) for intermediates before new ones.
    """
    spare = [] if spare is None else spare

    def fresh() -> NDArray[np.signedinteger]:
        return spare.pop() if spare else np.empty_like(w)

    if s == 1:
        np.multiply(d, sign, out=w, dtype=w.dtype, casting="unsafe")  # -(-2^15): wide
        return
    p = d
    if sign < 0:  # the window of 1 sample, negated
        p = fresh()
        np.multiply(d, sign, out=p, dtype=p.dtype, casting="unsafe")
    width, top = 1, 1 << (s.bit_length() - 1)
    while width < top:  # p: window of 2 width samples
        nxt = fresh() if width * 2 < top or s != top else w
        _shifted_add(p, p, width, nxt)
        p, width = nxt, width * 2
    if s == top:
        return  # p is w
    # s = top + rest: the top window, then the remaining bits' windows after it
    np.copyto(w, p)
    offset, rest = top, s - top
    while rest:
        bit = 1 << (rest.bit_length() - 1)
        _shifted_add(w, _window(d, bit, sign, w.dtype), offset, w)
        offset, rest = offset + bit, rest - bit


def _window(d: NDArray[np.integer], s: int, sign: int, dtype: np.dtype) -> NDArray:
    """The window sums of ``s`` samples (a power of two) as a new array."""
    w = np.empty(d.shape, dtype=dtype)
    _window_sums(d, s, sign, w)
    return w


def correlate_at(
    bip: NDArray[np.int8], acc: NDArray[np.int64], lags: NDArray[np.int64], s: int
) -> NDArray[np.int64]:
    """Per-period raw correlation at given lags (the UID signs at the peaks).

    ``bip`` (K, N) +-1, ``acc`` (C, n, N*S), ``lags`` (C, K, P) in 0..NS-1 (samples).
    Returns (C, K, P, n) int64 ``sum_i ref_k[i] acc[c, p, (i + lag) mod NS]``, exact.
    """
    c, n_uid, ns = acc.shape
    k, n = bip.shape
    _, _, npk = lags.shape
    y = chip_sums(acc.reshape(c * n_uid, ns), s).reshape(c, n_uid, s, n)
    q, r = np.divmod(lags, s)
    out = np.empty((c, k, npk, n_uid), dtype=np.int64)
    block = max(1, BLOCK_BYTES // (k * npk * n * 8 * 2))
    b64 = bip.astype(np.int64)[None, :, None, :]
    for c0 in range(0, c, block):
        c1 = min(c, c0 + block)
        ci = np.arange(c0, c1)[:, None, None]
        for p in range(n_uid):
            y2 = np.concatenate([y[c0:c1, p], y[c0:c1, p]], axis=-1)  # (cb, S, 2N)
            win = sliding_window_view(y2, n, axis=-1)  # (cb, S, N+1, N)
            rows = win[ci - c0, r[c0:c1], q[c0:c1]]  # (cb, K, P, N)
            out[c0:c1, :, :, p] = (rows * b64).sum(axis=-1)
    return out
