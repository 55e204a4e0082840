"""Linear feedback shift registers over GF(2): the FPGA's code generator, bit for bit.

Polynomials are written as in the paper: a tuple of exponents, highest first,
constant term implied. ``(11, 2)`` is x^11 + x^2 + 1; its degree m is the
register length. Degrees 2 to 32 are supported. Their bit masks (coefficient
mask, wire mask, register tap mask) follow the one convention of
:mod:`cdma_lidar.poly`; :func:`normalize_poly` is the validation.

Fibonacci form (the FPGA's form)
--------------------------------
Stages are numbered 1..m. On every clock the new stage-1 bit is the XOR of the
stages named by the polynomial's exponents, every other stage takes the value
of the stage below it, and the chip that leaves is stage m. The chip of clock n
is stage m *before* clock n, so chip 0 is stage m of the seed::

    (11, 2):  x^11 + x^2 + 1

          +---------------- XOR <------------------------------+
          |                  ^                                 |
          v                  |                                 |
       +----+----+----+     +----+     +-----+     +-----+     |
       | s1 | s2 | s3 | ... | .. | ... | s10 | ... | s11 |--+--+--> chip n
       +----+----+----+     +----+     +-----+     +-----+
         stage 2 is tapped ---^   (exponent 2)   stage 11 is tapped (exponent 11 = m)

    clock:  s1' = s11 ^ s2          (XOR of the stages named by the exponents)
            s_j' = s_(j-1), j = 2..m (shift up by one)
            chip = s11 (before the clock)

Seeds are bit strings, stage 1 first (``"10000000000"`` sets s1 = 1 only); the
default seed is all ones. The output a[n] obeys a[n] = XOR_e a[n - e] for n >= m
(e over the exponents), its first m chips are stages m, m-1, ..., 1 of the seed,
and the register after n clocks holds stage j = a[n + m - j].

Galois form (reference model)
-----------------------------
Same stage numbering, but the register shifts *down*, the chip leaves at
stage 1, and the chip is XORed into each stage named by an exponent below m
(stage m simply receives it)::

    chip n <--+-- s1 <-- s2 <-(+)- s3 <- ... <- s_m <--+
              |                ^                        |
              +----------------+------------------------+
                     (XOR into stage e, each exponent e < m)

    clock:  o = s1;  s_j' = s_(j+1) ^ (o if j is an exponent), j = 1..m-1;  s_m' = o

Both forms produce sequences with the same recurrence, so with the same
polynomial they give the same m-sequence up to a phase. The Galois register
loaded with ``fibonacci_to_galois(poly, seed)`` reproduces the Fibonacci chips
from chip 0 exactly; :func:`galois_to_fibonacci` is the inverse. Loaded with the
same bit string both registers give cyclic shifts of one sequence.

scipy
-----
``scipy.signal.max_len_seq(m, state=seed[::-1], taps=[m - e for e in exps[1:]])``
returns exactly ``mseq(exps, seed)`` chip for chip, and its returned state is
our end state reversed (scipy's state is the next m chips, oldest first; see
:func:`scipy_arguments`). scipy's default tap table uses the same m - e
relation: its taps ``[9]`` for m = 11 are our ``(11, 2)``.

Jump-ahead
----------
The Fibonacci clock is the GF(2) matrix ``transition_matrix(poly)`` acting on
the state vector (stage 1 first); k clocks are its k-th power, computed by
square-and-multiply in O(m^3 log k) bit operations (:func:`jump`).
"""

from __future__ import annotations

import functools
import logging
from collections.abc import Sequence

import numpy as np

from cdma_lidar.checks import is_int
from cdma_lidar.errors import ConfigError, out_of_range
from cdma_lidar.poly import Poly, poly_to_mask, tap_mask

__all__ = [
    "MAX_DEGREE",
    "MIN_DEGREE",
    "FibonacciLFSR",
    "GaloisLFSR",
    "check_primitive",
    "fibonacci_run",
    "fibonacci_to_galois",
    "format_poly",
    "galois_run",
    "galois_to_fibonacci",
    "is_primitive",
    "jump",
    "jump_matrix",
    "mseq",
    "normalize_poly",
    "parse_poly",
    "parse_seed",
    "poly_degree",
    "prime_factors",
    "reciprocal_poly",
    "scipy_arguments",
    "seed_to_str",
    "transition_matrix",
]

