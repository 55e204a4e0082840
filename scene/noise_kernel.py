r"""The compiled row kernels of the noise of both fidelity levels (numba: the ``fast`` extra).

``accumulated``: :func:`row_kernel`, one column of
:func:`cdma_lidar.scene.instrument._draw_table_sums` in one call::

    words[j] = PCG64 output j of the generator seeded with ``seed``      j < ceil(L / 4)
    out[i] = floor(table[words16[i]] * scale + mean[i])                  i = 0 .. L - 1

``seed`` the column's four seeding words (:func:`cdma_lidar.scene.streams.seed_words`:
what ``default_rng(key)`` hands its PCG64), ``words16`` the words' 16-bit quarters in
memory order (numpy's ``random_raw(...).view(np.uint16)``), ``table`` the 65536 float32
quantiles of ``_normal_table``, ``scale`` (float32, LSB) its noise scale, ``mean``
(float32, LSB) its mean, ``out`` int32. The generator is numpy's PCG64 written out:
``pcg64_set_seed`` (increment ``(seed[2:] << 1) | 1``, state ``(inc + seed[:2]) M +
inc``), then per word the 128-bit step ``state = state M + inc`` (one LLVM i128
multiply-add) and the XSL-RR output ``rotr64(hi ^ lo, hi >> 58)``: numpy's words bit for
bit (tests/scene/test_noise_blocks.py), without a Generator object or a call through a
function pointer per word. Then the same float32 operations in the same order as numpy's
blocks (a product rounded to float32, then a sum rounded to float32, then the floor):
numba compiles without fast-math, so nothing is reassociated or fused into a
multiply-add, and the values are bit for bit those of the numpy path. numpy spends a
generator, a ``random_raw`` call and five passes (widening the words to indices, the
gather, the scale, the mean, the floor) where this spends one call per column
(``python -m bench scene`` times both).

``exact``: :func:`repetition_kernel`, one column of
:func:`cdma_lidar.scene.instrument.draw_repetition_sums`::

    t[i] = sum_j octets[j, i]                                   j = 0 .. R - 2
    out[i] = floor((normals[i] * scale + mean[i]) - (t[i] + (R - 1) / 2) / 256)

``normals`` the column's L float64 standard normals and ``octets`` its (R - 1, L) random
bytes, both as numpy's generator drew them; ``scale`` (LSB) and ``mean`` (L,) float64,
``out`` int32. The byte rows are summed into an integer scratch row (L values, in the
cache; an exact sum whatever the order), then one pass does the float64 arithmetic in
numpy's order: the product rounded, the sum rounded, the uniform's sum (exact) times 2^-8
(exact), the difference rounded, the floor. numpy's blocks make eight passes (the byte
sums, the product, the sum, the uniforms' three, the difference, the floor).

The Gaussians themselves: :func:`normal_kernel` fills the column's L normals from its
generator with numba's own port of numpy's ``Generator.standard_normal`` (the same
ziggurat on the same bit generator words, the same values, checked against numpy's in
tests/scene/test_noise_blocks.py) in half the time numpy's call takes here, the
generator left in the same state for the bytes that follow.

Without numba, the three functions return None and the caller uses numpy.
"""

from __future__ import annotations

import functools
import logging
from collections.abc import Callable

import numpy as np
from numpy.typing import NDArray

__all__ = ["compile_kernel", "normal_kernel", "repetition_kernel", "row_kernel"]

logger = logging.getLogger(__name__)


