"""Exact lag-window kernel (``method="windows"``): one matrix product per phase, the lags
as rows.

The gated lags of phase r sit at consecutive chip offsets ``a_r .. a_r + L_r - 1``
(:mod:`.matmul`). Their windows of the chip sums, each a row, make one operand, and one
product with the codes gives every channel at every lag of the phase::

    D_r[c L_r + t, j] = Y[c, r, (j + a_r + t) mod N]        t < L_r, j < N
    raw[c, :, lag of (r, t)] = (bip @ D_r.T)[:, c L_r + t]   (K, N) @ (N, rows)

Where :mod:`.direct` makes one matrix-vector product per lag (one row: a column) and
:mod:`.matmul` a Hankel block of the codes (``K L N`` floats), this kernel copies
``L N`` floats of data per column and phase and multiplies them by the codes once: a
true matrix product of ``C L`` rows whose large operand, the (K, N) codes, is read
once. So a long code with many channels (degree 15, K = 1,200, a 64-lag gate: one
(33, 32767) @ (32767, 1200) product per phase) runs at the machine's product rate.

Exactness as in :mod:`.matmul`: every partial sum of one output is a sum of a subset of
``+-Y_r``, so a float32 product is exact when ``sum_j |Y_r[j]|`` stays below
:meth:`GatePlan.float32_limit` (proven for all data by ``N y_bound``, or for a block by
the receiver's ``bound``, ``sum_i |d_i|`` per column), float64 when ``N max|Y|`` stays
below ``2^float_bits``, else ``Y`` is split into limbs (:func:`.base.product_limbs`).
"""

from __future__ import annotations

import math
import threading

import numpy as np
from numpy.lib.stride_tricks import as_strided
from numpy.typing import NDArray

from cdma_lidar.firmware_model.correlators.base import (
    BLOCK_BYTES,
    Correlator,
    GatePlan,
    product_limbs,
)
from cdma_lidar.firmware_model.correlators.costs import Coefficients, Estimate, gemm_seconds

__all__ = ["WindowsCorrelator"]


#: numpy calls' worth of Python per phase and block of columns: the rotated copy, the
#: windows, the product and the store (10 us per phase measured on the 2-core machine,
#: 16 phases of a degree-6 code).
PHASE_CALLS = 16


def _phases(plan: GatePlan) -> list[tuple[int, int, int]]:
    """(phase r, first chip offset a_r, lags L_r) of every phase with a gated lag."""
    return [(r, (plan.q0 + int(plan.u_m[sel[0]])) % plan.n, len(sel))
            for r, sel in enumerate(plan.sel) if len(sel)]


#: Bytes of output per block of columns: every phase stores its lags (every S-th) into
#: the block's rows, which then stay in the cache from one phase to the next. (Blocks of
#: 64 MiB stored a degree-5, 253-channel, 160-column frame's 10 phases through 42 MB of
#: output each: 2.5x matmul's kernel time, which scatters in such steps too.)
STORE_BYTES = 1 << 20
#: Bytes of windows copied per product (float64 counted): a gate over many lags of a
#: long code is taken in chunks of lags.
WINDOW_BYTES = 32 << 20


