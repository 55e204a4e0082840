"""Exact float64 matrix-product kernel (``method="matmul"``): short gates, many columns.

Per phase r: ``Y_r (C, N) @ B_r (N, K * nq_r)`` in float64 with the constant Hankel
block ``B_r[m, k, u] = bip_k[(m - q0 - u) mod N]`` holding only the chip lags that
phase needs. Every product is +-y and every partial sum is bounded by ``N * max|y|``;
when that is below ``2^float_bits`` (<= 2^53) the BLAS result is the exact integer
whatever the summation order. Otherwise ``y`` is split into limbs of h bits
(``N * 2^h < 2^float_bits``), each product exact, recombined in int64 (the result
fits: W_raw <= 56 bits, docs/firmware.md section 3).
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from cdma_lidar.firmware_model.correlators.base import (
    BLOCK_BYTES,
    Correlator,
    GatePlan,
    limbs,
)

__all__ = ["MatmulCorrelator"]

#: Largest Hankel matrix (bytes) ``"auto"`` will build; beyond it the FFT is chosen.
_MATMUL_BMAT_BYTES = 128 << 20


class MatmulCorrelator(Correlator):
    """Hankel blocks per phase, float64 GEMM, limb splitting for the 2^53 bound."""

    @classmethod
    def cost(cls, plan: GatePlan) -> float:
        """Multiply-adds per column, ``N K count / S``; inf when the Hankel blocks are too big."""
        mm_ops = plan.n * plan.k * plan.count / plan.s
        mm_bytes = plan.n * plan.k * plan.count * 8
        return mm_ops if mm_bytes <= _MATMUL_BMAT_BYTES else float("inf")

    def __init__(self, plan: GatePlan) -> None:
        super().__init__(plan)
        n, bip = plan.n, plan.bip
        # one Hankel block per phase r holding only the chip lags that phase needs
        self.bmat = []
        for sel in plan.sel:
            u = plan.u_m[sel]
            idx = (np.arange(n)[:, None] - plan.q0 - u[None, :]) % n  # (N, nq_r)
            self.bmat.append(np.ascontiguousarray(
                bip[:, idx].transpose(1, 0, 2).reshape(n, plan.k * len(u)), dtype=np.float64
            ))

    def __call__(self, y: NDArray[np.int64]) -> NDArray[np.int64]:
        plan = self.plan
        c, s, n = y.shape
        count = plan.count
        limit = 1 << plan.float_bits
        h = plan.float_bits - n.bit_length()
        per_col = s * n * 8 * 2 + plan.k * count * 16
        block = max(1, BLOCK_BYTES // per_col)
        out = np.zeros((c, plan.k, count), dtype=np.int64)
        for c0 in range(0, c, block):
            yb = y[c0 : c0 + block]
            cb = yb.shape[0]
            acc = out[c0 : c0 + cb]
            for limb, shift in limbs(yb, lambda v: n * int(np.abs(v).max(initial=0)) < limit, h):
                lf = limb.astype(np.float64)  # exact: |limb| < 2^53
                for r, sel in enumerate(plan.sel):
                    if len(sel):
                        o = lf[:, r, :] @ self.bmat[r]  # (cb, K * nq_r), exact integers
                        o = o.reshape(cb, plan.k, len(sel)).astype(np.int64)
                        acc[:, :, sel] += o << shift
        return out

