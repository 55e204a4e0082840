r"""The compiled row kernel of ``accumulated`` fidelity's noise (numba: the ``fast`` extra).

One column of :func:`cdma_lidar.scene.instrument._draw_table_sums` in one pass::

    out[i] = floor(table[words[i]] * scale + mean[i])      i = 0 .. L - 1

``words`` the column's 16-bit generator words, ``table`` the 65536 float32 quantiles of
``_normal_table``, ``scale`` (float32, LSB) its noise scale, ``mean`` (float32, LSB) its
mean, ``out`` int32. The same float32 operations in the same order as numpy's blocks (a
product rounded to float32, then a sum rounded to float32, then the floor): numba
compiles without fast-math, so nothing is reassociated or fused into a multiply-add, and
the values are bit for bit those of the numpy path (tests/scene/test_noise_blocks.py).
numpy spends five passes (widening the words to indices, the gather, the scale, the
mean, the floor) where this spends one per column: the noise of a cold 160-column
paper-scene1 frame took 3.8 ms instead of 6.3 (CPU, best of 21, both paths in one
process, load 0.7).

Without numba, :func:`row_kernel` returns None and the caller uses numpy.
"""

from __future__ import annotations

import functools
import logging
from collections.abc import Callable

import numpy as np
from numpy.typing import NDArray

__all__ = ["row_kernel"]

logger = logging.getLogger(__name__)


def _row(words: NDArray[np.uint16], table: NDArray[np.float32], scale: np.float32,
         mean: NDArray[np.float32], out: NDArray[np.int32]) -> None:
    """The kernel's source (plain Python: what numba compiles)."""
    if words.size < out.size or mean.size != out.size:
        raise ValueError("words must cover the row and mean must match it")
    for i in range(out.size):
        out[i] = np.int32(np.floor(table[words[i]] * scale + mean[i]))


@functools.cache
def row_kernel() -> Callable[..., None] | None:
    """``_row`` compiled for float32 tables and means, int32 output (None without numba).

    The signature is fixed: float64 means or a float64 scale are refused, not silently
    computed in another precision. Compiled once per process and cached on disk by numba
    (in memory only where it finds no writable folder for the cache).
    """
    try:
        import numba  # optional (extra "fast"): without it the noise runs on numpy
    except ImportError:
        logger.info("numba is not installed: accumulated noise runs on numpy "
                    "(pip install 'cdma-lidar[fast]' for the compiled kernel)")
        return None
    t = numba.types

    def readonly(dtype: object) -> object:
        return t.Array(dtype, 1, "C", readonly=True)

    signature = t.void(readonly(t.uint16), readonly(t.float32), t.float32,
                       readonly(t.float32), t.Array(t.int32, 1, "C"))
    try:
        return numba.njit(signature, cache=True, nogil=True)(_row)
    except RuntimeError:  # numba finds no writable folder for its cache: compile in memory
        return numba.njit(signature, nogil=True)(_row)