def _block(plan: GatePlan) -> int:
    """Columns per block: one phase's windows (float64) and products within BLOCK_BYTES,
    the block's output within STORE_BYTES."""
    top = max(length for _, _, length in _phases(plan))
    return max(1, min(BLOCK_BYTES // (8 * top * (plan.n + 2 * plan.k)),
                      STORE_BYTES // (8 * plan.k * plan.count)))


class WindowsCorrelator(Correlator):
    """Per active phase, the windows of the chip sums at its lags, copied as rows, times
    the codes: float32 when provably exact, float64 otherwise, limbs for the 2^53 bound."""

    #: its Python per call (buffers, the float32 rule), as matmul's: the two measured
    #: level on tiny plans (12-15 us on the 2-core machine, where matmul's 400 calls
    #: were fitted on another); per phase and block PHASE_CALLS more
    fixed_calls = 400.0
    takes_bound = True  # sum |d| per column proves float32 products without a look at Y

    @classmethod
    def estimate(cls, plan: GatePlan, co: Coefficients) -> Estimate:
        """Per block and phase: the windows copied in, one product, the lags scattered out.

        float32 is only counted on when ``N y_bound`` proves it for all data, as in
        :mod:`.matmul`."""
        c, n, k = plan.columns, plan.n, plan.k
        cb = min(c, _block(plan))
        single = plan.float32_certain()
        parts = 1 if single else plan.matmul_limbs()
        item = 4.0 if single else 8.0
        phases = _phases(plan)

        def block(rows: int) -> float:
            t = 0.0
            for _, _, length in phases:
                m = rows * length
                product = gemm_seconds(k, n, m, co, item) if single else \
                    gemm_seconds(m, n, k, co, item)  # the orientation __call__ takes
                t += product \
                    + co.byte * ((8.0 + item) * m * n + (item + 16.0) * m * k) \
                    + PHASE_CALLS * co.call
            return parts * t

        full, rest = divmod(c, cb)
        seconds = full * block(cb) + (block(rest) if rest else 0.0) + cls.fixed_calls * co.call
        top = max(length for _, _, length in phases)
        peak = (item + 8.0) * n * k + min(item * cb * top * n, WINDOW_BYTES) \
            + item * cb * top * k + item * cb * (n + top) + 8.0 * c * k * plan.count
        return Estimate(seconds, peak)

    def __init__(self, plan: GatePlan) -> None:
        super().__init__(plan)
        self._phases = _phases(plan)
        self._codes: dict[type, NDArray[np.floating]] = {}  # (K, N) +-1 by float type
        self._lock = threading.Lock()
        self._local = threading.local()  # per-thread operand buffers

    def _bip(self, dtype: type) -> NDArray[np.floating]:
        """The codes as a C-contiguous (K, N) ``dtype`` matrix."""
        b = self._codes.get(dtype)
        if b is None:
            with self._lock:
                b = self._codes.get(dtype)
                if b is None:
                    b = self._codes[dtype] = self.plan.bip.astype(dtype)
        return b

    def _buffer(self, name: str, shape: tuple[int, ...], dtype: type) -> NDArray[np.floating]:
        """A reused per-thread buffer (no fresh pages to fault in on every call)."""
        bufs = self._local.__dict__.setdefault("bufs", {})
        size = math.prod(shape)
        work = bufs.get((name, dtype))
        if work is None or work.size < size:
            work = bufs[name, dtype] = np.empty(size, dtype=dtype)
        return work[:size].reshape(shape)

    def _product(self, rows: NDArray[np.floating], codes: NDArray[np.floating],
                 single: bool, lags: NDArray[np.int64], shift: int, only: bool,
                 first: bool) -> None:
        """``rows`` (C L, N) of windows times the (K, N) ``codes`` into ``lags`` (C, K, L)
        (a strided view of the output): stored, shifted by ``shift`` (the first of
        several limbs) or added (the later ones); ``only``: one limb, no shift."""
        cb, k, lt = lags.shape
        dtype = rows.dtype.type
        if single:  # (K, N) @ (N, C L): measured the faster in float32
            o = self._buffer("out", (k, cb * lt), dtype)
            np.matmul(codes, rows.T, out=o)  # exact integers (module doc)
            src = o.reshape(k, cb, lt).transpose(1, 0, 2)
        else:  # (C L, N) @ (N, K): the faster in float64
            o = self._buffer("out", (cb * lt, k), dtype)
            np.matmul(rows, codes.T, out=o)
            src = o.reshape(cb, lt, k).transpose(0, 2, 1)
        if only:
            np.copyto(lags, src, casting="unsafe")  # exact integers
        elif first:
            np.left_shift(src.astype(np.int64), shift, out=lags)
        else:
            lags += src.astype(np.int64) << shift

    def __call__(self, y: NDArray[np.signedinteger],
                 bound: NDArray[np.unsignedinteger] | None = None) -> NDArray[np.int64]:
        plan = self.plan
        c, _, n = y.shape
        k, s = plan.k, plan.s
        limit = plan.float32_limit()
        out = np.empty((c, k, plan.count), dtype=np.int64)
        block = _block(plan)
        for c0 in range(0, c, block):
            yb = y[c0 : c0 + block]
            cb = yb.shape[0]
            dst = out[c0 : c0 + cb]
            single = bool(limit) and (plan.float32_certain() or (
                bound is not None and int(bound[c0 : c0 + cb].max()) < limit))
            parts = [(yb, 0)] if single else product_limbs(plan, yb)
            dtype = np.float32 if single else np.float64
            codes = self._bip(dtype)
            for i, (limb, shift) in enumerate(parts):
                for r, a, length in self._phases:
                    # Y_r rotated by a, then its first L - 1 chips again: window t = row t
                    ext = self._buffer("ext", (cb, n + length - 1), dtype)
                    row = limb[:, r, :]
                    np.copyto(ext[:, : n - a], row[:, a:], casting="unsafe")
                    np.copyto(ext[:, n - a : n], row[:, :a], casting="unsafe")
                    done = n
                    while done < n + length - 1:  # L - 1 > N only for a gate over a period
                        take = min(n, n + length - 1 - done)
                        ext[:, done : done + take] = ext[:, :take]
                        done += take
                    lags = dst[:, :, int(plan.sel[r][0]) :: s]  # phase r's lags: strided
                    step = ext.strides[1]  # window t starts t chips in: rows overlap
                    chunk = max(1, min(length, WINDOW_BYTES // (8 * cb * n)))
                    for t0 in range(0, length, chunk):
                        lt = min(chunk, length - t0)
                        windows = self._buffer("win", (cb, lt, n), dtype)
                        np.copyto(windows, as_strided(ext[:, t0:], (cb, lt, n),
                                                      (ext.strides[0], step, step)))
                        self._product(windows.reshape(cb * lt, n), codes, single,
                                      lags[:, :, t0 : t0 + lt], shift, len(parts) == 1,
                                      i == 0)
        return out
