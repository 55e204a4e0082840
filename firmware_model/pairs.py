"""Preferred pairs of primitive polynomials for Gold families, degrees 5 to 20.

The table holds every pair of the paper's Table 1 (Supplementary Note 8) that
is preferred, the example pair of the CLI contract, and for every degree 5..20
that is not a multiple of 4 pairs derived by the classic construction:

* u is a primitive polynomial (the lowest-weight one found, or the paper's);
* v is the decimation v[n] = u[q n mod N] with q = 2^e + 1 or 2^(2e) - 2^e + 1,
  where gcd(m, e) = 1 for odd m and gcd(m, e) = 2 for m = 2 mod 4 (Gold 1968,
  Kasami 1971); e = 1, 2 gives q = 3, 5, 13 (q = 3 only for odd m, since
  3 divides 2^m - 1 for even m);
* v's polynomial is read off the decimated sequence by Berlekamp-Massey over
  GF(2) (:func:`derive_pair`).

Degrees that are multiples of 4 have no preferred pairs (Gold families need
m != 0 mod 4), and asking for one is a ConfigError. Every entry is proven
preferred in ``tests/firmware_model/test_pairs.py`` by its periodic
cross-correlation taking only the values {-1, -t(m), t(m) - 2}, and the table is
regenerated there from :func:`derive_pair`. ``docs/codes.md`` lists the paper's
pairs that fail the property and are kept out.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from cdma_lidar.checks import check_int
from cdma_lidar.errors import ConfigError, out_of_range
from cdma_lidar.firmware_model.lfsr import check_primitive, mseq
from cdma_lidar.poly import Poly

__all__ = [
    "DECIMATIONS",
    "MAX_PAIR_DEGREE",
    "MIN_PAIR_DEGREE",
    "PAIR_TABLE",
    "PAPER_PAIR",
    "PreferredPair",
    "berlekamp_massey",
    "decimate",
    "derive_pair",
    "pair_degrees",
    "pair_table",
    "preferred_pairs",
]

log = logging.getLogger(__name__)

MIN_PAIR_DEGREE = 5
MAX_PAIR_DEGREE = 20

#: The pair used in the paper's experiment and simulation (eqs. 3 and 4).
PAPER_PAIR: tuple[Poly, Poly] = ((11, 2), (11, 8, 5, 2))


@dataclass(frozen=True)
class PreferredPair:
    """One verified preferred pair; ``source`` says where it comes from."""

    u: Poly
    v: Poly
    source: str

    @property
    def degree(self) -> int:
        """Register length m (chips per period N = 2^m - 1)."""
        return self.u[0]


def _p(u: Poly, v: Poly, source: str) -> PreferredPair:
    return PreferredPair(u, v, source)


_PAPER = "paper Table 1"
_PAPER_STAR = "paper Table 1, starred row (experiment and simulation)"
_ISSUE = "CLI contract example (issue 2)"


def _dec(q: int) -> str:
    return f"decimation of u by {q}"


#: Verified preferred pairs by degree, paper's pairs first. Regenerate the derived
#: rows with ``derive_pair(u, q)``; tests/firmware_model/test_pairs.py checks both.
PAIR_TABLE: dict[int, tuple[PreferredPair, ...]] = {
    5: (
        _p((5, 2), (5, 4, 3, 2), _dec(3)),
        _p((5, 2), (5, 4, 2, 1), _dec(5)),
        _p((5, 2), (5, 4, 3, 1), _dec(13)),
    ),
    6: (
        _p((6, 1), (6, 5, 2, 1), _dec(5)),
        _p((6, 1), (6, 4, 3, 1), _dec(13)),
    ),
    7: (
        _p((7, 1), (7, 5, 3, 1), _dec(3)),
        _p((7, 1), (7, 3, 2, 1), _dec(5)),
        _p((7, 1), (7, 6, 5, 2), _dec(13)),
    ),
    9: (
        _p((9, 4), (9, 6, 4, 3), _dec(3)),
        _p((9, 4), (9, 8, 5, 4), _dec(5)),
        _p((9, 4), (9, 6, 5, 4, 2, 1), _dec(13)),
    ),
    10: (
        _p((10, 3), (10, 8, 3, 2), _PAPER_STAR + "; " + _dec(5)),
        _p((10, 3), (10, 9, 8, 6, 3, 2), _ISSUE),
        _p((10, 3), (10, 6, 5, 3, 2, 1), _dec(13)),
    ),
    11: (
        _p((11, 2), (11, 8, 5, 2), _PAPER_STAR + "; " + _dec(3)),
        _p((11, 2), (11, 7, 3, 2), _dec(5)),
        _p((11, 2), (11, 6, 5, 1), _dec(13)),
    ),
    13: (
        _p((13, 4, 3, 1), (13, 10, 9, 7, 5, 4), _PAPER_STAR + "; " + _dec(3)),
        _p((13, 10, 9, 7, 5, 4), (13, 12, 8, 7, 6, 5), _PAPER),
        _p((13, 11, 8, 7, 4, 1), (13, 11, 10, 5, 4, 3, 2, 1), _PAPER),
        _p((13, 4, 3, 1), (13, 11, 8, 7, 4, 1), _dec(5)),
        _p((13, 4, 3, 1), (13, 12, 6, 5, 4, 3), _dec(13)),
    ),
    14: (
        _p((14, 12, 2, 1), (14, 12, 11, 9, 8, 6, 5, 4, 2, 1), _dec(5)),
        _p((14, 12, 2, 1), (14, 13, 12, 7, 6, 5), _dec(13)),
    ),
    15: (
        _p((15, 1), (15, 10, 5, 1), _dec(3)),
        _p((15, 1), (15, 12, 3, 1), _dec(5)),
        _p((15, 1), (15, 7, 6, 3, 2, 1), _dec(13)),
    ),
    17: (
        _p((17, 3), (17, 3, 2, 1), _dec(3)),
        _p((17, 3), (17, 8, 4, 3), _dec(5)),
        _p((17, 3), (17, 12, 9, 7, 6, 4, 3, 2), _dec(13)),
    ),
    18: (
        _p((18, 7), (18, 10, 7, 5), _dec(5)),
        _p((18, 7), (18, 13, 11, 9, 8, 7, 6, 3), _dec(13)),
    ),
    19: (
        _p((19, 5, 2, 1), (19, 13, 8, 5, 4, 3), _dec(3)),
        _p((19, 5, 2, 1), (19, 12, 10, 9, 7, 3), _dec(5)),
        _p((19, 5, 2, 1), (19, 9, 8, 7, 6, 3), _dec(13)),
    ),
}

#: Decimations q tried by the construction, by m mod 4 (see module docstring).
DECIMATIONS: dict[str, tuple[int, ...]] = {"odd": (3, 5, 13), "2 mod 4": (5, 13)}


def _check_degree(degree: int, field: str = "degree") -> int:
    m = check_int(field, degree, MIN_PAIR_DEGREE, MAX_PAIR_DEGREE)
    if m % 4 == 0:
        raise ConfigError(
            f"{field} must not be a multiple of 4 (degrees 8, 12, 16, 20 have no "
            f"preferred pairs), not {m}",
            field=field,
        )
    return m


def pair_degrees() -> list[int]:
    """Degrees with preferred pairs in the table: 5..20 except multiples of 4."""
    return sorted(PAIR_TABLE)


def pair_table(degree: int | None = None, field: str = "degree") -> list[PreferredPair]:
    """Table entries (with their sources) for one degree, or for all degrees."""
    if degree is None:
        return [p for m in sorted(PAIR_TABLE) for p in PAIR_TABLE[m]]
    return list(PAIR_TABLE[_check_degree(degree, field=field)])


def preferred_pairs(degree: int) -> list[tuple[Poly, Poly]]:
    """Verified preferred pairs ``(poly_u, poly_v)`` of a degree in 5..20.

    ConfigError for degrees out of range and for multiples of 4 (none exist).
    """
    return [(p.u, p.v) for p in pair_table(degree)]


# --------------------------------------------------------------------------- construction


def berlekamp_massey(bits: Sequence[int] | np.ndarray) -> Poly:
    """Shortest Fibonacci register for a bit sequence, as exponents (our convention).

    Returns the exponents e with c_e = 1 of the connection polynomial
    C(x) = 1 + sum c_e x^e, i.e. s[n] = XOR_e s[n - e]; its highest exponent is the
    linear complexity L. Needs 2L bits to be unique.
    """
    s = [int(b) & 1 for b in bits]
    n = len(s)
    c = [1] + [0] * n
    b = [1] + [0] * n
    length, shift = 0, 1
    for i in range(n):
        d = s[i]
        for j in range(1, length + 1):
            d ^= c[j] & s[i - j]
        if d == 0:
            shift += 1
            continue
        previous = c[:]
        for j in range(n + 1 - shift):
            c[j + shift] ^= b[j]
        if 2 * length <= i:
            length, b, shift = i + 1 - length, previous, 1
        else:
            shift += 1
    return tuple(e for e in range(length, 0, -1) if c[e])


def decimate(poly_u: Sequence[int] | str, q: int, chips: int | None = None) -> np.ndarray:
    """v[n] = u[q n mod N] for n < chips (default N), u the default-seed m-sequence."""
    pu = check_primitive(poly_u)
    n = (1 << pu[0]) - 1
    count = n if chips is None else int(chips)
    u = mseq(pu)
    return u[(int(q) * np.arange(count, dtype=np.int64)) % n]


def derive_pair(poly_u: Sequence[int] | str, q: int) -> tuple[Poly, Poly]:
    """``(u, v)`` with v the polynomial of u decimated by q (Berlekamp-Massey on 2m chips).

    ConfigError when gcd(q, 2^m - 1) != 1 (the decimation is not an m-sequence).
    """
    pu = check_primitive(poly_u, field="poly_u")
    m = pu[0]
    n = (1 << m) - 1
    if np.gcd(int(q), n) != 1:
        raise out_of_range("q", f"coprime to 2^{m} - 1 = {n}", q)
    pv = berlekamp_massey(decimate(pu, q, 2 * m))
    return pu, check_primitive(pv, field="poly_v")
