"""User identification (UID) codes: binary necklaces and period polarity modulation.

Supplementary Note 11 and the main text's "Identity-enabled ranging". A UID of
n bits flips whole code periods: period p of the transmitted sequence is the
Gold code with every chip bit XORed with bit p of the UID, which in bipolar
form multiplies period p by (-1)^bit_p::

    uid = 0b110 (n = 3; bit 0 = period 0):
    period:      0          1          2
    chips:   c ^ 0 ... | c ^ 1 ... | c ^ 1 ...      (c = the Gold code, N chips)
    bipolar:   +c'     |   -c'     |   -c'

An asynchronous receiver sees the n periods with an unknown whole-period delay,
i.e. some rotation of the UID bits. UIDs are therefore chosen as *necklaces*:
one canonical representative per rotation class, here the smallest rotation as
an integer (bit p = period p). Their number is u(n) of eq. 50,
u(n) = (1/n) sum_{d | n} phi(d) 2^(n/d) (OEIS A000031): u(3) = 4, namely
0 (000), 1 (100), 3 (110), 7 (111) written period 0 first. (The paper names the
same four classes by other members: 000, 111, 101, 010.)

Candidate counts (eqs. 52, 53): an m-th order Gold family with an n = 2^l bit
UID offers (2^m + 1) u(2^l) sequences of n (2^m - 1) chips; plain direct
spreading of the same order m + l offers 2^(m+l) + 1 of 2^(m+l) - 1 chips.
"""

from __future__ import annotations

import logging
from math import gcd

import numpy as np

from cdma_lidar.checks import check_int, is_int
from cdma_lidar.errors import out_of_range

__all__ = [
    "MAX_UID_BITS",
    "candidates_direct",
    "candidates_uid",
    "canonical_necklace",
    "direct_length",
    "necklace_count",
    "necklaces",
    "polarity_modulate",
    "rotations",
    "uid_bits",
    "uid_length",
    "uid_to_str",
]

log = logging.getLogger(__name__)

#: Largest n for which :func:`necklaces` lists the representatives (2^24 candidates scanned).
MAX_UID_BITS = 24


def _check_bits(n: int, field: str = "n", hi: int | None = MAX_UID_BITS) -> int:
    """A UID width: 1..hi, or any positive integer when ``hi`` is None."""
    if hi is not None:
        return check_int(field, n, 1, hi)
    if not is_int(n) or int(n) < 1:
        raise out_of_range(field, "a positive integer", n)
    return int(n)


def _check_uid(uid: int, n: int, field: str = "uid") -> int:
    """A UID value of n bits: 0..2^n - 1."""
    return check_int(field, uid, 0, (1 << n) - 1)


def _totient(d: int) -> int:
    return sum(1 for k in range(1, d + 1) if gcd(k, d) == 1)


def necklace_count(n: int) -> int:
    """u(n), eq. 50: the number of binary necklaces of n bits (exact integer)."""
    n = _check_bits(n, hi=None)
    total = sum(_totient(d) * (1 << (n // d)) for d in range(1, n + 1) if n % d == 0)
    return total // n


def rotations(value: int, n: int) -> list[int]:
    """All n rotations of an n-bit value; rotation r moves bit p to bit (p + r) mod n."""
    n = _check_bits(n, hi=None)
    value = _check_uid(value, n, field="value")
    mask = (1 << n) - 1
    return [((value << r) | (value >> (n - r))) & mask for r in range(n)]


def canonical_necklace(value: int, n: int) -> int:
    """The smallest rotation of an n-bit value (the representative of its necklace)."""
    return min(rotations(value, n))


def necklaces(n: int) -> list[int]:
    """Canonical representatives of all n-bit necklaces, ascending; len == u(n).

    Vectorised over all 2^n values (n <= MAX_UID_BITS): a value is canonical when no
    rotation is smaller.
    """
    n = _check_bits(n)
    values = np.arange(1 << n, dtype=np.uint32)
    smallest = values.copy()
    rot = values.copy()
    top = np.uint32(n - 1)
    one = np.uint32(1)
    for _ in range(n - 1):
        rot = (rot >> one) | ((rot & one) << top)
        np.minimum(smallest, rot, out=smallest)
    return np.flatnonzero(smallest == values).tolist()


def uid_bits(uid: int, n: int) -> np.ndarray:
    """Bits of ``uid`` as uint8, index p = period p."""
    n = _check_bits(n, hi=None)
    uid = _check_uid(uid, n)
    return np.array([(uid >> p) & 1 for p in range(n)], dtype=np.uint8)


def uid_to_str(uid: int, n: int) -> str:
    """``uid`` as a bit string, period 0 first (``uid_to_str(1, 3) == "100"``)."""
    return "".join(str(b) for b in uid_bits(uid, n))


def polarity_modulate(code_bits: np.ndarray, uid: int, n: int) -> np.ndarray:
    """n periods of a code, period p XORed with bit p of ``uid`` (chip bits, uint8).

    ``code_bits`` has N chips on its last axis (leading axes, e.g. K channels, are
    kept); the result has n N chips: ``out[..., p N + i] = code[..., i] ^ bit_p``.
    In bipolar form that is period p multiplied by (-1)^bit_p.
    """
    code = np.asarray(code_bits)
    if code.ndim < 1 or code.shape[-1] == 0 or not np.isin(code, (0, 1)).all():
        raise out_of_range("code_bits", "a non-empty array of chip bits 0/1", code.shape)
    bits = uid_bits(uid, n)
    out = code.astype(np.uint8)[..., None, :] ^ bits[:, None]
    return out.reshape(*code.shape[:-1], n * code.shape[-1])


def candidates_uid(m: int, l: int) -> int:  # noqa: E741 - the paper's symbol
    """Eq. 52: (2^m + 1) u(2^l) sequences for an order-m Gold family with a 2^l-bit UID."""
    return ((1 << m) + 1) * necklace_count(1 << l)


def candidates_direct(m: int, l: int) -> int:  # noqa: E741 - the paper's symbol
    """Eq. 53: 2^(m+l) + 1 Gold codes of order m + l (direct spreading, no UID)."""
    return (1 << (m + l)) + 1


def uid_length(m: int, l: int) -> int:  # noqa: E741 - the paper's symbol
    """Chips of an order-m code carrying a 2^l-bit UID: 2^l (2^m - 1)."""
    return (1 << l) * ((1 << m) - 1)


def direct_length(m: int, l: int) -> int:  # noqa: E741 - the paper's symbol
    """Chips of an order-(m + l) code: 2^(m+l) - 1 (always longer than uid_length)."""
    return (1 << (m + l)) - 1
