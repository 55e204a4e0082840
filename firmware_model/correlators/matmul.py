"""Exact float64 matrix-product kernel (``method="matmul"``): short gates, many columns.

Per phase r: ``Y_r (C, N) @ B_r (N, K * nq_r)`` in float64 with the constant Hankel
block ``B_r[m, k, u] = bip_k[(m - q0 - u) mod N]`` holding only the chip lags that
phase needs (or the S phases stacked into one product, :func:`stacked_layout`).
Every product is +-y and every partial sum is bounded by ``N * max|y|``;
when that is below ``2^float_bits`` (<= 2^53) the BLAS result is the exact integer
whatever the summation order. Otherwise ``y`` is split into limbs of h bits
(``N * 2^h < 2^float_bits``), each product exact, recombined in int64 (the result
fits: W_raw <= 56 bits, docs/firmware.md section 3).
"""

from __future__ import annotations

import math
import threading

import numpy as np
from numpy.typing import NDArray

from cdma_lidar.firmware_model.correlators.base import (
    BLOCK_BYTES,
    Correlator,
    GatePlan,
    limbs,
)
from cdma_lidar.firmware_model.correlators.costs import Coefficients, Estimate, gemm_seconds

__all__ = ["MatmulCorrelator", "stacked_layout"]


def _block(plan: GatePlan) -> int:
    """Columns per block: chip sums, float operands and output within BLOCK_BYTES."""
    return max(1, BLOCK_BYTES // (plan.s * plan.n * 8 * 2 + plan.k * (plan.count + 2 * plan.s)
                                  * 16))


def stacked_layout(plan: GatePlan) -> bool:
    """Whether one product of the S phases stacked beats S per-phase products.

    Stacked: ``[Y_0; ...; Y_{S-1}] (S C, N) @ B (N, K nq)`` with one Hankel block of
    every chip offset u < nq, ``S nq`` output columns per channel for ``count`` lags.
    It wastes ``S nq - count`` columns (at most 2 S - 1) but makes one large product
    instead of S small ones: taken when the waste is under 1/16 of the work.
    """
    return plan.s > 1 and 16 * (plan.s * plan.nq - plan.count) <= plan.count


class MatmulCorrelator(Correlator):
    """Hankel blocks, float64 GEMM, limb splitting for the 2^53 bound.

    Two layouts of the same products (:func:`stacked_layout`): per phase r,
    ``Y_r (C, N) @ B_r (N, K nq_r)`` holding only the chip lags phase r needs; or the
    S phases stacked into one ``(S C, N) @ (N, K nq)`` product when that wastes little.
    """

    @classmethod
    def estimate(cls, plan: GatePlan, co: Coefficients) -> Estimate:
        """The products of the chosen layout, the operand copies and the output scatter."""
        c, n, k, s = plan.columns, plan.n, plan.k, plan.s
        cb = min(c, _block(plan))
        blocks = math.ceil(c / cb)
        parts = plan.matmul_limbs()
        if stacked_layout(plan):
            width, hankel = plan.s * plan.nq, plan.nq  # output and Hankel columns / channel
            prods = gemm_seconds(s * cb, n, k * plan.nq, co)
        else:
            width = hankel = plan.count
            prods = sum(gemm_seconds(cb, n, k * len(sel), co) for sel in plan.sel if len(sel))
        active = sum(1 for sel in plan.sel if len(sel))
        moves = co.byte * (16.0 * s * cb * n + 24.0 * cb * k * width) + 4 * active * co.call
        seconds = blocks * parts * (prods + moves) + 4 * co.call
        peak = 8.0 * n * k * hankel + 8.0 * s * cb * n + 8.0 * cb * k * width \
            + 8.0 * c * k * plan.count
        return Estimate(seconds, peak)

    def __init__(self, plan: GatePlan) -> None:
        super().__init__(plan)
        n, bip = plan.n, plan.bip
        self.stacked = stacked_layout(plan)
        offsets = [np.arange(plan.nq)] if self.stacked else [plan.u_m[sel] for sel in plan.sel]
        # one Hankel block per phase r (or one for all) holding only the chip offsets needed
        self.bmat = []
        for u in offsets:
            idx = (np.arange(n)[:, None] - plan.q0 - u[None, :]) % n  # (N, nq_r)
            b = np.empty((n, plan.k, len(u)))  # filled channel by channel: no int8 copies
            for kk in range(plan.k):
                b[:, kk, :] = bip[kk][idx]
            self.bmat.append(b.reshape(n, plan.k * len(u)))
        self._local = threading.local()  # per-thread operand buffer: calls may overlap

    def _buffer(self, rows: int, n: int) -> NDArray[np.float64]:
        """A (rows, n) float64 operand buffer, reused across calls (no fresh pages)."""
        work = getattr(self._local, "work", None)
        if work is None or work.size < rows * n:
            work = self._local.work = np.empty(rows * n)
        return work[: rows * n].reshape(rows, n)

    def __call__(self, y: NDArray[np.signedinteger]) -> NDArray[np.int64]:
        plan = self.plan
        c, s, n = y.shape
        k, count = plan.k, plan.count
        limit = 1 << plan.float_bits
        h = plan.float_bits - n.bit_length()
        block = _block(plan)
        out = np.empty((c, k, count), dtype=np.int64)
        # lags of phase r are m = m_r, m_r + S, ...: a strided slice of the output
        sl = [slice(int(sel[0]), None, s) if len(sel) else None for sel in plan.sel]
        bound_ok = plan.y_bound is not None and n * plan.y_bound < limit

        def fits(v: NDArray[np.signedinteger]) -> bool:
            return bound_ok or n * int(np.abs(v).max(initial=0)) < limit

        def put(dst: NDArray[np.int64], o: NDArray[np.float64], i: int, shift: int,
                single: bool) -> None:
            if single:
                dst[...] = o  # exact integers: the cast to int64 is exact
            elif i == 0:
                dst[...] = o.astype(np.int64) << shift
            else:
                dst += o.astype(np.int64) << shift

        for c0 in range(0, c, block):
            yb = y[c0 : c0 + block]
            cb = yb.shape[0]
            acc = out[c0 : c0 + cb]
            parts = limbs(yb, fits, h)
            single = len(parts) == 1
            for i, (limb, shift) in enumerate(parts):
                # exact: |limb| < 2^53 and every partial sum < 2^float_bits
                if self.stacked:
                    lf = self._buffer(s * cb, n)
                    # one pass (0.3 ms for the paper frame; split across threads it was 0.6)
                    np.copyto(lf.reshape(s, cb, n), limb.transpose(1, 0, 2))
                    o = (lf @ self.bmat[0]).reshape(s, cb, k, plan.nq)
                    for r, sel in enumerate(plan.sel):
                        if len(sel):
                            u0 = int(plan.u_m[sel[0]])
                            put(acc[:, :, sl[r]], o[r, :, :, u0 : u0 + len(sel)], i, shift,
                                single)
                    continue
                lf = self._buffer(cb, n)
                for r, sel in enumerate(plan.sel):
                    if len(sel):
                        np.copyto(lf, limb[:, r, :])
                        o = (lf @ self.bmat[r]).reshape(cb, k, len(sel))  # (cb, K, nq_r)
                        put(acc[:, :, sl[r]], o, i, shift, single)
        return out
