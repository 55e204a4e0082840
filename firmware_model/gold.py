"""Gold code families of a preferred pair, their FPGA seeds, and periodic correlations.

Family (Supplementary Note 2, eq. 2) of a pair (u, v) of degree m, N = 2^m - 1,
u and v the Fibonacci m-sequences of ``poly_u`` and ``poly_v`` (default seeds
all ones, see :mod:`cdma_lidar.firmware_model.lfsr`)::

    member k, 0 <= k < N:   c_k[n] = u[n] XOR v[(n - k) mod N]   (v delayed by k chips)
    member N:               u
    member N + 1:           v                                    (2^m + 1 codes)

Chips are uint8 bits; the bipolar chip is +1 for bit 0 and -1 for bit 1.

Periodic correlation of bipolar sequences a', b' of length N (lag k in chips)::

    theta_ab(k) = sum_n a'[n] b'[(n + k) mod N]

computed by FFT and rounded to the exact integer. A preferred pair has
theta_uv(k) in {-1, -t(m), t(m) - 2} for every k, t(m) = 1 + 2^floor((m + 2) / 2);
then every pair of distinct family members, and every member against itself at
k != 0, also stays within {-1, -t(m), t(m) - 2}.

FPGA seeds: the hardware runs two free-running Fibonacci registers from chip 0
and XORs them. ``gold_seeds`` loads u with its default seed and v with the state
the default v register has after (N - k) mod N clocks (jump-ahead), so the XOR
is member k. For members N and N + 1 the other register is loaded with zeros
(an all-zero Fibonacci register outputs 0 for ever).
"""

from __future__ import annotations

import functools
import logging
from collections.abc import Sequence

import numpy as np
from numpy.lib.stride_tricks import sliding_window_view
from numpy.typing import NDArray

from cdma_lidar.checks import check_int
from cdma_lidar.errors import ConfigError, out_of_range
from cdma_lidar.firmware_model.lfsr import (
    _check_chips,
    check_primitive,
    jump,
    mseq,
    parse_seed,
    seed_to_str,
)
from cdma_lidar.poly import Poly

__all__ = [
    "MAX_FAMILY_DEGREE",
    "MAX_SHARED_DEGREE",
    "bipolar",
    "check_pair",
    "family_size",
    "gold_code",
    "gold_codes",
    "gold_family",
    "gold_seeds",
    "is_preferred_pair",
    "periodic_xcorr",
    "t_value",
    "xcorr_values",
]

log = logging.getLogger(__name__)

Seed = str | Sequence[int] | np.ndarray | None

#: Largest degree :func:`gold_family` builds whole (degree 16: 4.3 GB of chips).
MAX_FAMILY_DEGREE = 16
#: Largest degree whose m-sequences :func:`gold_code` generates whole and shares
#: (2^20 - 1 chips: 1 MB each); above it each call clocks only the chips it returns.
MAX_SHARED_DEGREE = 20


