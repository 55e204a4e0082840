"""Exact matrix-product kernel (``method="matmul"``): short gates, many columns.

The gated lags of phase r are the chip offsets ``u = a_r .. a_r + len_r - 1``
(``a_r`` the first, ``len_r`` = L or L - 1 with ``L = ceil(count / S)`` when every
phase has a lag). Each phase's chip sums ``Y_r`` (C, N) are copied once into a float
operand, rotated by ``a_r`` chips, so that every phase needs the same Hankel block
``B_L[i, k, t] = bip_k[(i - q0 - t) mod N]``, t < L: the phases with L lags are
stacked into one product ``(|A| C, N) @ (N, K L)``, those with L - 1 into a second one
with ``B_{L-1}`` (or into the first, computing one lag too many, while those lags are
few: :data:`MERGE_WASTE`). Every output lag is computed exactly once (up to that
one extra lag per phase), in at most two large products.

Exactness: every product is +-y and every partial sum of one output is a sum of a
subset of ``+-Y_r[i]``, bounded by ``sum_i |Y_r[i]|``, so whatever the summation
order of the BLAS:

* float32 products when that sum is below ``2^min(float32_bits, float_bits)``
  (<= 2^24) for every column and phase of a block: measured on the float32 operand
  itself (a value of 2^24 or more cannot round below 2^24, so a large value is never
  missed), summed in float64 (exact), or proven for all data by ``N y_bound``, or
  for the block by the caller's ``bound`` (the receiver's ``sum_i |d_i|`` per column:
  phase r's windows tile the period once, so ``sum_m |Y_r[m]| <= sum_i |d_i|``);
* else float64 when ``N max|y| < 2^float_bits`` (<= 2^53);
* else ``y`` is split into limbs of h bits (``N 2^h < 2^float_bits``), each product
  exact in float64, recombined in int64 (the result fits: W_raw <= 56 bits,
  docs/firmware.md section 3).
"""

from __future__ import annotations

import collections
import threading
from collections.abc import Iterable, Iterator

import numpy as np
from numpy.lib.stride_tricks import sliding_window_view
from numpy.typing import NDArray

from cdma_lidar.firmware_model.correlators.base import (
    BLOCK_BYTES,
    Correlator,
    GatePlan,
    product_limbs,
)
from cdma_lidar.firmware_model.correlators.costs import (
    Coefficients,
    Estimate,
    gemm_seconds,
)

__all__ = ["HANKEL_BYTES", "MERGE_WASTE", "MatmulCorrelator", "phase_groups"]


def _block(plan: GatePlan) -> int:
    """Columns per block: chip sums, float operands and output within BLOCK_BYTES."""
    return max(1, BLOCK_BYTES // (plan.s * plan.n * 8 * 2 + plan.k * (plan.count + 2 * plan.s)
                                  * 16))


def _lengths(plan: GatePlan) -> dict[int, int]:
    """Lags per active phase r (phases without a gated lag left out)."""
    return {r: len(sel) for r, sel in enumerate(plan.sel) if len(sel)}


def _products(plan: GatePlan, merged: bool, rows: int) -> list[tuple[int, int]]:
    """(operand rows, Hankel offsets) of each product for ``rows`` columns per block."""
    lens = _lengths(plan)
    top = max(lens.values())
    if merged:
        return [(rows * len(lens), top)]
    groups = collections.Counter(lens.values())
    return [(rows * groups[length], length) for length in sorted(groups, reverse=True)]


def _seconds(plan: GatePlan, co: Coefficients, merged: bool, rows: int, item: float) -> float:
    """Predicted time of the products of one block of ``rows`` columns in ``item``-byte
    floats (:func:`.costs.gemm_seconds`)."""
    n, k = plan.n, plan.k
    return sum(gemm_seconds(m, n, k * width, co, item) for m, width in
               _products(plan, merged, rows))


#: The phases of L - 1 lags are merged into the product of those with L while the lags
#: computed in vain stay under this share of that product's output. Measured (OpenBLAS,
#: one thread, K = 40, N = 2047, 80 or 160 columns): merging at L = 17 with 2 of 4 phases
#: short (2.9 % in vain) took 0.89-0.92x the two products in float32 and 0.94-0.98x in
#: float64 (a second product packs a second Hankel block and runs on half the rows);
#: L = 5 (10 %) tied; L = 2 with 1 short (12.5 %) took 1.01-1.06x.
MERGE_WASTE = 1 / 8

#: Cache bytes per element of a Hankel block built on a call (a gathered int8 cast to a
#: float), charged where the blocks are not kept (:data:`HANKEL_BYTES`).
BUILD_BYTES = 16.0

