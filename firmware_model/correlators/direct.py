"""Exact per-lag kernel (``method="direct"``): short gates on long codes, little memory.

For each gated lag m (phase r_m, chip offset q_m = (q0 + u_m) mod N) one float64
product of the doubled chip sums' window with the codes::

    raw[:, :, m] = [Y_r, Y_r][:, q_m : q_m + N] (C, N) @ bip.T (N, K)

The window is a strided view (no copy), the codes are kept once as an (N, K)
float64 matrix: memory ``8 N K + 16 C N`` bytes whatever the gate, where the Hankel
blocks of :mod:`.matmul` take ``8 N K (G + 2)``. Exactness as in :mod:`.matmul`:
every partial sum is bounded by ``N max|Y|``, split into limbs when that reaches
``2^float_bits``.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from cdma_lidar.firmware_model.correlators.base import (
    BLOCK_BYTES,
    Correlator,
    GatePlan,
    product_limbs,
)
from cdma_lidar.firmware_model.correlators.costs import (
    CACHE_BYTES,
    PACK_BYTES,
    Coefficients,
    Estimate,
    packs,
    stream_bytes,
)

__all__ = ["DirectCorrelator"]


def _block(plan: GatePlan) -> int:
    """Columns per block: the doubled chip sums of one phase, float64, within BLOCK_BYTES."""
    return max(1, BLOCK_BYTES // (16 * plan.n + 8 * plan.k * plan.count))


def _store_bytes(rows: int, count: int, ram: float) -> float:
    """Cache-byte equivalents of writing ``count`` lags, one lag at a time, into ``rows``
    int64 rows of ``count`` (the kernel's ``out[:, :, m] = o``).

    Within the cache, a read and a write of each value. Beyond it, every lag's store
    reaches each row's cache line anew: a whole line (64 bytes, or the row when shorter)
    comes in and goes back out per value, from main memory. (Counting 16 bytes per value
    predicted 129 lags of 160 columns and 253 channels, 42 MB of output, at 13 ms where
    the kernel took 85 ms, and sent that plan to direct at 1.4-1.5x matmul's time.)
    """
    if 8.0 * rows * count <= CACHE_BYTES:
        return 16.0 * rows * count
    return 2.0 * min(64.0, 8.0 * count) * rows * count * ram


class DirectCorrelator(Correlator):
    """One (C, N) @ (N, K) product per gated lag on a window of the doubled chip sums."""

    #: its Python per call (limbs, doubled rows, output): 0.13 ms measured (costs.py)
    fixed_calls = 200.0

    @classmethod
    def estimate(cls, plan: GatePlan, co: Coefficients) -> Estimate:
        """Per lag a thin product; per phase a copy of the doubled chip sums."""
        c, n, k = plan.columns, plan.n, plan.k
        cb = min(c, _block(plan))
        parts = plan.matmul_limbs()
        active = sum(1 for sel in plan.sel if len(sel))

        def block(rows: int) -> float:
            """One block of ``rows`` columns, every lag and phase."""
            # the (K, N) codes, read on every lag
            codes = stream_bytes(8.0 * n * k, plan.count, co.ram, co.llc_bytes)
            if packs(rows, n, k):  # a product of several rows and channels packs both
                codes += PACK_BYTES * (rows * n + n * k) * plan.count  # operands (gemm_seconds)
            return (plan.count * (co.mac * rows * n * k + co.byte * 8.0 * (rows * n + rows * k)
                                  + 3 * co.call)  # slice, product, store
                    + co.byte * codes
                    + active * (co.byte * 8.0 * 3 * rows * n + 2 * co.call)
                    + co.byte * _store_bytes(rows * k, plan.count, co.ram))

        full, rest = divmod(c, cb)  # the last block holds only the columns left
        seconds = parts * (full * block(cb) + (block(rest) if rest else 0.0)) \
            + cls.fixed_calls * co.call
        peak = 8.0 * n * k + 16.0 * cb * n + 8.0 * c * k * plan.count + 8.0 * cb * k
        return Estimate(seconds, peak)

    def __init__(self, plan: GatePlan) -> None:
        super().__init__(plan)
        # (K, N) rows, used transposed: (C, N) @ (N, K) through BLAS's transposed operand
        # (a C-contiguous (N, K) matrix is ~50x slower for one column of a long code)
        self.bip_f = plan.bip.astype(np.float64)
        # chip offset of each gated lag m, q_m = (q0 + u_m) mod N: fixed by the plan
        self._q = [(plan.q0 + int(u)) % plan.n for u in plan.u_m]

    def __call__(self, y: NDArray[np.signedinteger]) -> NDArray[np.int64]:
        plan = self.plan
        c, _, n = y.shape
        k = plan.k
        block = _block(plan)
        out = np.empty((c, k, plan.count), dtype=np.int64)
        for c0 in range(0, c, block):
            yb = y[c0 : c0 + block]
            cb = yb.shape[0]
            acc = out[c0 : c0 + cb]
            parts = product_limbs(plan, yb)
            y2 = np.empty((cb, 2 * n))
            for i, (limb, shift) in enumerate(parts):
                for r, sel in enumerate(plan.sel):
                    if not len(sel):
                        continue
                    y2[:, :n] = limb[:, r, :]
                    y2[:, n:] = limb[:, r, :]
                    for m in sel.tolist():
                        q = self._q[m]
                        o = y2[:, q : q + n] @ self.bip_f.T  # (cb, K), exact integers
                        if len(parts) == 1:
                            acc[:, :, m] = o
                        elif i == 0:
                            acc[:, :, m] = o.astype(np.int64) << shift
                        else:
                            acc[:, :, m] += o.astype(np.int64) << shift
        return out