log = logging.getLogger(__name__)

MIN_DEGREE = 2
MAX_DEGREE = 32


# --------------------------------------------------------------------------- polynomials


def parse_poly(text: str, field: str = "poly") -> Poly:
    """Parse ``"11,2"`` (or ``"[11, 2, 0]"``) into ``(11, 2)``.

    A trailing ``0`` (the paper's explicit constant term) is accepted and dropped.
    Raises ConfigError naming ``field`` for anything that is not a valid exponent list.
    """
    body = str(text).strip().strip("[]()").strip()
    parts = [p.strip() for p in body.replace(" ", ",").split(",") if p.strip()]
    try:
        exps = [int(p) for p in parts]
    except ValueError:
        raise out_of_range(field, "comma-separated exponents like 11,2", text) from None
    return normalize_poly(exps, field=field)


def normalize_poly(poly: Sequence[int] | str, field: str = "poly") -> Poly:
    """Check an exponent list and return it as a tuple, highest first, without the 0.

    Degree must be in MIN_DEGREE..MAX_DEGREE; exponents distinct, each 1..degree.
    """
    if isinstance(poly, str):
        return parse_poly(poly, field=field)
    try:
        exps = [int(e) for e in poly]
        whole = all(e == x for e, x in zip(exps, poly, strict=True) if not isinstance(x, str))
    except (TypeError, ValueError):
        exps, whole = [], False
    if not whole or any(isinstance(x, bool) for x in poly):
        raise out_of_range(field, "a sequence of integer exponents", poly)
    if exps and min(exps) == 0 and exps.count(0) == 1:
        exps.remove(0)
    if not exps:
        raise out_of_range(field, "a non-empty exponent list", poly)
    exps.sort(reverse=True)
    m = exps[0]
    if not MIN_DEGREE <= m <= MAX_DEGREE:
        raise out_of_range(field, f"of degree {MIN_DEGREE}..{MAX_DEGREE}", poly)
    if exps[-1] < 1 or len(set(exps)) != len(exps):
        raise out_of_range(field, f"distinct exponents in 1..{m} (constant implied)", poly)
    return tuple(exps)


def poly_degree(poly: Sequence[int]) -> int:
    """Degree m of a normalised polynomial (its highest exponent)."""
    return max(int(e) for e in poly)


def reciprocal_poly(poly: Sequence[int]) -> Poly:
    """x^m f(1/x): exponents e -> m - e. Its m-sequence is ours reversed in time."""
    p = normalize_poly(poly)
    m = p[0]
    return tuple(sorted([m] + [m - e for e in p[1:]], reverse=True))


def format_poly(poly: Sequence[int]) -> str:
    """``(11, 2)`` -> ``"11,2"``: the CLI and table form."""
    return ",".join(str(int(e)) for e in poly)


def _clmul(a: int, b: int) -> int:
    """Carry-less (GF(2)[x]) product of two coefficient masks."""
    result = 0
    while b:
        if b & 1:
            result ^= a
        a <<= 1
        b >>= 1
    return result


def _polymod(a: int, f: int) -> int:
    """a mod f in GF(2)[x]."""
    df = f.bit_length()
    while a.bit_length() >= df:
        a ^= f << (a.bit_length() - df)
    return a


def _x_pow_mod(k: int, f: int) -> int:
    """x^k mod f in GF(2)[x], square-and-multiply."""
    result, base = 1, _polymod(2, f)
    while k:
        if k & 1:
            result = _polymod(_clmul(result, base), f)
        base = _polymod(_clmul(base, base), f)
        k >>= 1
    return result


@functools.lru_cache(maxsize=64)
def prime_factors(n: int) -> tuple[int, ...]:
    """Distinct prime factors of n >= 1 by trial division (exact; n < 2^64 is quick
    when n = 2^m - 1 with m <= 32, as then sqrt(n) < 65536)."""
    factors = []
    d = 2
    while d * d <= n:
        if n % d == 0:
            factors.append(d)
            while n % d == 0:
                n //= d
        d += 1 if d == 2 else 2
    if n > 1:
        factors.append(n)
    return tuple(factors)


