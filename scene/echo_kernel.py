r"""The compiled kernels of the echoes (numba: the ``fast`` extra).

``accumulated``: :func:`terms_kernel`.
:meth:`cdma_lidar.scene.echoes.Echoes.tabulated_echoes` sets each row of the
flat batch ``y`` that the terms reach to ``start`` and adds each echo term k (in the
batch's order) into its row from its Gold member's waveform table (a stack of every
member's, flat): two BLAS saxpy calls, ``y += a_k w_p`` then ``y += b_k w_(p+1)``::

    row = y[y_at[k] : y_at[k] + L]               (y_at[k] a multiple of L)
    w0  = table[x_at[k] : x_at[k] + L]           (phase p, rotated by the delay)
    w1  = table[x_at[k] + 2L : x_at[k] + 3L]     (phase p + 1)
    row[j] = fma(b_k, w1[j], fma(a_k, w0[j], row[j]))      j = 0 .. L - 1

Each step is a fused multiply-add rounded once to float32, which is what BLAS's saxpy
computes on hardware with FMA (OpenBLAS's x86-64 and ARM kernels), and a zero
coefficient is skipped as BLAS skips it. So the values are those of the saxpy path
wherever BLAS fuses; tests/scene/test_echo_kernel.py checks it where a probe finds that
it does. A batch's terms come row by row, and the kernel takes a run of up to four
terms of one row (none with a zero coefficient) in one pass over the row, their eight
multiply-adds in the saxpy calls' order: the row is read and written once per four
terms (the saxpy path: twice per term), and set to ``start`` when its first term is
added (in the cache), not in a pass over the whole batch before. One call per batch.

``exact``: :func:`synthesis_kernel`, the per-channel work of the Fourier synthesis,
:meth:`cdma_lidar.scene.codebook.Codebook.sum_delayed` (its docstring has the
algebra) for complex128 sums, before the spectral weight. For each term k, in order, with
``x y`` numpy's complex product (re = fma(xr, yr, -(xi yi)), im = fma(xr, yi, xi yr):
numpy's SIMD loops fuse it so on every machine with FMA, which the tests probe)::

    u[p]  = (dft_k[p] lo_k[p % B]) hi_k[p // B]                  p = 0 .. period - 1
    out[row_k, j period + p]  (+)=  u[p]             (j = 0)
                                    u[p] turn_k,j    (j >= 1, while the bin is < m)

``(+)=``: the row's first term is written, later ones added. numpy does this as two
multiplies over the period, then a copy or an add, and a multiply and an add per further
period, each a call from Python: eight calls and passes per term, where the kernel makes
one call per batch and one pass per period. The same operations in the same order: the
same values bit for bit (tests/scene/test_echo_kernel.py).
:func:`single_synthesis_kernel` is the same source for complex64 sums (``accumulated``'s
echo where its waveform tables would not fit, e.g. ``paper-massive``): every product's
parts are float32 fused multiply-adds rounded to float32, as numpy's complex64 product,
and every intermediate stays complex64 (2.5 to 3 times faster than numpy's passes at
K = 1,200, N = 32,767).

Without numba both functions return None and the callers use BLAS (saxpy) or numpy.
"""

from __future__ import annotations

import functools
from collections.abc import Callable

import numpy as np
from numpy.typing import NDArray

from cdma_lidar.scene.noise_kernel import compile_kernel

__all__ = ["single_synthesis_kernel", "synthesis_kernel", "terms_kernel"]


