"""Exact fast kernels of the receive chain: integrate-and-dump, gated correlation, UID dots.

Integrate-and-dump into the chip domain: with ``W[i] = sum_{s<S} d[(i + s) mod NS]``
and ``Y_r[m] = W[m S + r]`` (r = 0..S-1, m = 0..N-1), a sample lag ``l = q S + r`` gives::

    raw[l] = sum_i ref[i] d[(i + l) mod NS] = sum_c bip[c] Y_r[(c + q) mod N]

so the correlation over N*S samples becomes S chip-rate correlations of length N.

Two exact ways to evaluate it (both return int64, identical to the definition):

* ``matmul``: ``Y (C*S, N) @ B (N, K*nq)`` in float64 with the constant Hankel
  ``B[m, k, u] = bip_k[(m - q0 - u) mod N]``. Every product is +-y and every
  partial sum is bounded by ``N * max|y|``; when that is below 2^53 the BLAS
  result is the exact integer whatever the summation order. Otherwise ``y`` is
  split into limbs of h bits (``N * 2^h < 2^53``) and recombined in int64.
* ``fft``: linear correlation of ``bip`` with ``[Y_r, Y_r]`` through power-of-two
  real FFTs of length ``L >= 2N``, rounded to the nearest integer. Exact when the
  float error is below 1/2; a rigorous bound (Higham, "Accuracy and Stability",
  §24.1, with a generous constant) ``16 log2(L) eps (|a|_2 |y|_1 + 2 |a|_1 |y|_2)``
  must stay below 1/4, else ``y`` is split into limbs the same way.
"""

from __future__ import annotations

import logging
import math

import numpy as np
from numpy.lib.stride_tricks import sliding_window_view
from numpy.typing import NDArray
from scipy import fft as sfft

from cdma_lidar.errors import out_of_range

__all__ = ["GateCorrelator", "chip_sums", "correlate_at"]

log = logging.getLogger(__name__)

_EPS = float(np.finfo(np.float64).eps)
_FFT_GUARD = 0.25
_FFT_CONST = 16.0
_MEM_BYTES = 64 << 20  # working-set cap per block of columns / channels
_FFT_BLOCK_BYTES = 16 << 20  # spectra x channels per inverse-FFT batch
_MATMUL_BMAT_BYTES = 128 << 20
_FFT_COST_FACTOR = 8.0  # BLAS throughput / FFT throughput, per "operation" below


def chip_sums(d: NDArray[np.int64], s: int) -> NDArray[np.int64]:
    """Integrate-and-dump: (C, N*S) -> (C, S, N), ``Y[c, r, m] = sum_{t<S} d[(mS+r+t) mod NS]``.

    First the circular window sums ``W[i] = sum_{t<S} d[(i + t) mod NS]`` at every
    sample (S - 1 shifted adds for small S, a prefix sum otherwise), then
    ``Y[c, r, m] = W[c, m S + r]`` as one contiguous transpose.
    """
    c, ns = d.shape
    n = ns // s
    if s <= 8:
        w = d.astype(np.int64, copy=True)
        for t in range(1, s):
            w[:, :-t] += d[:, t:]
            w[:, -t:] += d[:, :t]
    else:
        ext = np.concatenate([np.zeros((c, 1), np.int64), d, d[:, : s - 1]], axis=1)
        cs = np.cumsum(ext, axis=1)
        w = cs[:, s : s + ns] - cs[:, :ns]
    return np.ascontiguousarray(w.reshape(c, n, s).transpose(0, 2, 1))


def _limbs(
    y: NDArray[np.int64], fits, h: int
) -> list[tuple[NDArray[np.int64], int]]:
    """Split y = sum limb * 2^shift until ``fits(limb)``; low limbs are in [0, 2^h)."""
    out: list[tuple[NDArray[np.int64], int]] = []
    shift = 0
    while not fits(y):
        out.append((y & ((1 << h) - 1), shift))
        y = y >> h
        shift += h
    out.append((y, shift))
    return out