#: Bytes of output scattered per step: the 4 phases writing every 4th lag of a paper frame
#: (3.4 MB of int64) took 0.58-0.82 ms in one pass each, 0.41-0.45 ms in steps of 12
#: columns (this size), on the 2-core development machine.
SCATTER_BYTES = 1 << 18

#: The Hankel blocks of one float type are prepared once and kept while they take at most
#: this many bytes (every group's together); beyond it (a degree-15 code, 400 channels and
#: a 64-lag gate at S = 2 would keep 3.4 GB of them, and a bench process reached 6 GB) the
#: kernel builds them on every call in chunks of channels of at most HANKEL_BYTES / 8
#: bytes each, in a per-thread buffer: its memory is then O(chunk N), whatever K, and the
#: cost model charges the build (:meth:`MatmulCorrelator.estimate`).
HANKEL_BYTES = 256 << 20


def _hankel_width(plan: GatePlan) -> int:
    """Offsets of every product's Hankel block together (K times this many rows of N)."""
    return sum(w for _, w in _products(plan, phase_groups(plan), 1))


def _cached(plan: GatePlan, item: float) -> bool:
    """Whether the Hankel blocks of ``item``-byte floats are prepared once and kept."""
    return item * plan.k * _hankel_width(plan) * plan.n <= HANKEL_BYTES