def t_value(m: int) -> int:
    """t(m) = 1 + 2^floor((m + 2) / 2): the Gold bound on |cross-correlation|."""
    return 1 + (1 << ((int(m) + 2) // 2))


def family_size(m: int) -> int:
    """Number of codes in a degree-m Gold family: 2^m + 1."""
    return (1 << int(m)) + 1


def check_pair(poly_u: Sequence[int] | str, poly_v: Sequence[int] | str,
               field_u: str = "poly_u", field_v: str = "poly_v") -> tuple[Poly, Poly]:
    """Normalise two primitive polynomials of one degree (ConfigError otherwise)."""
    pu = check_primitive(poly_u, field=field_u)
    pv = check_primitive(poly_v, field=field_v)
    if pu[0] != pv[0]:
        raise out_of_range(field_v, f"of the same degree as {field_u} ({pu[0]})", poly_v)
    return pu, pv


def _check_index(index: int, n: int, field: str = "index") -> int:
    """A member index of a family of code length n: 0..n + 1."""
    return check_int(field, index, 0, n + 1)


def gold_code(poly_u: Sequence[int] | str, poly_v: Sequence[int] | str, index: int,
              chips: int | None = None, seed_u: Seed = None, seed_v: Seed = None) -> np.ndarray:
    """Member ``index`` of the Gold family (see module docstring) as uint8 chip bits.

    ``chips`` defaults to one period N; longer requests repeat the code periodically.
    ``seed_u``/``seed_v`` choose the phases of u and v (bit strings, stage 1 first).

    Member k is u XOR v delayed by k chips, and v delayed by k is a shift of one shared
    v: up to degree :data:`MAX_SHARED_DEGREE` both m-sequences are generated once per
    (polynomial, seed) and kept (:func:`_msequence`), so K members cost one XOR of N
    chips each, not one recurrence each. Above it (a short prefix of a degree-32
    member, say) v's register is started k chips early, i.e. from its seed jumped
    ahead by (N - k) mod N clocks (the FPGA's own trick, see :func:`gold_seeds`):
    O(chips), not O(2^m).
    """
    pu, pv = check_pair(poly_u, poly_v)
    m = pu[0]
    n = (1 << m) - 1
    k = _check_index(index, n)
    chips = n if chips is None else _check_chips(chips)
    if m > MAX_SHARED_DEGREE:
        if k == n + 1:
            return mseq(pv, seed_v, chips)
        u = mseq(pu, seed_u, chips)
        if k == n:
            return u
        return u ^ mseq(pv, jump(pv, seed_v, (n - k) % n), chips)
    u = None if k == n + 1 else _msequence(pu, seed_to_str(parse_seed(seed_u, m)))
    v = None if k == n else _msequence(pv, seed_to_str(parse_seed(seed_v, m)))
    if u is None or v is None:
        one = v if u is None else u
    else:  # v[(t - k) mod N]: v shifted right by k
        one = u ^ np.concatenate([v[n - k:], v[:n - k]])
    return one.copy() if chips == n else np.resize(one, chips)


@functools.lru_cache(maxsize=16)
def _msequence(poly: Poly, seed: str) -> NDArray[np.uint8]:
    """One period of the m-sequence of a checked ``poly`` and ``seed`` (stage 1 first),
    read-only: shared by :func:`gold_code` calls."""
    seq = mseq(poly, seed)
    seq.flags.writeable = False
    return seq


def gold_family(poly_u: Sequence[int] | str, poly_v: Sequence[int] | str,
                seed_u: Seed = None, seed_v: Seed = None) -> np.ndarray:
    """All 2^m + 1 members, shape (2^m + 1, N) uint8; row k is ``gold_code(..., k)``.

    Vectorised: rows 0..N-1 are windows of v repeated twice (row k starts at
    N - k), XORed with u broadcast in one call, written straight into the result.
    """
    pu, pv = check_pair(poly_u, poly_v)
    if pu[0] > MAX_FAMILY_DEGREE:
        raise out_of_range("poly_u", f"of degree 2..{MAX_FAMILY_DEGREE} for a whole family "
                           f"((2^m + 1) x (2^m - 1) bytes); use gold_code per member", pu)
    n = (1 << pu[0]) - 1
    u = mseq(pu, seed_u)
    v = mseq(pv, seed_v)
    family = np.empty((n + 2, n), dtype=np.uint8)
    windows = sliding_window_view(np.concatenate([v, v]), n)  # windows[s] = vv[s:s+N]
    np.bitwise_xor(u, windows[n:0:-1], out=family[:n])  # s = N - k for k = 0..N-1
    family[n] = u
    family[n + 1] = v
    return family


def gold_codes(poly_u: Sequence[int] | str, poly_v: Sequence[int] | str,
               indices: Sequence[int], field: str = "index") -> NDArray[np.uint8]:
    """Members ``indices`` of the family, stacked: shape (len(indices), N) uint8 chip bits.

    Row i is ``gold_code(poly_u, poly_v, indices[i])`` (default seeds, one period).
    For the few members a device uses (the receiver's code set, the emitter's
    lasers): one XOR of u with a window of v repeated twice per member, and the
    m-sequences are kept (:func:`_msequence`), so a repeated call costs O(K N).
    An index outside 0..N+1 raises ConfigError naming ``field``.
    """
    pu, pv = check_pair(poly_u, poly_v)
    m = pu[0]
    u, v = _msequence(pu, "1" * m), _msequence(pv, "1" * m)
    n = u.size
    ks = [_check_index(k, n, field) for k in indices]
    out = np.empty((len(ks), n), dtype=np.uint8)
    vv = np.concatenate([v, v]) if any(k < n for k in ks) else v
    for row, k in enumerate(ks):
        if k == n:
            out[row] = u
        elif k == n + 1:
            out[row] = v
        else:
            np.bitwise_xor(u, vv[n - k : 2 * n - k], out=out[row])  # v[(i - k) mod N]
    return out


def gold_seeds(poly_u: Sequence[int] | str, poly_v: Sequence[int] | str,
               index: int) -> tuple[str, str]:
    """Seeds (stage 1 first) that make two free-running Fibonacci registers output
    member ``index`` from chip 0 when their chips are XORed.

    u: default seed (all ones); v: the default-seeded v register jumped ahead by
    (N - index) mod N clocks. Member N (u) loads v with zeros, member N + 1 (v)
    loads u with zeros.
    """
    pu, pv = check_pair(poly_u, poly_v)
    m = pu[0]
    n = (1 << m) - 1
    k = _check_index(index, n)
    ones = "1" * m
    zeros = "0" * m
    if k == n:
        return ones, zeros
    if k == n + 1:
        return zeros, ones
    return ones, seed_to_str(jump(pv, None, (n - k) % n))


def bipolar(bits: np.ndarray) -> np.ndarray:
    """Chip bits -> bipolar int8: 0 -> +1, 1 -> -1."""
    return (1 - 2 * np.asarray(bits, dtype=np.int8)).astype(np.int8)


def periodic_xcorr(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """theta_ab(k) = sum_n a'[n] b'[(n + k) mod N] for k = 0..N-1 (int64, exact).

    ``a`` and ``b`` are chip bits of equal length along the last axis (leading
    axes broadcast). Computed with real FFTs; every value is an integer of
    magnitude <= N, so float64 rounding is exact for N < 2^40.
    """
    a = np.asarray(a)
    b = np.asarray(b)
    if a.shape[-1] != b.shape[-1] or a.shape[-1] == 0:
        raise out_of_range("b", f"sequences of the same non-zero length as a ({a.shape[-1]})",
                           b.shape)
    n = a.shape[-1]
    fa = np.fft.rfft(bipolar(a).astype(np.float64), axis=-1)
    fb = np.fft.rfft(bipolar(b).astype(np.float64), axis=-1)
    theta = np.fft.irfft(np.conj(fa) * fb, n=n, axis=-1)
    return np.rint(theta).astype(np.int64)


def xcorr_values(poly_u: Sequence[int] | str, poly_v: Sequence[int] | str,
                 seed_u: Seed = None, seed_v: Seed = None) -> dict[int, int]:
    """The periodic cross-correlation values of u and v with their counts (over N lags)."""
    pu, pv = check_pair(poly_u, poly_v)
    theta = periodic_xcorr(mseq(pu, seed_u), mseq(pv, seed_v))
    values, counts = np.unique(theta, return_counts=True)
    return {int(v): int(c) for v, c in zip(values, counts, strict=True)}


def is_preferred_pair(poly_u: Sequence[int] | str, poly_v: Sequence[int] | str) -> bool:
    """True when every cross-correlation value is in {-1, -t(m), t(m) - 2} and u != v.

    Degrees that are multiples of 4 have no preferred pairs; the test still runs.
    """
    try:
        pu, pv = check_pair(poly_u, poly_v)
    except ConfigError:
        return False
    if pu == pv:
        return False
    t = t_value(pu[0])
    return set(xcorr_values(pu, pv)) <= {-1, -t, t - 2}