class GateCorrelator:
    """``raw[c, k, m]`` at lags ``(lag_lo + m) mod NS``, m < count, from chip sums Y (C, S, N)."""

    def __init__(
        self,
        bip: NDArray[np.int8],
        s: int,
        lag_lo: int,
        count: int,
        method: str | None = None,
        float_bits: int = 53,
    ) -> None:
        self.k, self.n = bip.shape
        self.s = s
        self.bip = bip
        n, k = self.n, self.k
        if not n.bit_length() + 2 <= float_bits <= 53:
            raise out_of_range("float_bits", f"{n.bit_length() + 2}..53", float_bits)
        self.float_bits = float_bits
        self.q0, self.r0 = divmod(int(lag_lo), s)
        m = np.arange(count)
        self.u_m = (self.r0 + m) // s
        self.r_m = (self.r0 + m) % s
        self.nq = int(self.u_m[-1]) + 1
        self.fft_len = 1 << (2 * n - 1).bit_length()
        self.sel = [np.nonzero(self.r_m == r)[0] for r in range(s)]  # lags m of phase r
        mm_ops = n * k * count / s
        fft_ops = (k + 1) * self.fft_len * math.log2(self.fft_len) * _FFT_COST_FACTOR
        mm_bytes = n * k * count * 8
        if method is None:
            method = "matmul" if (mm_ops <= fft_ops and mm_bytes <= _MATMUL_BMAT_BYTES) else "fft"
        if method not in ("matmul", "fft"):
            raise out_of_range("method", "'matmul', 'fft' or None", method)
        self.method = method
        if method == "matmul":
            # one Hankel block per phase r holding only the chip lags that phase needs
            self.bmat = []
            for sel in self.sel:
                u = self.u_m[sel]
                idx = (np.arange(n)[:, None] - self.q0 - u[None, :]) % n  # (N, nq_r)
                self.bmat.append(np.ascontiguousarray(
                    bip[:, idx].transpose(1, 0, 2).reshape(n, k * len(u)), dtype=np.float64
                ))
        else:
            self._spec = None
        log.debug("gate correlator: N=%d S=%d K=%d lags=%d via %s", n, s, k, count, method)

    def __call__(self, y: NDArray[np.int64]) -> NDArray[np.int64]:
        if self.method == "matmul":
            return self._matmul(y)
        return self._fft(y)

    # -- exact float64 matrix product

    def _matmul(self, y: NDArray[np.int64]) -> NDArray[np.int64]:
        c, s, n = y.shape
        count = len(self.u_m)
        limit = 1 << self.float_bits
        h = self.float_bits - n.bit_length()
        per_col = s * n * 8 * 2 + self.k * count * 16
        block = max(1, _MEM_BYTES // per_col)
        out = np.zeros((c, self.k, count), dtype=np.int64)
        for c0 in range(0, c, block):
            yb = y[c0 : c0 + block]
            cb = yb.shape[0]
            acc = out[c0 : c0 + cb]
            for limb, shift in _limbs(yb, lambda v: n * int(np.abs(v).max(initial=0)) < limit, h):
                lf = limb.astype(np.float64)  # exact: |limb| < 2^53
                for r, sel in enumerate(self.sel):
                    if len(sel):
                        o = lf[:, r, :] @ self.bmat[r]  # (cb, K * nq_r), exact integers
                        o = o.reshape(cb, self.k, len(sel)).astype(np.int64)
                        acc[:, :, sel] += o << shift
        return out

    # -- FFT with a rigorous rounding guard

    def _spectra(self, k0: int, k1: int) -> NDArray[np.complex128]:
        nbytes = self.k * (self.fft_len // 2 + 1) * 16
        if nbytes <= _MEM_BYTES:
            if self._spec is None:
                self._spec = np.conj(sfft.rfft(self.bip.astype(np.float64), self.fft_len, axis=1))
            return self._spec[k0:k1]
        return np.conj(sfft.rfft(self.bip[k0:k1].astype(np.float64), self.fft_len, axis=1))

    def _fft_bound(self, v: NDArray[np.int64]) -> float:
        """Upper bound of |computed - exact| for correlating bip with [v, v] (each row)."""
        va = np.abs(v).astype(np.float64)
        l1 = 2.0 * float(va.sum(axis=-1).max(initial=0.0))
        l2 = math.sqrt(2.0 * float((va * va).sum(axis=-1).max(initial=0.0)))
        n = self.n
        mu = _FFT_CONST * math.log2(self.fft_len) * _EPS
        return mu * (math.sqrt(n) * l1 + 2.0 * n * l2) * 1.0001 + 1e-300

    def _fft(self, y: NDArray[np.int64]) -> NDArray[np.int64]:
        c, s, n = y.shape
        big = self.fft_len
        guard = _FFT_GUARD * 2.0 ** (self.float_bits - 53)
        mu = _FFT_CONST * math.log2(big) * _EPS
        unit = mu * (math.sqrt(n) * 2 * n + 2.0 * n * math.sqrt(2.0 * n)) * 1.0001
        h = math.floor(math.log2(guard / unit))
        if h < 1:
            raise out_of_range("float_bits", "large enough for an exact FFT", self.float_bits)
        kb = max(1, _FFT_BLOCK_BYTES // (s * (big // 2 + 1) * 16 + s * big * 8))
        out = np.zeros((c, self.k, len(self.u_m)), dtype=np.int64)
        sel = [np.nonzero(self.r_m == r)[0] for r in range(s)]
        qs = [(self.q0 + self.u_m[m]) % n for m in sel]
        for ci in range(c):
            yc = y[ci]  # (S, N)
            for limb, shift in _limbs(yc, lambda v: self._fft_bound(v) < guard, h):
                spec = sfft.rfft(np.concatenate([limb, limb], axis=1).astype(np.float64), big,
                                 axis=1)  # (S, L/2+1)
                for k0 in range(0, self.k, kb):
                    k1 = min(self.k, k0 + kb)
                    a = self._spectra(k0, k1)
                    x = sfft.irfft(a[None, :, :] * spec[:, None, :], big, axis=2)  # (S, Kb, L)
                    for r in range(s):
                        if len(sel[r]):
                            vals = np.rint(x[r][:, qs[r]]).astype(np.int64) << shift
                            out[ci][k0:k1, sel[r]] += vals  # (Kb, lags of phase r)
        return out


def correlate_at(
    bip: NDArray[np.int8], acc: NDArray[np.int64], lags: NDArray[np.int64], s: int
) -> NDArray[np.int64]:
    """Per-period raw correlation at given lags.

    ``bip`` (K, N) +-1, ``acc`` (C, n, N*S), ``lags`` (C, K, P) in 0..NS-1.
    Returns (C, K, P, n) int64 ``sum_i ref_k[i] acc[c, p, (i + lag) mod NS]``, exact.
    """
    c, n_uid, ns = acc.shape
    k, n = bip.shape
    _, _, npk = lags.shape
    y = chip_sums(acc.reshape(c * n_uid, ns), s).reshape(c, n_uid, s, n)
    q, r = np.divmod(lags, s)
    out = np.empty((c, k, npk, n_uid), dtype=np.int64)
    block = max(1, _MEM_BYTES // (k * npk * n * 8 * 2))
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
