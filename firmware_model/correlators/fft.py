"""Exact FFT kernel (``method="fft"``): long gates, e.g. the whole period.

Linear correlation of ``bip_k`` with ``[Y_r, Y_r]`` through power-of-two real FFTs of
length ``L >= 2N``, rounded to the nearest integer. Exact when the float error is
below 1/2; a rigorous bound (Higham, "Accuracy and Stability", section 24.1, with a
generous constant) ``16 log2(L) eps (|a|_2 |y|_1 + 2 |a|_1 |y|_2)`` must stay below
1/4 (scaled by ``2^(float_bits - 53)``), else ``y`` is split into limbs until every
limb passes. Measured errors are 10^3..10^7 times below the bound.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray
from scipy import fft as sfft

from cdma_lidar.errors import out_of_range
from cdma_lidar.firmware_model.correlators.base import (
    BLOCK_BYTES,
    Correlator,
    GatePlan,
    limbs,
)

__all__ = ["FFTCorrelator", "fft_length"]

_EPS = float(np.finfo(np.float64).eps)
_FFT_GUARD = 0.25
_FFT_CONST = 16.0
_FFT_BLOCK_BYTES = 16 << 20  # spectra x channels per inverse-FFT batch
_FFT_COST_FACTOR = 8.0  # BLAS throughput / FFT throughput, per "operation" of the cost


def fft_length(n: int) -> int:
    """The power-of-two transform length L >= 2N the kernel uses for N-chip codes."""
    return 1 << (2 * n - 1).bit_length()


class FFTCorrelator(Correlator):
    """Real FFTs of the doubled chip sums, ``rint`` under a rigorous error bound."""

    @classmethod
    def cost(cls, plan: GatePlan) -> float:
        """``(K + 1) L log2(L)`` times the BLAS/FFT throughput ratio (8), per column."""
        big = fft_length(plan.n)
        return (plan.k + 1) * big * math.log2(big) * _FFT_COST_FACTOR

    def __init__(self, plan: GatePlan) -> None:
        super().__init__(plan)
        self.fft_len = fft_length(plan.n)
        self._spec: NDArray[np.complex128] | None = None

    def _spectra(self, k0: int, k1: int) -> NDArray[np.complex128]:
        bip = self.plan.bip
        nbytes = self.plan.k * (self.fft_len // 2 + 1) * 16
        if nbytes <= BLOCK_BYTES:
            if self._spec is None:
                self._spec = np.conj(sfft.rfft(bip.astype(np.float64), self.fft_len, axis=1))
            return self._spec[k0:k1]
        return np.conj(sfft.rfft(bip[k0:k1].astype(np.float64), self.fft_len, axis=1))

    def _bound(self, v: NDArray[np.int64]) -> float:
        """Upper bound of |computed - exact| for correlating bip with [v, v] (each row)."""
        va = np.abs(v).astype(np.float64)
        l1 = 2.0 * float(va.sum(axis=-1).max(initial=0.0))
        l2 = math.sqrt(2.0 * float((va * va).sum(axis=-1).max(initial=0.0)))
        n = self.plan.n
        mu = _FFT_CONST * math.log2(self.fft_len) * _EPS
        return mu * (math.sqrt(n) * l1 + 2.0 * n * l2) * 1.0001 + 1e-300

    def __call__(self, y: NDArray[np.int64]) -> NDArray[np.int64]:
        plan = self.plan
        c, s, n = y.shape
        big = self.fft_len
        guard = _FFT_GUARD * 2.0 ** (plan.float_bits - 53)
        mu = _FFT_CONST * math.log2(big) * _EPS
        unit = mu * (math.sqrt(n) * 2 * n + 2.0 * n * math.sqrt(2.0 * n)) * 1.0001
        h = math.floor(math.log2(guard / unit))
        if h < 1:
            raise out_of_range("float_bits", "large enough for an exact FFT", plan.float_bits)
        kb = max(1, _FFT_BLOCK_BYTES // (s * (big // 2 + 1) * 16 + s * big * 8))
        out = np.zeros((c, plan.k, plan.count), dtype=np.int64)
        sel = plan.sel
        qs = [(plan.q0 + plan.u_m[m]) % n for m in sel]
        for ci in range(c):
            yc = y[ci]  # (S, N)
            for limb, shift in limbs(yc, lambda v: self._bound(v) < guard, h):
                spec = sfft.rfft(np.concatenate([limb, limb], axis=1).astype(np.float64), big,
                                 axis=1)  # (S, L/2+1)
                for k0 in range(0, plan.k, kb):
                    k1 = min(plan.k, k0 + kb)
                    a = self._spectra(k0, k1)
                    x = sfft.irfft(a[None, :, :] * spec[:, None, :], big, axis=2)  # (S, Kb, L)
                    for r in range(s):
                        if len(sel[r]):
                            vals = np.rint(x[r][:, qs[r]]).astype(np.int64) << shift
                            out[ci][k0:k1, sel[r]] += vals  # (Kb, lags of phase r)
        return out

