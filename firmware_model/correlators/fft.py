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

from cdma_lidar.errors import out_of_range
from cdma_lidar.firmware_model.correlators.base import (
    BLOCK_BYTES,
    Correlator,
    GatePlan,
    limbs,
)
from cdma_lidar.firmware_model.correlators.costs import Coefficients, Estimate

__all__ = ["FFTCorrelator", "fft_length"]

_EPS = float(np.finfo(np.float64).eps)
_FFT_GUARD = 0.25
_FFT_CONST = 16.0
_FFT_BLOCK_BYTES = 16 << 20  # spectra x channels per inverse-FFT batch


def fft_length(n: int) -> int:
    """The power-of-two transform length L >= 2N the kernel uses for N-chip codes."""
    return 1 << (2 * n - 1).bit_length()


def _blocks(k: int, big: int) -> tuple[int, int]:
    """(phases, channels) per inverse-FFT batch of length ``big``: within 16 MiB."""
    units = max(1, _FFT_BLOCK_BYTES // ((big // 2 + 1) * 16 + big * 8))
    return (max(1, units // k), k) if units >= k else (1, units)


def _unit_bound(n: int, big: int) -> float:
    """The error bound for one unit of |Y| (every |Y| = 1): the guard's scale."""
    mu = _FFT_CONST * math.log2(big) * _EPS
    return mu * (math.sqrt(n) * 2 * n + 2.0 * n * math.sqrt(2.0 * n)) * 1.0001


def _fft_limbs(plan: GatePlan) -> int:
    """Limbs the guard will split Y into when |Y| reaches ``plan.y_bound`` (estimate)."""
    if plan.y_bound is None:
        return 1
    guard = _FFT_GUARD * 2.0 ** (plan.float_bits - 53)
    unit = _unit_bound(plan.n, fft_length(plan.n))
    if unit * plan.y_bound < guard:
        return 1
    h = max(1, math.floor(math.log2(guard / unit)))
    return 1 + math.ceil((plan.y_bound.bit_length() - h) / h)


class FFTCorrelator(Correlator):
    """Real FFTs of the doubled chip sums, ``rint`` under a rigorous error bound."""

    #: its Python per call (error bound, blocks, transforms' set-up): 0.43 ms measured
    fixed_calls = 660.0

    @classmethod
    def estimate(cls, plan: GatePlan, co: Coefficients) -> Estimate:
        """Per column and limb: a forward transform per active phase, an inverse per phase
        and channel, the spectrum products and the extraction of the gated lags."""
        big = fft_length(plan.n)
        half = big // 2 + 1
        k = plan.k
        active = sum(1 for sel in plan.sel if len(sel))
        sb, kb = _blocks(plan.k, big)
        pts = big * math.log2(big)
        spectra = 16.0 * k * half
        cached = spectra <= BLOCK_BYTES  # code spectra made once, else per phase pass
        whole = active * half * 16 <= BLOCK_BYTES
        passes = 1 if whole else math.ceil(active / sb)
        per_limb = (co.fft * pts * (active + active * k + (0 if cached else k * passes))
                    + co.byte * (16.0 * 3 * active * k * half + 8.0 * 3 * active * k * big)
                    + co.call * (passes * (2 + 3 * math.ceil(k / kb))
                                 + 6 * active * math.ceil(k / kb)))
        parts = _fft_limbs(plan)
        seconds = plan.columns * parts * (per_limb + 40 * co.call) \
            + cls.fixed_calls * co.call  # + its Python per column, and per call
        rows = active if whole else sb
        # + the doubled phases in float64 and scipy's zero-padded copy of them (3 x 8 L
        # per phase row), and the error bound's |Y| and |Y|^2 in float64 (2 x 8 S N)
        peak = (spectra if cached else 16.0 * kb * half) \
            + 16.0 * rows * half + 16.0 * sb * kb * half \
            + 8.0 * sb * kb * big + 16.0 * sb * plan.n + 8.0 * plan.columns * k * plan.count \
            + 24.0 * rows * big + 16.0 * plan.s * plan.n
        return Estimate(seconds, peak)

    def __init__(self, plan: GatePlan) -> None:
        super().__init__(plan)
        self.fft_len = fft_length(plan.n)
        self._spec: NDArray[np.complex128] | None = None

    def _spectra(self, k0: int, k1: int) -> NDArray[np.complex128]:
        from scipy import fft as sfft  # deferred: 130 ms at start-up for one kernel's use

        bip = self.plan.bip
        nbytes = self.plan.k * (self.fft_len // 2 + 1) * 16
        if nbytes <= BLOCK_BYTES:
            if self._spec is None:
                spec = sfft.rfft(bip.astype(np.float64), self.fft_len, axis=1)
                self._spec = np.conjugate(spec, out=spec)
            return self._spec[k0:k1]
        spec = sfft.rfft(bip[k0:k1].astype(np.float64), self.fft_len, axis=1)
        return np.conjugate(spec, out=spec)

    def _bound(self, v: NDArray[np.int64]) -> float:
        """Upper bound of |computed - exact| for correlating bip with [v, v] (each row)."""
        va = np.abs(v).astype(np.float64)
        l1 = 2.0 * float(va.sum(axis=-1).max(initial=0.0))
        l2 = math.sqrt(2.0 * float((va * va).sum(axis=-1).max(initial=0.0)))
        n = self.plan.n
        mu = _FFT_CONST * math.log2(self.fft_len) * _EPS
        return mu * (math.sqrt(n) * l1 + 2.0 * n * l2) * 1.0001 + 1e-300

    def limb_width(self) -> int:
        """Bits h of the low limbs when the bound forces a split (raises if none would do)."""
        plan = self.plan
        guard = _FFT_GUARD * 2.0 ** (plan.float_bits - 53)
        h = math.floor(math.log2(guard / _unit_bound(plan.n, self.fft_len)))
        if h < 1:
            raise out_of_range("float_bits", "large enough for an exact FFT", plan.float_bits)
        return h

    @staticmethod
    def _extract(dst: NDArray[np.int64], x: NDArray[np.float64], rs: list[int],
                 runs: dict, shift: int) -> None:
        """Add the rounded lags of phases ``rs`` from ``x`` (len(rs), Kb, L) into ``dst``."""
        for j, r in enumerate(rs):  # x[j]: (Kb, L), lags of phase r
            sl1, q1, n1, sl2, n2 = runs[r]
            for sl, q, cnt in ((sl1, q1, n1), (sl2, 0, n2)):
                if cnt:
                    d = dst[:, sl]
                    if shift:
                        d += x[j, :, q : q + cnt].astype(np.int64) << shift
                    else:
                        d += x[j, :, q : q + cnt].astype(np.int64)

    def blocks(self) -> tuple[int, int]:
        """(phases, channels) per inverse-FFT batch: the batch stays within 16 MiB."""
        return _blocks(self.plan.k, self.fft_len)

    def __call__(self, y: NDArray[np.signedinteger]) -> NDArray[np.int64]:
        from scipy import fft as sfft  # deferred: 130 ms at start-up for one kernel's use

        plan = self.plan
        c, s, n = y.shape
        big = self.fft_len
        guard = _FFT_GUARD * 2.0 ** (plan.float_bits - 53)
        h = self.limb_width()
        sb, kb = self.blocks()
        out = np.zeros((c, plan.k, plan.count), dtype=np.int64)
        active = [r for r in range(s) if len(plan.sel[r])]  # phases holding gated lags
        # phase r's lags m = m_r, m_r + S, ... (a strided slice of out) need the chip
        # offsets q = (q0 + u_m) mod N, consecutive mod N: at most two runs of x
        runs = {}
        for r in active:
            sel = plan.sel[r]
            q_start = int((plan.q0 + plan.u_m[sel[0]]) % n)
            first = min(len(sel), n - q_start)
            runs[r] = (slice(int(sel[0]), int(sel[0]) + s * first, s), q_start, first,
                       slice(int(sel[0]) + s * first, None, s), len(sel) - first)
        # the phases' spectra: all at once when they fit (then each block of code
        # spectra is made once per column), else in batches of sb phases
        whole = len(active) * (big // 2 + 1) * 16 <= BLOCK_BYTES
        pb = len(active) if whole else sb
        for ci in range(c):
            yc = y[ci]  # (S, N)
            for limb, shift in limbs(yc, lambda v: self._bound(v) < guard, h):
                for i0 in range(0, len(active), pb):
                    rs_all = active[i0 : i0 + pb]
                    part = limb[rs_all].astype(np.float64)
                    spec_all = sfft.rfft(np.concatenate([part, part], axis=1), big, axis=1)
                    del part
                    for k0 in range(0, plan.k, kb):
                        k1 = min(plan.k, k0 + kb)
                        a = self._spectra(k0, k1)
                        for j0 in range(0, len(rs_all), sb):
                            rs, spec = rs_all[j0 : j0 + sb], spec_all[j0 : j0 + sb]
                            x = sfft.irfft(a[None, :, :] * spec[:, None, :], big, axis=2)
                            np.rint(x, out=x)
                            self._extract(out[ci, k0:k1], x, rs, runs, shift)
        return out
