"""Probes of how this machine rounds: whether a library's multiply-add is fused (one
rounding) or not. Where it is not, a compiled kernel that fuses (numba) differs from it in
the last bit, both valid; tests that compare them bit for bit ask here first."""

from __future__ import annotations

import numpy as np


def blas_fuses() -> bool:
    """Whether saxpy rounds a x + y once (FMA), in its vector body and in its tail: with
    a = x = 1 + 2^-12 and y = -(1 + 2^-11), a x + y is 2^-24 exactly, 0 when a x is
    rounded to float32 first."""
    from scipy.linalg.blas import saxpy

    one = np.float32(1 + 2.0**-12)
    for n in (3, 67):
        y = saxpy(np.full(n, one), np.full(n, -(1 + 2.0**-11), dtype=np.float32), a=one)
        if not np.all(y == np.float32(2.0**-24)):
            return False
    return True