def _row(seed: NDArray[np.uint64], table: NDArray[np.float32], scale: np.float32,
         mean: NDArray[np.float32], out: NDArray[np.int32]) -> None:
    """The kernel's source (plain Python: what numba compiles, ``_muladd`` then its 128-bit
    multiply-add). numpy's PCG64 (``pcg64_set_seed``, then XSL-RR on each new state)."""
    if seed.size != 4 or mean.size != out.size:
        raise ValueError("the seed is 4 words (state, increment) and mean must match the row")
    one, zero = np.uint64(1), np.uint64(0)
    inc_hi = (seed[2] << one) | (seed[3] >> np.uint64(63))  # increment (seed[2:] << 1) | 1
    inc_lo = (seed[3] << one) | one
    hi, lo = _muladd(inc_hi, inc_lo, zero, one, seed[0], seed[1])  # 0 M + inc + state
    hi, lo = _muladd(hi, lo, _MULT_HI, _MULT_LO, inc_hi, inc_lo)
    words = np.empty((out.size + 3) // 4, dtype=np.uint64)
    for j in range(words.size):
        hi, lo = _muladd(hi, lo, _MULT_HI, _MULT_LO, inc_hi, inc_lo)
        x, turn = hi ^ lo, hi >> np.uint64(58)
        words[j] = (x >> turn) | (x << ((np.uint64(64) - turn) & np.uint64(63)))
    quarters = words.view(np.uint16)  # little-endian: each word's quarters, low first
    for i in range(out.size):
        out[i] = np.int32(np.floor(table[quarters[i]] * scale + mean[i]))


#: PCG64's 128-bit multiplier (numpy's PCG_DEFAULT_MULTIPLIER_128), high and low words.
_MULT_HI, _MULT_LO = np.uint64(2549297995355413924), np.uint64(4865540595714422341)


def _muladd(a_hi: int, a_lo: int, b_hi: int, b_lo: int, c_hi: int, c_lo: int
            ) -> tuple[int, int]:
    """Set to numba's 128-bit ``a b + c`` (modulo 2**128) by :func:`row_kernel`."""
    raise NotImplementedError("compiled by row_kernel")


def _repetition_row(normals: NDArray[np.float64], octets: NDArray[np.uint8], scale: float,
                    mean: NDArray[np.float64], out: NDArray[np.int32]) -> None:
    """The exact kernel's source (plain Python: what numba compiles)."""
    size = out.size
    if normals.size != size or mean.size != size or octets.shape[1] != size:
        raise ValueError("normals, mean and every byte row must match the row")
    total = np.zeros(size, dtype=np.uint32)  # below (R - 1) 255 < 2**32
    for j in range(octets.shape[0]):
        for i in range(size):
            total[i] += octets[j, i]
    half = 0.5 * octets.shape[0]
    for i in range(size):
        d = normals[i] * scale
        d = d + mean[i]
        d = d - (total[i] + half) * (1.0 / 256)
        out[i] = np.int32(np.floor(d))


def _normals(rng: np.random.Generator, out: NDArray[np.float64]) -> None:
    """The Gaussians' source: ``rng.standard_normal(out=out)`` as numba compiles it."""
    for i in range(out.size):
        out[i] = rng.standard_normal()


@functools.cache
def row_kernel() -> Callable[..., None] | None:
    """``_row`` compiled for a (4,) uint64 PCG64 seed, float32 tables and means, int32
    output (None without numba).

    The signature is fixed: float64 means or a float64 scale are refused, not silently
    computed in another precision. Compiled once per process and cached on disk by numba
    (in memory only where it finds no writable folder for the cache).
    """
    def signature(t: object, readonly: Callable[..., object]) -> object:
        from llvmlite import ir  # numba's own dependency
        from numba.extending import intrinsic  # present: compile_kernel imported numba

        @intrinsic
        def muladd(typingctx, a_hi, a_lo, b_hi, b_lo, c_hi, c_lo):  # numba's protocol
            def codegen(context, builder, signature, args):
                wide = ir.IntType(128)

                def join(hi, lo):
                    return builder.or_(builder.shl(builder.zext(hi, wide), wide(64)),
                                       builder.zext(lo, wide))

                r = builder.add(builder.mul(join(*args[0:2]), join(*args[2:4])),
                                join(*args[4:6]))
                halves = (builder.trunc(builder.lshr(r, wide(64)), ir.IntType(64)),
                          builder.trunc(r, ir.IntType(64)))
                return context.make_tuple(builder, signature.return_type, halves)

            u64 = t.uint64
            return t.UniTuple(u64, 2)(u64, u64, u64, u64, u64, u64), codegen

        global _muladd  # numba reads it when it compiles _row (or loads it from its cache)
        _muladd = muladd
        return t.void(readonly(t.uint64), readonly(t.float32), t.float32,
                      readonly(t.float32), t.Array(t.int32, 1, "C"))

    return compile_kernel(_row, signature, "accumulated noise runs on numpy")


@functools.cache
def repetition_kernel() -> Callable[..., None] | None:
    """``_repetition_row`` compiled for float64 normals and means, (R - 1, L) uint8 octets,
    int32 output (None without numba).

    The signature is fixed, as :func:`row_kernel`'s: float32 values or wider byte rows are
    refused, not silently converted. Compiled once per process, cached on disk by numba.
    """
    def signature(t: object, readonly: Callable[..., object]) -> object:
        return t.void(readonly(t.float64), readonly(t.uint8, 2), t.float64,
                      readonly(t.float64), t.Array(t.int32, 1, "C"))

    return compile_kernel(_repetition_row, signature, "exact noise runs on numpy")


@functools.cache
def normal_kernel() -> Callable[..., None] | None:
    """``_normals`` compiled for a numpy Generator (any bit generator) and a float64 row
    (None without numba).

    numba (>= 0.56) runs numpy's ``standard_normal`` algorithm on the generator's own bit
    generator; should a numba or numpy release part ways, the tests that compare it with
    numpy's draws (tests/scene/test_noise_blocks.py) fail.
    """
    def signature(t: object, readonly: Callable[..., object]) -> object:
        import numba  # present: compile_kernel imported it

        return t.void(numba.typeof(np.random.default_rng(0)), t.Array(t.float64, 1, "C"))

    return compile_kernel(_normals, signature, "exact noise runs on numpy")


def compile_kernel(source: Callable[..., None], signature: Callable[..., object],
                   fallback: str) -> Callable[..., None] | None:
    """``source`` compiled by numba for ``signature(numba.types, readonly)``, or None and
    a log line saying what runs instead (``fallback``) without numba: without fast-math,
    cached on disk (in memory only where numba finds no writable folder for its cache).
    The scene's compiled kernels (here and :mod:`cdma_lidar.scene.echo_kernel`) are all
    made by it."""
    try:
        import numba  # optional (extra "fast"): without it the callers run numpy or BLAS
    except ImportError:
        logger.info("numba is not installed: %s (pip install 'cdma-lidar[fast]' for the "
                    "compiled kernel)", fallback)
        return None
    t = numba.types

    def readonly(dtype: object, ndim: int = 1) -> object:
        return t.Array(dtype, ndim, "C", readonly=True)

    compiled = signature(t, readonly)
    try:
        return numba.njit(compiled, cache=True, nogil=True)(source)
    except RuntimeError:  # numba finds no writable folder for its cache: compile in memory
        return numba.njit(compiled, nogil=True)(source)