@functools.lru_cache(maxsize=4096)
def _is_primitive_cached(poly: Poly) -> bool:
    f = poly_to_mask(poly)
    m = poly[0]
    order = (1 << m) - 1
    if _x_pow_mod(order, f) != 1:
        return False
    return all(_x_pow_mod(order // p, f) != 1 for p in prime_factors(order))


def is_primitive(poly: Sequence[int] | str) -> bool:
    """True when the polynomial is primitive over GF(2): x has order exactly 2^m - 1
    modulo f (tested against every prime factor of 2^m - 1, exact integers)."""
    return _is_primitive_cached(normalize_poly(poly))


def check_primitive(poly: Sequence[int] | str, field: str = "poly") -> Poly:
    """Normalise ``poly`` and raise ConfigError (naming ``field``) unless it is primitive."""
    p = normalize_poly(poly, field=field)
    if not _is_primitive_cached(p):
        raise ConfigError(
            f"{field} must be a primitive polynomial (period 2^m - 1), "
            f"not {format_poly(p)} (x^{' + x^'.join(map(str, p))} + 1)",
            field=field,
        )
    return p


# --------------------------------------------------------------------------- seeds


def parse_seed(seed: str | Sequence[int] | np.ndarray | None, degree: int,
               field: str = "seed", allow_zero: bool = False) -> np.ndarray:
    """Register state as a uint8 array, index j-1 = stage j.

    ``seed`` is a bit string, stage 1 first (``"1011"``), a 0/1 sequence in the same
    order, or None for all ones. An all-zero seed is an error (the register would
    stay at zero) unless ``allow_zero``.
    """
    if seed is None:
        return np.ones(degree, dtype=np.uint8)
    if isinstance(seed, str):
        text = seed.strip()
        if len(text) != degree or set(text) - {"0", "1"}:
            raise out_of_range(field, f"a string of {degree} bits (0/1, stage 1 first)", seed)
        state = np.frombuffer(text.encode("ascii"), dtype=np.uint8) - ord("0")
    else:
        arr = np.asarray(seed)
        if arr.shape != (degree,) or not np.isin(arr, (0, 1)).all():
            raise out_of_range(field, f"{degree} bits (0/1, stage 1 first)", seed)
        state = arr.astype(np.uint8)
    if not allow_zero and not state.any():
        raise out_of_range(field, "a non-zero register state", seed)
    return state.copy()


def seed_to_str(state: Sequence[int] | np.ndarray) -> str:
    """State array (stage 1 first) -> bit string, stage 1 first."""
    return "".join("1" if int(b) else "0" for b in state)


# --------------------------------------------------------------------------- Fibonacci kernel


def _recurrence_fill(exps: Poly, out: np.ndarray, start: int) -> None:
    """Fill ``out[start:]`` so that out[t] = XOR_e out[t - e] (out[:start] given, start >= m).

    Vectorised by the Frobenius identity f(x)^(2^j) = f(x^(2^j)) over GF(2): the
    sequence also obeys out[t] = XOR_e out[t - e 2^j] once t >= m 2^j, which yields
    a block of e_min 2^j new chips from older ones in one numpy XOR per exponent.
    """
    m, emin = exps[0], exps[-1]
    total = out.shape[0]
    n = start
    while n < total:
        step = 1 << ((n // m).bit_length() - 1)  # largest 2^j with m 2^j <= n
        length = min(step * emin, total - n)
        dst = out[n : n + length]
        first = n - exps[0] * step
        if len(exps) == 1:
            np.copyto(dst, out[first : first + length])
        else:
            second = n - exps[1] * step
            np.bitwise_xor(out[first : first + length], out[second : second + length], out=dst)
            for e in exps[2:]:
                src = n - e * step
                dst ^= out[src : src + length]
        n += length


def _fib_kernel(exps: Poly, state: np.ndarray, chips: int) -> tuple[np.ndarray, np.ndarray]:
    m = exps[0]
    out = np.empty(chips + m, dtype=np.uint8)
    out[:m] = state[::-1]
    _recurrence_fill(exps, out, m)
    return out[:chips], out[chips:][::-1].copy()


def fibonacci_run(poly: Sequence[int] | str, state: str | Sequence[int] | np.ndarray | None,
                  chips: int, allow_zero: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """Clock a Fibonacci register ``chips`` times: returns ``(chips_out, end_state)``.

    Streaming form (state in, state out) so a sequence can be made in chunks:
    two calls with the returned state equal one call of the total length. Works for
    any valid polynomial (primitive or not). An all-zero state is an error unless
    ``allow_zero`` (the register then outputs zeros, as the hardware does).
    """
    exps = normalize_poly(poly)
    st = parse_seed(state, exps[0], allow_zero=allow_zero)
    chips = _check_chips(chips)
    return _fib_kernel(exps, st, chips)


def _check_chips(chips: int, field: str = "chips") -> int:
    """A chip count: any non-negative integer (no upper bound, so not ``check_int``)."""
    if not is_int(chips) or int(chips) < 0:
        raise out_of_range(field, "a non-negative integer", chips)
    return int(chips)


def mseq(poly: Sequence[int] | str, seed: str | Sequence[int] | np.ndarray | None = None,
         chips: int | None = None) -> np.ndarray:
    """The first ``chips`` chips (default one period, 2^m - 1) of the Fibonacci m-sequence.

    Chips are uint8 bits 0/1 (bit 0 -> +1, bit 1 -> -1 in bipolar form). The
    polynomial must be primitive and the seed non-zero (ConfigError otherwise).
    """
    exps = check_primitive(poly)
    m = exps[0]
    st = parse_seed(seed, m)
    n = (1 << m) - 1 if chips is None else _check_chips(chips)
    return _fib_kernel(exps, st, n)[0]


# --------------------------------------------------------------------------- jump-ahead


def transition_matrix(poly: Sequence[int] | str) -> np.ndarray:
    """The m x m GF(2) matrix M of one Fibonacci clock: state' = M state (stage 1 first)."""
    exps = normalize_poly(poly)
    m = exps[0]
    mat = np.zeros((m, m), dtype=np.uint8)
    mat[0, [e - 1 for e in exps]] = 1
    mat[np.arange(1, m), np.arange(m - 1)] = 1
    return mat


def _gf2_matmul(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return ((a.astype(np.int64) @ b.astype(np.int64)) & 1).astype(np.uint8)


def jump_matrix(poly: Sequence[int] | str, k: int) -> np.ndarray:
    """M^k over GF(2) by square-and-multiply: O(m^3 log k)."""
    if int(k) < 0:
        raise out_of_range("k", "a non-negative clock count", k)
    base = transition_matrix(poly)
    result = np.eye(base.shape[0], dtype=np.uint8)
    k = int(k)
    while k:
        if k & 1:
            result = _gf2_matmul(result, base)
        base = _gf2_matmul(base, base)
        k >>= 1
    return result


def jump(poly: Sequence[int] | str, state: str | Sequence[int] | np.ndarray | None,
         k: int) -> np.ndarray:
    """The Fibonacci register state after k clocks from ``state``, without clocking."""
    exps = normalize_poly(poly)
    st = parse_seed(state, exps[0])
    return _gf2_matmul(jump_matrix(exps, k), st[:, None])[:, 0]


# --------------------------------------------------------------------------- Galois form


def galois_run(poly: Sequence[int] | str, state: str | Sequence[int] | np.ndarray | None,
               chips: int) -> tuple[np.ndarray, np.ndarray]:
    """Clock the Galois register chip by chip (reference model): ``(chips_out, end_state)``.

    State is stage 1 first, like the Fibonacci form; see the module docstring.
    """
    exps = normalize_poly(poly)
    m = exps[0]
    st = parse_seed(state, m)
    chips = _check_chips(chips)
    reg = int(sum(int(b) << j for j, b in enumerate(st)))
    mask = tap_mask(exps)  # stage j is bit j - 1
    out = bytearray(chips)
    for n in range(chips):
        o = reg & 1
        out[n] = o
        reg >>= 1
        if o:
            reg ^= mask
    end = np.array([(reg >> j) & 1 for j in range(m)], dtype=np.uint8)
    return np.frombuffer(bytes(out), dtype=np.uint8).copy(), end


def fibonacci_to_galois(poly: Sequence[int] | str,
                        state: str | Sequence[int] | np.ndarray | None) -> np.ndarray:
    """Galois state whose chips equal the Fibonacci chips of ``state`` from chip 0.

    With o[n] the common output, the Galois stage j holds
    o[j-1] ^ XOR_{e exponent, e < j} o[j-1-e].
    """
    exps = normalize_poly(poly)
    m = exps[0]
    st = parse_seed(state, m)
    o = st[::-1]  # first m Fibonacci chips
    gal = o.copy()
    for e in exps[1:]:
        gal[e:] ^= o[: m - e]
    return gal


def galois_to_fibonacci(poly: Sequence[int] | str,
                        state: str | Sequence[int] | np.ndarray | None) -> np.ndarray:
    """Inverse of :func:`fibonacci_to_galois`: Fibonacci stage j = Galois chip m - j."""
    exps = normalize_poly(poly)
    first = galois_run(exps, state, exps[0])[0]
    return first[::-1].copy()


def scipy_arguments(poly: Sequence[int] | str,
                    seed: str | Sequence[int] | np.ndarray | None = None) -> dict[str, object]:
    """Keyword arguments making ``scipy.signal.max_len_seq(**kw)[0]`` equal ``mseq(poly, seed)``.

    ``nbits = m``, ``taps = [m - e for e < m]``, ``state = seed`` reversed (stage m first).
    """
    exps = normalize_poly(poly)
    m = exps[0]
    st = parse_seed(seed, m)
    return {"nbits": m, "state": st[::-1].astype(np.int8), "taps": [m - e for e in exps[1:]]}


# --------------------------------------------------------------------------- register classes


class FibonacciLFSR:
    """A Fibonacci register with a state: ``step(n)`` returns n chips and advances.

    ``clock()`` is the literal chip-by-chip FPGA model (Python integers, bit j-1 =
    stage j); ``step`` uses the vectorised kernel; both advance the same state.
    """

    def __init__(self, poly: Sequence[int] | str,
                 seed: str | Sequence[int] | np.ndarray | None = None) -> None:
        self.poly: Poly = check_primitive(poly)
        self.degree = self.poly[0]
        self.period = (1 << self.degree) - 1
        self.state = parse_seed(seed, self.degree)
        self._mask = tap_mask(self.poly)  # stage j is bit j - 1

    def clock(self) -> int:
        """One clock: returns the chip (stage m) and shifts in the feedback bit."""
        m = self.degree
        reg = int(sum(int(b) << j for j, b in enumerate(self.state)))
        chip = (reg >> (m - 1)) & 1
        fb = (reg & self._mask).bit_count() & 1
        reg = ((reg << 1) & ((1 << m) - 1)) | fb
        self.state = np.array([(reg >> j) & 1 for j in range(m)], dtype=np.uint8)
        return chip

    def clock_many(self, chips: int) -> np.ndarray:
        """``chips`` clocks done one by one in Python (the baseline for benchmarks)."""
        m = self.degree
        reg = int(sum(int(b) << j for j, b in enumerate(self.state)))
        full, mask, top = (1 << m) - 1, self._mask, m - 1
        out = bytearray(chips)
        for n in range(chips):
            out[n] = (reg >> top) & 1
            reg = ((reg << 1) & full) | ((reg & mask).bit_count() & 1)
        self.state = np.array([(reg >> j) & 1 for j in range(m)], dtype=np.uint8)
        return np.frombuffer(bytes(out), dtype=np.uint8).copy()

    def step(self, chips: int) -> np.ndarray:
        """The next ``chips`` chips (vectorised); the state advances by ``chips`` clocks."""
        bits, self.state = _fib_kernel(self.poly, self.state, _check_chips(chips))
        return bits

    def jump(self, k: int) -> None:
        """Advance the state by k clocks in O(m^3 log k) without producing chips."""
        self.state = jump(self.poly, self.state, k)

    @property
    def seed_str(self) -> str:
        """The current state as a bit string, stage 1 first."""
        return seed_to_str(self.state)


class GaloisLFSR:
    """A Galois register (reference model, chip by chip); see the module docstring."""

    def __init__(self, poly: Sequence[int] | str,
                 seed: str | Sequence[int] | np.ndarray | None = None) -> None:
        self.poly: Poly = check_primitive(poly)
        self.degree = self.poly[0]
        self.state = parse_seed(seed, self.degree)

    def step(self, chips: int) -> np.ndarray:
        """The next ``chips`` chips; the state advances."""
        bits, self.state = galois_run(self.poly, self.state, chips)
        return bits

    def to_fibonacci(self) -> np.ndarray:
        """The Fibonacci state that produces the same chips from now on."""
        return galois_to_fibonacci(self.poly, self.state)