def _terms(table: NDArray[np.float32], x_at: NDArray[np.int64], y_at: NDArray[np.int64],
           a: NDArray[np.float32], b: NDArray[np.float32], start: float,
           y: NDArray[np.float32], length: int) -> None:
    """The kernel's source (numba compiles it, ``_fma`` then its fused multiply-add)."""
    two = 2 * length
    if length < 1 or x_at.size != y_at.size or a.size != x_at.size or b.size != x_at.size:
        raise RuntimeError("one offset pair and two coefficients per term, length >= 1")
    for k in range(x_at.size):
        if x_at[k] < 0 or x_at[k] + two + length > table.size or y_at[k] < 0 \
                or y_at[k] + length > y.size or y_at[k] % length:
            raise RuntimeError("a term reaches outside its table or the batch, or starts "
                             "within a row")
    written = np.zeros(y.size // length, dtype=np.bool_)
    k = 0
    while k < x_at.size:
        y0 = y_at[k]
        row = y[y0:y0 + length]
        if not written[y0 // length]:  # the row's first term: set the row then (in cache)
            row[:] = start
            written[y0 // length] = True
        group = 0  # terms from k on that add into the same row, neither coefficient zero
        while group < 4 and k + group < x_at.size and y_at[k + group] == y0 \
                and a[k + group] != 0 and b[k + group] != 0:
            group += 1
        if group == 4:  # four terms, eight multiply-adds in order, one pass over the row
            (w0, w1), a0, b0 = _waves(table, x_at[k], length), a[k], b[k]
            (w2, w3), a1, b1 = _waves(table, x_at[k + 1], length), a[k + 1], b[k + 1]
            (w4, w5), a2, b2 = _waves(table, x_at[k + 2], length), a[k + 2], b[k + 2]
            (w6, w7), a3, b3 = _waves(table, x_at[k + 3], length), a[k + 3], b[k + 3]
            for j in range(length):
                v = _fma(b1, w3[j], _fma(a1, w2[j], _fma(b0, w1[j], _fma(a0, w0[j], row[j]))))
                row[j] = _fma(b3, w7[j], _fma(a3, w6[j], _fma(b2, w5[j], _fma(a2, w4[j], v))))
        elif group >= 2:  # two terms, as above
            group = 2
            (w0, w1), a0, b0 = _waves(table, x_at[k], length), a[k], b[k]
            (w2, w3), a1, b1 = _waves(table, x_at[k + 1], length), a[k + 1], b[k + 1]
            for j in range(length):
                row[j] = _fma(b1, w3[j], _fma(a1, w2[j], _fma(b0, w1[j], _fma(a0, w0[j],
                                                                                row[j]))))
        else:  # one term, a zero coefficient skipped as BLAS skips it
            group = 1
            (w0, w1), a0, b0 = _waves(table, x_at[k], length), a[k], b[k]
            if a0 != 0 and b0 != 0:
                for j in range(length):
                    row[j] = _fma(b0, w1[j], _fma(a0, w0[j], row[j]))
            elif a0 != 0:
                for j in range(length):
                    row[j] = _fma(a0, w0[j], row[j])
            elif b0 != 0:
                for j in range(length):
                    row[j] = _fma(b0, w1[j], row[j])
        k += group


def _waves(table: NDArray[np.float32], x0: int, length: int
           ) -> tuple[NDArray[np.float32], NDArray[np.float32]]:
    """A term's two table rows: phase p at ``x0`` and phase p + 1 two frames on."""
    return table[x0:x0 + length], table[x0 + 2 * length:x0 + 3 * length]


def _synthesis(spectra: NDArray[np.complexfloating], members: NDArray[np.int64],
               rows: NDArray[np.int64], lo: NDArray[np.complexfloating],
               hi: NDArray[np.complexfloating], turns: NDArray[np.complexfloating], period: int,
               out: NDArray[np.complexfloating]) -> None:
    """The synthesis kernel's source: spectra (M, A B) flat chip spectra, members/rows (T,)
    each term's spectrum and row of ``out`` (R, m), lo (T, B) and hi (T, A) the ramp's
    factors (hi with the amplitude), turns (T, periods - 1) each further period's turn;
    all complex128 or all complex64 (``u`` and every product then complex64)."""
    size, b, a = out.shape[1], lo.shape[1], hi.shape[1]
    if (members.size != rows.size or lo.shape[0] != rows.size or hi.shape[0] != rows.size
            or turns.shape[0] != rows.size or period < 1 or a * b < period
            or spectra.shape[1] != a * b or (turns.shape[1] + 1) * period < size):
        raise RuntimeError("one spectrum, row, ramp and turns per term, covering every bin")
    written = np.zeros(out.shape[0], dtype=np.bool_)
    u = np.empty(a * b, dtype=out.dtype)
    for k in range(rows.size):
        i, r = members[k], rows[k]
        if i < 0 or i >= spectra.shape[0] or r < 0 or r >= out.shape[0]:
            raise RuntimeError("a term's spectrum or row is out of range")
        dft, row, add = spectra[i], out[r], written[r]
        written[r] = True
        for alpha in range(a):
            h = hi[k, alpha]
            for beta in range(b):
                u[alpha * b + beta] = _mul(_mul(dft[alpha * b + beta], lo[k, beta]), h)
        for j in range(turns.shape[1] + 1):
            q0 = j * period
            n = min(period, size - q0)
            if j == 0 and add:
                for p in range(n):
                    row[p] = row[p] + u[p]
            elif j == 0:
                row[:n] = u[:n]
            elif add:
                for p in range(n):
                    row[q0 + p] = row[q0 + p] + _mul(u[p], turns[k, j - 1])
            else:
                for p in range(n):
                    row[q0 + p] = _mul(u[p], turns[k, j - 1])
    for r in range(out.shape[0]):
        if not written[r]:
            out[r, :] = 0


def _fma(a: float, b: float, c: float) -> float:
    """``a b + c`` rounded once: llvm.fma of the arguments' float type in compiled code
    (:func:`_register`)."""
    raise NotImplementedError("compiled code only")


def _mul(x: complex, y: complex) -> complex:
    """numpy's complex product: each part one fused multiply-add of a rounded product (in
    compiled code in the arguments' precision: complex64 parts are float32 and so is the
    product)."""
    return complex(_fma(x.real, y.real, -(x.imag * y.imag)),
                   _fma(x.real, y.imag, x.imag * y.real))


@functools.cache
def terms_kernel() -> Callable[..., None] | None:
    """``_terms`` compiled for float32 tables and batches (None without numba).

    The signature is fixed (read-only float32 table and coefficients, int64 offsets, a
    float32 start, a writable float32 batch, an int64 length): other types are refused,
    not converted.
    Compiled once per process and cached on disk by numba (in memory only where it
    finds no writable folder for the cache).
    """
    def signature(t: object, readonly: Callable[..., object]) -> object:
        _register()
        return t.void(readonly(t.float32), readonly(t.int64), readonly(t.int64),
                      readonly(t.float32), readonly(t.float32), t.float32,
                      t.Array(t.float32, 1, "C"), t.int64)

    return compile_kernel(_terms, signature, "accumulated echoes call BLAS saxpy")


def _synthesis_kernel(dtype: str, fallback: str) -> Callable[..., None] | None:
    """``_synthesis`` compiled for ``dtype`` (numba's name: complex128 or complex64).

    The signature is fixed (read-only spectra and ramps, int64 indices, a writable (R, m)
    sum), as :func:`terms_kernel`'s. Compiled once per process, cached on disk by numba.
    """
    def signature(t: object, readonly: Callable[..., object]) -> object:
        _register()
        c = getattr(t, dtype)
        return t.void(readonly(c, 2), readonly(t.int64), readonly(t.int64), readonly(c, 2),
                      readonly(c, 2), readonly(c, 2), t.int64, t.Array(c, 2, "C"))

    return compile_kernel(_synthesis, signature, fallback)


@functools.cache
def synthesis_kernel() -> Callable[..., None] | None:
    """``_synthesis`` compiled for complex128 (``exact``; None without numba)."""
    return _synthesis_kernel("complex128", "exact echoes run on numpy")


@functools.cache
def single_synthesis_kernel() -> Callable[..., None] | None:
    """``_synthesis`` compiled for complex64 (``accumulated``; None without numba)."""
    return _synthesis_kernel("complex64", "accumulated's Fourier echoes run on numpy")


@functools.cache
def _register() -> None:
    """Make ``_fma`` numba's fused multiply-add intrinsic and ``_mul`` callable from the
    compiled kernels (numba's register_jitable). Once, before a kernel compiles (numba is
    present: compile_kernel imported it)."""
    from numba.extending import intrinsic, overload, register_jitable  # optional: "fast"

    @intrinsic
    def fma(typingctx, a, b, c):  # numba's intrinsic protocol
        def codegen(context, builder, signature, args):
            return builder.fma(*args)

        return a(a, a, a), codegen

    overload(_fma)(lambda a, b, c: lambda a, b, c: fma(a, b, c))
    for helper in (_mul, _waves):
        register_jitable(inline="always")(helper)
