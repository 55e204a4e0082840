r"""The compiled kernel of ``accumulated`` fidelity's tabulated echoes (numba: the ``fast``
extra).

:meth:`cdma_lidar.scene.instrument.Instrument._tabulated_echoes` adds each echo term k
(in the batch's order) into its row of the flat batch ``y`` from its Gold member's flat
waveform table: two BLAS saxpy calls, ``y += a_k w_p`` then ``y += b_k w_(p+1)``::

    row = y[y_at[k] : y_at[k] + L]
    w0  = table[x_at[k] : x_at[k] + L]           (phase p, rotated by the delay)
    w1  = table[x_at[k] + 2L : x_at[k] + 3L]     (phase p + 1)
    row[j] = fma(b_k, w1[j], fma(a_k, w0[j], row[j]))      j = 0 .. L - 1

This kernel does both in one pass over the row, each step a fused multiply-add rounded
once to float32, which is what BLAS's saxpy computes on hardware with FMA (OpenBLAS's
x86-64 and ARM kernels), and skips a zero coefficient as BLAS does. So the values are
those of the saxpy path wherever BLAS fuses; tests/scene/test_echo_kernel.py checks it
where a probe finds that it does. One pass instead of two, and no Python call per term.

Without numba, :func:`terms_kernel` returns None and the caller calls saxpy.
"""

from __future__ import annotations

import functools
from collections.abc import Callable

import numpy as np
from numpy.typing import NDArray

from cdma_lidar.scene.noise_kernel import compile_kernel

__all__ = ["terms_kernel"]

def _terms(table: NDArray[np.float32], x_at: NDArray[np.int64], y_at: NDArray[np.int64],
           a: NDArray[np.float32], b: NDArray[np.float32], y: NDArray[np.float32],
           length: int) -> None:
    """The kernel's source (numba compiles it, ``_fma`` then its fused multiply-add)."""
    two = 2 * length
    if length < 1 or x_at.size != y_at.size or a.size != x_at.size or b.size != x_at.size:
        raise ValueError("one offset pair and two coefficients per term, length >= 1")
    for k in range(x_at.size):
        x0, y0 = x_at[k], y_at[k]
        if x0 < 0 or x0 + two + length > table.size or y0 < 0 or y0 + length > y.size:
            raise ValueError("a term reaches outside its table or the batch")
        row = y[y0:y0 + length]
        w0 = table[x0:x0 + length]
        w1 = table[x0 + two:x0 + two + length]
        ak, bk = a[k], b[k]
        if ak != 0 and bk != 0:  # both saxpy calls, fused into one pass over the row
            for j in range(length):
                row[j] = _fma(bk, w1[j], _fma(ak, w0[j], row[j]))
        elif ak != 0:  # BLAS skips a zero coefficient: so do we
            for j in range(length):
                row[j] = _fma(ak, w0[j], row[j])
        elif bk != 0:
            for j in range(length):
                row[j] = _fma(bk, w1[j], row[j])


def _fma(a: float, b: float, c: float) -> float:
    """Set to the compiled fused multiply-add by :func:`terms_kernel` (numba's intrinsic)."""
    raise NotImplementedError("compiled by terms_kernel")


@functools.cache
def terms_kernel() -> Callable[..., None] | None:
    """``_terms`` compiled for float32 tables and batches (None without numba).

    The signature is fixed (read-only float32 table and coefficients, int64 offsets, a
    writable float32 batch, an int64 length): other types are refused, not converted.
    Compiled once per process and cached on disk by numba (in memory only where it
    finds no writable folder for the cache).
    """
    def signature(t: object, readonly: Callable[..., object]) -> object:
        from numba.extending import intrinsic  # present: compile_kernel imported numba

        @intrinsic
        def fma32(typingctx, a, b, c):  # numba's intrinsic protocol
            def codegen(context, builder, signature, args):
                return builder.fma(*args)  # llvm.fma.f32: one rounding, as BLAS's FMA

            return t.float32(t.float32, t.float32, t.float32), codegen

        global _fma  # numba reads it when it compiles _terms (or loads it from its cache)
        _fma = fma32
        return t.void(readonly(t.float32), readonly(t.int64), readonly(t.int64),
                      readonly(t.float32), readonly(t.float32), t.Array(t.float32, 1, "C"),
                      t.int64)

    return compile_kernel(_terms, signature, "accumulated echoes call BLAS saxpy")
