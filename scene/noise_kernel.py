r"""The compiled row kernels of the noise of both fidelity levels (numba: the ``fast`` extra).

``accumulated``: :func:`row_kernel`, one column of
:func:`cdma_lidar.scene.sums._draw_table_sums` in one call::

    words[j] = PCG64 output j of the generator seeded with ``seed``      j < ceil(L / 4)
    out[i] = floor(table[words16[i]] * scale + mean[i])                  i = 0 .. L - 1

``seed`` the column's four seeding words (:func:`cdma_lidar.scene.streams.seed_words`:
what ``default_rng(key)`` hands its PCG64), ``words16`` the words' 16-bit quarters in
memory order (numpy's ``random_raw(...).view(np.uint16)``: low quarter first, on the
little-endian machines numba runs on), ``table`` the 65536 float32
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
gather, the scale, the mean, the floor) where this spends one call per column and two
passes: the table lookups of a word's four quarters as it is made (they run while the
next 128-bit step waits on its multiply), then the arithmetic in a pass with no lookup,
which the compiler vectorises (``python -m bench scene`` times both).

``exact``: :func:`repetition_kernel`, one column of
:func:`cdma_lidar.scene.sums._draw_exact_sums`, its draws included::

    z[i]     = standard_normal(generator)                       i = 0 .. L - 1
    word[w]  = next word of the generator                       w < ceil(n / 8)
    octet[k] = byte k of the words in memory                    k = 0 .. n - 1
    t[i]     = sum_j octet[j L + i]                             j = 0 .. R - 2
    out[i]   = floor((z[i] * scale + mean[i]) - (t[i] + (R - 1) / 2) / 256)

n = (R - 1) L random bytes, the generator the column's PCG64 as above; ``scale`` (LSB)
and ``mean`` (L,) float64, ``out`` int32. These are the draws of numpy's path:
``standard_normal(L)`` (numpy's ziggurat, ``random_standard_normal``, as numba ports it:
its tables are numba's copies of numpy's; the tail's log1p and the wedges' exp are
numba's, which call the same C library functions), then ``random_raw(ceil(n / 8))`` read
as bytes in memory order (numpy's ``view``) as an (R - 1, L) array. The byte rows are
summed into an integer scratch row (an exact sum whatever the order), then one pass does
the float64 arithmetic in numpy's order: the product rounded, the sum rounded, the
uniform's sum (exact) times 2^-8 (exact), the difference rounded, the floor. numpy's
path takes a Generator, a ``standard_normal`` call, a ``random_raw`` call (a call
through a function pointer per word) and eight passes over the column (the byte sums,
the product, the sum, the uniforms' three, the difference, the floor); this one call.
The Gaussians, the words and the sums are checked against numpy's generator and
arithmetic, bit for bit, in tests/scene/test_noise_blocks.py (300 000 draws reach the
ziggurat's tail).

The generator's four words of state travel through the helpers in registers (each
returns the state it advanced); the helpers are plain Python that numba compiles into
the kernels (:func:`_register`). Without numba, both kernels are None and the callers
use numpy's generators and blocks.
"""

from __future__ import annotations

import functools
import logging
from collections.abc import Callable

import numpy as np
from numpy.typing import NDArray

__all__ = ["compile_kernel", "repetition_kernel", "row_kernel"]

logger = logging.getLogger(__name__)


def _row(seed: NDArray[np.uint64], table: NDArray[np.float32], scale: np.float32,
         mean: NDArray[np.float32], out: NDArray[np.int32]) -> None:
    """The accumulated kernel's source (plain Python: what numba compiles)."""
    if mean.size != out.size:
        raise RuntimeError("mean must match the row")
    hi, lo, inc_hi, inc_lo = _pcg(seed)
    draw = np.empty(out.size + 3, dtype=np.float32)
    for i in range(0, out.size, 4):  # the lookups run in the shadow of the 128-bit step
        hi, lo, word = _next64(hi, lo, inc_hi, inc_lo)
        for q in range(4):  # the word's quarters in memory order (little-endian)
            draw[i + q] = table[np.intp((word >> np.uint64(16 * q)) & np.uint64(0xFFFF))]
    for i in range(out.size):  # one pass with no lookup: vectorised
        out[i] = np.int32(np.floor(draw[i] * scale + mean[i]))