def _chunk(plan: GatePlan, width: int, item: float) -> int:
    """Channels per Hankel block: all when the blocks are kept, else HANKEL_BYTES / 8."""
    if _cached(plan, item):
        return plan.k
    return max(1, min(plan.k, int(HANKEL_BYTES // 8 // (item * width * plan.n))))


def phase_groups(plan: GatePlan) -> bool:
    """Whether the phases of L - 1 lags are merged into the product of those with L.

    Merged: one product that computes one lag too many for each of those phases; split:
    two products, nothing wasted. Merged while the lags computed in vain are under
    :data:`MERGE_WASTE` of its output (always when every phase has L lags).
    """
    lens = _lengths(plan)
    top = max(lens.values())
    return sum(top - v for v in lens.values()) < MERGE_WASTE * top * len(lens)


class MatmulCorrelator(Correlator):
    """Rotated phase operands, one or two stacked Hankel products, float32 when provably
    exact, float64 otherwise, limb splitting for the 2^53 bound.

    ``products`` counts the products run per dtype name ("float32", "float64"), for tests
    and benchmarks.
    """

    #: its Python per call (buffers, float32 test, groups): 0.26 ms measured (costs.py)
    fixed_calls = 400.0
    takes_bound = True  # sum |d| per column proves float32 products without a look at Y

    @classmethod
    def estimate(cls, plan: GatePlan, co: Coefficients) -> Estimate:
        """The products, the operand copies and the output scatter.

        float32 is only counted on when ``N y_bound`` proves it for all data; otherwise
        the float64 products are predicted (the data may still allow float32).
        """
        c, n, k = plan.columns, plan.n, plan.k
        cb = min(c, _block(plan))
        single = plan.float32_certain()
        parts = 1 if single else plan.matmul_limbs()
        item = 4.0 if single else 8.0
        merged = phase_groups(plan)
        shapes = _products(plan, merged, cb)
        active = len(_lengths(plan))
        width = sum(m // cb * w for m, w in shapes)  # output columns per channel

        def block(rows: int) -> float:
            """One block of ``rows`` columns: products, copies, the float32 test."""
            prods = _seconds(plan, co, merged, rows, item)
            moves = co.byte * ((4.0 + item) * active * rows * n
                               + (item + 16.0) * rows * k * width) \
                + 4 * active * co.call  # per phase: a rotated copy in, a strided copy out
            # float32 bound test: on data too large for it, usually one phase copied, summed
            check = 0.0 if single or not plan.float32_limit() else \
                co.byte * 12.0 * rows * n + 6 * co.call
            return parts * (prods + moves + build) + check

        hankel = sum(w for _, w in shapes)
        kept = _cached(plan, item)
        # Hankel blocks beyond HANKEL_BYTES: built per block of columns and limb, each
        # element a gathered int8 cast to a float (BUILD_BYTES cache bytes)
        build = 0.0 if kept else co.byte * BUILD_BYTES * k * hankel * n \
            + co.call * 2 * k * len(shapes)
        full, rest = divmod(c, cb)  # the last block holds only the columns left
        seconds = full * block(cb) + (block(rest) if rest else 0.0) \
            + cls.fixed_calls * co.call
        chunk = k if kept else max(_chunk(plan, w, item) * w for _, w in shapes)
        peak = item * n * (k * hankel if kept else chunk) + item * active * cb * n \
            + item * cb * (k * width if kept else chunk) + 8.0 * c * k * plan.count
        return Estimate(seconds, peak)

    def __init__(self, plan: GatePlan) -> None:
        super().__init__(plan)
        lens = _lengths(plan)
        self._phases = list(lens)  # active phases r
        self._len = lens
        # phase r's first chip offset: its operand is rotated by it
        self._rot = {r: int(plan.u_m[plan.sel[r][0]]) % plan.n for r in lens}
        merged = phase_groups(plan)
        top = max(lens.values())
        # product groups: (offsets, phases), the phases of L lags first
        if merged:
            self._groups = [(top, list(lens))]
        else:
            self._groups = [(w, [r for r in lens if lens[r] == w])
                            for w in sorted(set(lens.values()), reverse=True)]
        self._hankels: dict[tuple[int, type], NDArray[np.floating]] = {}
        self._lock = threading.Lock()
        self._local = threading.local()  # per-thread operand and output buffers
        self.products: collections.Counter[str] = collections.Counter()
        for width, _ in self._groups:  # the float64 blocks now, float32 ones on first use
            if _cached(plan, 4 if plan.float32_certain() else 8):
                self._hankel(width, np.float32 if plan.float32_certain() else np.float64)

    def _fill_hankel(self, dst: NDArray[np.floating], k0: int, k1: int, width: int) -> None:
        """``dst[(k - k0) width + t, i] = bip_k[(i - q0 - t) mod N]`` for k0 <= k < k1, t <
        width: rows of channel k's codes rotated by ``q0 + t``, channel by channel (no
        (K, width, N) int8 copy; per channel a (width, N) int8 one)."""
        plan, n = self.plan, self.plan.n
        starts = (-plan.q0 - np.arange(width)) % n  # row t: the code from chip starts[t] on
        for kk in range(k0, k1):
            code = plan.bip[kk]
            windows = sliding_window_view(np.concatenate((code, code)), n)  # a view
            dst[(kk - k0) * width : (kk - k0 + 1) * width] = windows[starts]

    def _hankel(self, width: int, dtype: type
                ) -> Iterable[tuple[int, int, NDArray[np.floating]]]:
        """``B[i, k, t] = bip_k[(i - q0 - t) mod N]`` for t < width in chunks of channels:
        ``(k0, k1, an (N, (k1 - k0) width) view)`` each.

        Stored as its C-contiguous transpose (K width, N): BLAS reads it as a transposed
        operand, up to 1.7x faster than an (N, K width) matrix for products of few rows.
        Kept whole when the blocks fit :data:`HANKEL_BYTES`; else each chunk is built when
        the caller iterates to it, in one per-thread buffer (use it before the next).
        """
        plan, n = self.plan, self.plan.n
        if not _cached(plan, np.dtype(dtype).itemsize):
            return self._hankel_chunks(width, dtype)
        key = (width, dtype)
        b = self._hankels.get(key)
        if b is None:
            with self._lock:
                b = self._hankels.get(key)
                if b is None:
                    b = np.empty((plan.k * width, n), dtype=dtype)
                    self._fill_hankel(b, 0, plan.k, width)
                    self._hankels[key] = b
        return [(0, plan.k, b.T)]

    def _hankel_chunks(self, width: int, dtype: type
                       ) -> Iterator[tuple[int, int, NDArray[np.floating]]]:
        """The chunks of :meth:`_hankel` built one at a time in a per-thread buffer."""
        plan = self.plan
        step = _chunk(plan, width, np.dtype(dtype).itemsize)
        for k0 in range(0, plan.k, step):
            k1 = min(plan.k, k0 + step)
            b = self._buffer("hankel", ((k1 - k0) * width, plan.n), dtype)
            self._fill_hankel(b, k0, k1, width)
            yield k0, k1, b.T

    def _buffer(self, name: str, shape: tuple[int, int], dtype: type) -> NDArray[np.floating]:
        """A reused per-thread buffer (no fresh pages to fault in on every call)."""
        key = (name, dtype)
        bufs = self._local.__dict__.setdefault("bufs", {})
        work = bufs.get(key)
        size = shape[0] * shape[1]
        if work is None or work.size < size:
            work = bufs[key] = np.empty(size, dtype=dtype)
        return work[:size].reshape(shape)

    def _fill(self, lf: NDArray[np.floating], yb: NDArray[np.signedinteger],
              phases: list[int]) -> None:
        """Operand rows of ``phases``: ``lf[i cb + c, j] = Y[c, r_i, (j + a_r) mod N]``."""
        cb, _, n = yb.shape
        for i, r in enumerate(phases):
            a = self._rot[r]
            rows = lf[i * cb : (i + 1) * cb]
            np.copyto(rows[:, : n - a], yb[:, r, a:], casting="unsafe")
            if a:
                np.copyto(rows[:, n - a :], yb[:, r, :a], casting="unsafe")

    def _operands(self, yb: NDArray[np.signedinteger], dtype: type) -> list:
        """Every group's operand in ``dtype`` (the receiver spreads columns over threads)."""
        cb, _, n = yb.shape
        ops = []
        for g, (_, phases) in enumerate(self._groups):
            lf = self._buffer(f"op{g}", (len(phases) * cb, n), dtype)
            self._fill(lf, yb, phases)
            ops.append(lf)
        return ops

    def _float32_operands(self, yb: NDArray[np.signedinteger],
                          bound: NDArray[np.unsignedinteger] | None) -> list | None:
        """The float32 operands of every group when float32 products are exact, else None.

        Per column and phase the sum of ``|Y|`` over the N chips must stay below
        :meth:`GatePlan.float32_limit`. The caller's ``bound`` (an upper bound of those
        sums per column) proves it without a look when every column's is below the limit.
        Otherwise one row is looked at first: data too large for float32 is usually
        refused there, on its first 4096 chips (a refusal is always safe: float64 is
        exact), then every column and phase of the operands.
        """
        plan = self.plan
        limit = plan.float32_limit()
        if not limit:
            return None
        if plan.float32_certain() or (bound is not None and int(bound.max()) < limit):
            return self._operands(yb, np.float32)
        r0 = self._groups[0][1][0]
        # a part of one row whose sum of |Y| already reaches the limit refuses it cheaply
        if np.abs(yb[0, r0, :4096].astype(np.float64)).sum() >= limit:
            return None
        ops = self._operands(yb, np.float32)
        cb, _, n = yb.shape
        mag = self._buffer("abs", (cb, n), np.float32)
        for lf, (_, phases) in zip(ops, self._groups, strict=True):
            for i in range(len(phases)):
                np.abs(lf[i * cb : (i + 1) * cb], out=mag)
                # a float32 sum (any order) of these integers decides "< limit" exactly:
                # partial sums below limit <= 2^24 are exact, and rounding is monotone,
                # so a partial sum reaching limit (or a |Y| >= 2^24, which cannot have
                # rounded below 2^24) leaves the computed total >= limit
                if np.add.reduce(mag, axis=-1).max() >= limit:
                    return None
        return ops

    def _run(self, operands: list, dst: NDArray[np.int64], dtype: type, shift: int,
             single: bool, first: bool) -> None:
        """Run each group's product and scatter its lags into ``dst`` (cb, K, count)."""
        plan = self.plan
        cb = dst.shape[0]
        s = plan.s
        for g, ((width, phases), lf) in enumerate(zip(self._groups, operands, strict=True)):
            for k0, k1, hankel in self._hankel(width, dtype):
                kc = k1 - k0
                o = self._buffer(f"out{g}", (lf.shape[0], kc * width), dtype)
                np.matmul(lf, hankel, out=o)  # exact integers (module doc)
                o4 = o.reshape(len(phases), cb, kc, width)
                # the phases interleave in dst's lags: a few columns at a time, so that
                # every phase's strided writes find those columns' lines of dst cached
                step = max(1, SCATTER_BYTES // (8 * kc * plan.count))
                for c0 in range(0, cb, step):
                    for i, r in enumerate(phases):
                        sel = plan.sel[r]
                        # phase r's lags: strided
                        d = dst[c0 : c0 + step, k0:k1, int(sel[0]) :: s]
                        src = o4[i, c0 : c0 + step, :, : self._len[r]]
                        if single:
                            np.copyto(d, src, casting="unsafe")  # exact: an exact cast
                        elif first:
                            np.left_shift(src.astype(np.int64), shift, out=d)
                        else:
                            d += src.astype(np.int64) << shift
            with self._lock:  # called from several column threads at once
                self.products[np.dtype(dtype).name] += 1

    def __call__(self, y: NDArray[np.signedinteger],
                 bound: NDArray[np.unsignedinteger] | None = None) -> NDArray[np.int64]:
        plan = self.plan
        c = y.shape[0]
        k, count = plan.k, plan.count
        block = _block(plan)
        out = np.empty((c, k, count), dtype=np.int64)
        for c0 in range(0, c, block):
            yb = y[c0 : c0 + block]
            cb = yb.shape[0]
            dst = out[c0 : c0 + cb]
            ops32 = self._float32_operands(yb, None if bound is None else
                                           bound[c0 : c0 + cb])
            if ops32 is not None:
                self._run(ops32, dst, np.float32, 0, True, True)
                continue
            parts = product_limbs(plan, yb)
            for i, (limb, shift) in enumerate(parts):
                ops = self._operands(limb, np.float64)
                self._run(ops, dst, np.float64, shift, len(parts) == 1, i == 0)
        return out
