"""Polynomials over GF(2): the one tuple form and the one bit-mask convention.

A polynomial is a tuple of exponents, highest first, constant term implied, as in the
paper: ``(11, 2)`` is x^11 + x^2 + 1. Its **coefficient mask** has bit e set for every
term x^e, the constant included (bit 0)::

    (11, 2)  ->  x^11 + x^2 + 1

    bit:   11 10  9  8  7  6  5  4  3  2  1  0
           1  0  0  0  0  0  0  0  0  1  0  1     = 0x805 = poly_to_mask((11, 2))

Everything else is a view of that mask:

* the **wire** (protocol CONFIG ``poly_u``/``poly_v``) drops the constant, which every
  primitive polynomial has: ``mask & ~1`` (0x804 above);
* the **tap mask** of a Fibonacci or Galois register word, whose bit j - 1 holds
  stage j (stage 1 in bit 0, docs/codes.md), is ``mask >> 1`` (0x402 above: stages
  11 and 2 are tapped).
"""

from __future__ import annotations

from collections.abc import Sequence

__all__ = ["Poly", "mask_to_poly", "poly_to_mask", "tap_mask"]

Poly = tuple[int, ...]


def poly_to_mask(poly: Sequence[int]) -> int:
    """Coefficient mask of an exponent tuple: bit e per term x^e, and bit 0 (the constant).

    The caller validates the exponents (distinct, >= 1); this only converts.
    """
    mask = 1
    for e in poly:
        mask |= 1 << int(e)
    return mask


def mask_to_poly(mask: int) -> Poly:
    """Exponent tuple (highest first) of a coefficient or wire mask; bit 0 is ignored."""
    return tuple(e for e in range(int(mask).bit_length() - 1, 0, -1) if mask >> e & 1)


def tap_mask(poly: Sequence[int]) -> int:
    """Register-word tap mask: bit e - 1 set for each exponent e (stage j is bit j - 1)."""
    return poly_to_mask(poly) >> 1