def _repetition_row(seed: NDArray[np.uint64], repetitions: int, scale: float,
                    mean: NDArray[np.float64], draw: NDArray[np.float64],
                    total: NDArray[np.uint32], words: NDArray[np.uint64],
                    out: NDArray[np.int32]) -> None:
    """The exact kernel's source (plain Python: what numba compiles)."""
    size = out.size
    n = (repetitions - 1) * size  # random bytes, after the L Gaussians
    if repetitions < 1 or mean.size != size or draw.size != size or total.size != size \
            or words.size < -(-n // 8):
        raise RuntimeError("repetitions >= 1; mean and the scratch rows must match the row, "
                         "words cover its bytes")
    hi, lo, inc_hi, inc_lo = _pcg(seed)
    for i in range(size):
        hi, lo, draw[i] = _standard_normal(hi, lo, inc_hi, inc_lo)
    for j in range(-(-n // 8)):  # random_raw(ceil(n / 8))
        hi, lo, words[j] = _next64(hi, lo, inc_hi, inc_lo)
    octets = words.view(np.uint8)  # in memory order, as random_raw(...).view(np.uint8)
    total[:] = 0  # below (R - 1) 255 < 2**32
    for j in range(repetitions - 1):
        for i in range(size):
            total[i] += octets[j * size + i]
    half = 0.5 * (repetitions - 1)
    for i in range(size):
        d = draw[i] * scale
        d = d + mean[i]
        d = d - (total[i] + half) * (1.0 / 256)
        out[i] = np.int32(np.floor(d))


#: PCG64's 128-bit multiplier (numpy's PCG_DEFAULT_MULTIPLIER_128), high and low words.
_MULT_HI, _MULT_LO = np.uint64(2549297995355413924), np.uint64(4865540595714422341)


def _pcg(seed: NDArray[np.uint64]) -> tuple[int, int, int, int]:
    """numpy's PCG64 seeded with the four words ``default_rng(key)`` hands it
    (``pcg64_set_seed``): (state high, low, increment high, low), the increment
    ``(seed[2:] << 1) | 1`` and the state ``(inc + seed[:2]) M + inc``. The generator
    is these four words, passed along in registers (the helpers below return the state
    they advanced)."""
    if seed.size != 4:
        raise RuntimeError("the seed is 4 words (state, increment)")
    one, zero = np.uint64(1), np.uint64(0)
    inc_hi = (seed[2] << one) | (seed[3] >> np.uint64(63))
    inc_lo = (seed[3] << one) | one
    hi, lo = _muladd(inc_hi, inc_lo, zero, one, seed[0], seed[1])
    hi, lo = _muladd(hi, lo, _MULT_HI, _MULT_LO, inc_hi, inc_lo)
    return hi, lo, inc_hi, inc_lo


def _next64(hi: int, lo: int, inc_hi: int, inc_lo: int) -> tuple[int, int, int]:
    """(new state high, low; the generator's next word, ``next_uint64`` and
    ``random_raw``'s): the 128-bit step ``state M + inc``, then XSL-RR,
    ``rotr64(high ^ low, high >> 58)``."""
    hi, lo = _muladd(hi, lo, _MULT_HI, _MULT_LO, inc_hi, inc_lo)
    x, turn = hi ^ lo, hi >> np.uint64(58)
    return hi, lo, (x >> turn) | (x << ((np.uint64(64) - turn) & np.uint64(63)))


def _next_double(hi: int, lo: int, inc_hi: int, inc_lo: int) -> tuple[int, int, float]:
    """(new state; ``next_double``: the top 53 bits of the next word, times 2**-53)."""
    hi, lo, word = _next64(hi, lo, inc_hi, inc_lo)
    return hi, lo, (word >> np.uint64(11)) * (1.0 / 9007199254740992.0)


def _standard_normal(hi: int, lo: int, inc_hi: int, inc_lo: int) -> tuple[int, int, float]:
    """(new state; numpy's ``random_standard_normal``: the ziggurat of
    numpy/random/src/distributions as numba ports it, its tables numba's copies of
    numpy's, on this generator)."""
    while True:
        hi, lo, r = _next64(hi, lo, inc_hi, inc_lo)
        idx = r & 0xff
        r >>= 8
        sign = r & 0x1
        rabs = (r >> 1) & 0x000fffffffffffff
        x = rabs * _WI[idx]
        if sign & 0x1:
            x = -x
        if rabs < _KI[idx]:
            return hi, lo, x
        if idx == 0:
            while True:
                hi, lo, u = _next_double(hi, lo, inc_hi, inc_lo)
                xx = -_NOR_INV_R * np.log1p(-u)
                hi, lo, u = _next_double(hi, lo, inc_hi, inc_lo)
                yy = -np.log1p(-u)
                if yy + yy > xx * xx:
                    if (rabs >> 8) & 0x1:
                        return hi, lo, -(_NOR_R + xx)
                    return hi, lo, _NOR_R + xx
        else:
            hi, lo, u = _next_double(hi, lo, inc_hi, inc_lo)
            if ((_FI[idx - 1] - _FI[idx]) * u + _FI[idx]) < np.exp(-0.5 * x * x):
                return hi, lo, x


def _muladd(a_hi: int, a_lo: int, b_hi: int, b_lo: int, c_hi: int, c_lo: int
            ) -> tuple[int, int]:
    """``a b + c`` modulo 2**128, each as (high, low) uint64 words: one LLVM i128
    multiply-add in compiled code (:func:`_register`)."""
    raise NotImplementedError("compiled code only")


#: The ziggurat's tables and constants, numba's copies of numpy's (:func:`_register`).
_WI = _KI = _FI = np.empty(0)
_NOR_R = _NOR_INV_R = 0.0


@functools.cache
def _register() -> None:
    """Make the helpers above callable from compiled kernels (numba's register_jitable)
    and ``_muladd`` numba's i128 intrinsic; load the ziggurat's tables. Once, before a
    kernel compiles (numba is present: compile_kernel imported it)."""
    # numba and its llvmlite: optional (extra "fast"), here only once compile_kernel found it
    from llvmlite import ir  # numba's code generator
    from numba.core import types  # optional, as above
    from numba.extending import intrinsic, overload, register_jitable  # optional, as above
    from numba.np.random import _constants  # optional, as above (numpy's ziggurat tables)

    global _WI, _KI, _FI, _NOR_R, _NOR_INV_R
    _WI, _KI, _FI = _constants.wi_double, _constants.ki_double, _constants.fi_double
    _NOR_R, _NOR_INV_R = _constants.ziggurat_nor_r, _constants.ziggurat_nor_inv_r

    @intrinsic
    def muladd(typingctx, a_hi, a_lo, b_hi, b_lo, c_hi, c_lo):  # numba's protocol
        def codegen(context, builder, signature, args):
            wide = ir.IntType(128)

            def join(hi, lo):
                return builder.or_(builder.shl(builder.zext(hi, wide), wide(64)),
                                   builder.zext(lo, wide))

            r = builder.add(builder.mul(join(*args[0:2]), join(*args[2:4])), join(*args[4:6]))
            halves = (builder.trunc(builder.lshr(r, wide(64)), ir.IntType(64)),
                      builder.trunc(r, ir.IntType(64)))
            return context.make_tuple(builder, signature.return_type, halves)

        u64 = types.uint64
        return types.UniTuple(u64, 2)(u64, u64, u64, u64, u64, u64), codegen

    @overload(_muladd)
    def _muladd_impl(a_hi, a_lo, b_hi, b_lo, c_hi, c_lo):
        return lambda a_hi, a_lo, b_hi, b_lo, c_hi, c_lo: muladd(a_hi, a_lo, b_hi, b_lo,
                                                                  c_hi, c_lo)

    for helper in (_pcg, _next64, _next_double, _standard_normal):
        register_jitable(inline="always")(helper)


@functools.cache
def row_kernel() -> Callable[..., None] | None:
    """``_row`` compiled for a (4,) uint64 PCG64 seed, float32 tables and means, int32
    output (None without numba).

    The signature is fixed: float64 means or a float64 scale are refused, not silently
    computed in another precision. Compiled once per process and cached on disk by numba
    (in memory only where it finds no writable folder for the cache).
    """
    def signature(t: object, readonly: Callable[..., object]) -> object:
        _register()
        return t.void(readonly(t.uint64), readonly(t.float32), t.float32,
                      readonly(t.float32), t.Array(t.int32, 1, "C"))

    return compile_kernel(_row, signature, "accumulated noise runs on numpy")


@functools.cache
def repetition_kernel() -> Callable[..., None] | None:
    """``_repetition_row`` compiled for a (4,) uint64 PCG64 seed, float64 scale, means and
    draw row, uint32 totals, uint64 words and int32 output (None without numba).

    The signature is fixed, as :func:`row_kernel`'s: float32 values or other scratch
    types are refused, not silently converted. The ziggurat is numba's port of numpy's
    (its tables numba's copies); should a numba or numpy release part ways, the tests
    that compare the kernel with numpy's generator (tests/scene/test_noise_blocks.py)
    fail. Compiled once per process, cached on disk by numba.
    """
    def signature(t: object, readonly: Callable[..., object]) -> object:
        _register()
        return t.void(readonly(t.uint64), t.int64, t.float64, readonly(t.float64),
                      t.Array(t.float64, 1, "C"), t.Array(t.uint32, 1, "C"),
                      t.Array(t.uint64, 1, "C"), t.Array(t.int32, 1, "C"))

    return compile_kernel(_repetition_row, signature, "exact noise runs on numpy")


def compile_kernel(source: Callable[..., None], signature: Callable[..., object],
                   fallback: str) -> Callable[..., None] | None:
    """``source`` compiled by numba for ``signature(numba.types, readonly)``, or None and
    a log line saying what runs instead (``fallback``) without numba, or with a numba
    whose internals the kernel's helpers import have moved: without fast-math,
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

    try:
        compiled = signature(t, readonly)
    except (ImportError, AttributeError) as exc:  # a numba without the internals we use
        logger.warning("numba %s lacks what the compiled kernel needs (%s): %s",
                       numba.__version__, exc, fallback)
        return None
    try:
        return numba.njit(compiled, cache=True, nogil=True)(source)
    except RuntimeError:  # numba finds no writable folder for its cache: compile in memory
        return numba.njit(compiled, nogil=True)(source)
