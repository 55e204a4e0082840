r"""The compiled row kernels of the noise of both fidelity levels (numba: the ``fast`` extra).

``accumulated``: :func:`row_kernel`, one column of
:func:`cdma_lidar.scene.instrument._draw_table_sums` in one pass::

    out[i] = floor(table[words[i]] * scale + mean[i])      i = 0 .. L - 1

``words`` the column's 16-bit generator words, ``table`` the 65536 float32 quantiles of
``_normal_table``, ``scale`` (float32, LSB) its noise scale, ``mean`` (float32, LSB) its
mean, ``out`` int32. The same float32 operations in the same order as numpy's blocks (a
product rounded to float32, then a sum rounded to float32, then the floor): numba
compiles without fast-math, so nothing is reassociated or fused into a multiply-add, and
the values are bit for bit those of the numpy path (tests/scene/test_noise_blocks.py).
numpy spends five passes (widening the words to indices, the gather, the scale, the
mean, the floor) where this spends one per column (``python -m bench scene`` times both).

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


def _row(words: NDArray[np.uint16], table: NDArray[np.float32], scale: np.float32,
         mean: NDArray[np.float32], out: NDArray[np.int32]) -> None:
    """The kernel's source (plain Python: what numba compiles)."""
    if words.size < out.size or mean.size != out.size:
        raise ValueError("words must cover the row and mean must match it")
    for i in range(out.size):
        out[i] = np.int32(np.floor(table[words[i]] * scale + mean[i]))


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
    """``_row`` compiled for float32 tables and means, int32 output (None without numba).

    The signature is fixed: float64 means or a float64 scale are refused, not silently
    computed in another precision. Compiled once per process and cached on disk by numba
    (in memory only where it finds no writable folder for the cache).
    """
    def signature(t: object, readonly: Callable[..., object]) -> object:
        return t.void(readonly(t.uint16), readonly(t.float32), t.float32,
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
