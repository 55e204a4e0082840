"""LFSR: conventions, primitivity, jump-ahead, Galois and scipy equivalence, streaming."""

from __future__ import annotations

import itertools

import numpy as np
import pytest
import scipy.signal
from hypothesis import given, settings
from hypothesis import strategies as st

from cdma_lidar.errors import ConfigError
from cdma_lidar.firmware_model.gold import periodic_xcorr
from cdma_lidar.firmware_model.lfsr import (
    FibonacciLFSR,
    GaloisLFSR,
    fibonacci_run,
    fibonacci_to_galois,
    galois_run,
    galois_to_fibonacci,
    is_primitive,
    jump,
    jump_matrix,
    mseq,
    normalize_poly,
    parse_poly,
    parse_seed,
    prime_factors,
    reciprocal_poly,
    scipy_arguments,
    seed_to_str,
    transition_matrix,
)
from cdma_lidar.poly import mask_to_poly, poly_to_mask, tap_mask

# scipy's default taps (its private table, read here only as an independent list of
# primitive polynomials for every degree 2..32): taps t <-> our exponent m - t.
SCIPY_TAPS = scipy.signal._max_len_seq._mls_taps
SCIPY_POLYS = {m: tuple(sorted([m] + [m - t for t in taps], reverse=True))
               for m, taps in SCIPY_TAPS.items()}
SMALL_POLYS = [p for m, p in SCIPY_POLYS.items() if m <= 14] + [
    (11, 2), (11, 8, 5, 2), (10, 3), (10, 8, 3, 2), (13, 4, 3, 1), (5, 2), (7, 1)]

polys = st.sampled_from(SMALL_POLYS)


@st.composite
def poly_and_seed(draw, pool=SMALL_POLYS):
    poly = draw(st.sampled_from(pool))
    m = poly[0]
    bits = draw(st.lists(st.integers(0, 1), min_size=m, max_size=m).filter(any))
    return poly, "".join(map(str, bits))


def brute_force_distinct_states(poly, chips):
    """Number of distinct m-chip windows of the output: the distinct register states."""
    m = poly[0]
    out = fibonacci_run(poly, None, chips + m - 1)[0].astype(np.int64)
    windows = np.lib.stride_tricks.sliding_window_view(out, m)
    codes = windows @ (1 << np.arange(m, dtype=np.int64))
    return len(np.unique(codes))


# ----------------------------------------------------------------- polynomials


def test_parse_poly_forms():
    assert parse_poly("11,2") == (11, 2)
    assert parse_poly("[10,3,0]") == (10, 3)
    assert parse_poly("2, 11") == (11, 2)
    assert normalize_poly([13, 4, 3, 1]) == (13, 4, 3, 1)
    assert poly_to_mask((11, 2)) == (1 << 11) | 4 | 1
    assert mask_to_poly(poly_to_mask((13, 4, 3, 1))) == (13, 4, 3, 1)
    assert tap_mask((11, 2)) == (1 << 10) | 2  # stage j is bit j - 1
    assert reciprocal_poly((11, 2)) == (11, 9)


@pytest.mark.parametrize("bad", ["", "11,x", "1", "33,1", "11,11,2", "11,-2", "11,0,0"])
def test_parse_poly_rejects(bad):
    with pytest.raises(ConfigError, match="poly"):
        parse_poly(bad)


@pytest.mark.parametrize("bad", [[11, 2.5], [11, None], [True, 2], 5])
def test_normalize_poly_rejects_non_integer_exponents(bad):
    with pytest.raises(ConfigError, match="integer exponents"):
        normalize_poly(bad)


def test_primitive_counts_match_euler_phi():
    # number of primitive polynomials of degree m is phi(2^m - 1) / m
    for m in range(2, 10):
        n = (1 << m) - 1
        phi = n
        for p in prime_factors(n):
            phi = phi // p * (p - 1)
        found = [
            (m, *c)
            for w in range(0, m)
            for c in itertools.combinations(range(m - 1, 0, -1), w)
            if is_primitive((m, *c))
        ]
        assert len(found) == phi // m, m


def test_primitive_equals_full_period_brute_force():
    for m in range(2, 9):
        n = (1 << m) - 1
        for w in range(0, m):
            for c in itertools.combinations(range(m - 1, 0, -1), w):
                poly = (m, *c)
                assert is_primitive(poly) == (brute_force_distinct_states(poly, n) == n), poly


@pytest.mark.parametrize("m", sorted(SCIPY_POLYS))
def test_scipy_table_polys_primitive(m):
    assert is_primitive(SCIPY_POLYS[m])


@pytest.mark.parametrize("poly", [(4, 2), (4, 3, 2, 1), (6, 3), (11, 1), (32, 1)])
def test_non_primitive_rejected(poly):
    assert not is_primitive(poly)
    with pytest.raises(ConfigError, match="primitive"):
        mseq(poly)


def test_seed_errors():
    with pytest.raises(ConfigError, match="seed"):
        mseq((5, 2), seed="00000")
    with pytest.raises(ConfigError, match="seed"):
        mseq((5, 2), seed="1111")
    with pytest.raises(ConfigError, match="seed"):
        mseq((5, 2), seed="11121")
    with pytest.raises(ConfigError, match="chips"):
        mseq((5, 2), chips=-1)
    assert seed_to_str(parse_seed("10110", 5)) == "10110"


# ----------------------------------------------------------------- Fibonacci convention


def test_fibonacci_convention_by_hand():
    # (3, 1): s1' = s3 ^ s1; chip = s3. Seed "100": s1=1, s2=0, s3=0.
    reg = FibonacciLFSR((3, 1), "100")
    chips, states = [], []
    for _ in range(7):
        chips.append(reg.clock())
        states.append(reg.seed_str)
    assert states[:3] == ["110", "111", "011"]
    assert chips == [0, 0, 1, 1, 1, 0, 1]
    assert mseq((3, 1), "100").tolist() == chips
    assert mseq((11, 2))[:11].tolist() == [1] * 11  # default seed all ones


@given(poly_and_seed())
def test_vectorised_kernel_equals_chip_by_chip(ps):
    poly, seed = ps
    reg = FibonacciLFSR(poly, seed)
    n = min(3 * ((1 << poly[0]) - 1), 3000)
    assert np.array_equal(reg.clock_many(n), fibonacci_run(poly, seed, n)[0])
    assert reg.seed_str == seed_to_str(fibonacci_run(poly, seed, n)[1])


@given(poly_and_seed())
def test_mseq_period_and_balance(ps):
    poly, seed = ps
    n = (1 << poly[0]) - 1
    two = mseq(poly, seed, chips=2 * n)
    assert np.array_equal(two[:n], two[n:])
    assert int(two[:n].sum()) == (n + 1) // 2  # 2^(m-1) ones, 2^(m-1) - 1 zeros
    assert brute_force_distinct_states(poly, n) == n  # no shorter period


@given(poly_and_seed())
def test_two_valued_autocorrelation(ps):
    poly, seed = ps
    a = mseq(poly, seed)
    theta = periodic_xcorr(a, a)
    assert theta[0] == len(a)
    assert set(theta[1:].tolist()) == {-1}


@given(poly_and_seed(), st.lists(st.integers(0, 700), min_size=1, max_size=5))
def test_chunked_generation_equals_one_call(ps, sizes):
    poly, seed = ps
    state = seed
    parts = []
    for size in sizes:
        bits, state = fibonacci_run(poly, state, size)
        parts.append(bits)
    whole, end = fibonacci_run(poly, seed, sum(sizes))
    assert np.array_equal(np.concatenate(parts), whole)
    assert np.array_equal(state, end)
    reg = FibonacciLFSR(poly, seed)
    assert np.array_equal(np.concatenate([reg.step(s) for s in sizes]), whole)


# ----------------------------------------------------------------- jump-ahead


@given(poly_and_seed(), st.integers(0, 3000))
def test_jump_equals_clocking(ps, k):
    poly, seed = ps
    reg = FibonacciLFSR(poly, seed)
    reg.clock_many(k)
    assert seed_to_str(jump(poly, seed, k)) == reg.seed_str


@settings(max_examples=20)
@given(st.sampled_from(sorted(SCIPY_POLYS.values())), st.integers(0, 2**40), st.integers(0, 2**40))
def test_jump_composes_and_has_period(poly, a, b):
    n = (1 << poly[0]) - 1
    assert np.array_equal(jump(poly, jump(poly, None, a), b), jump(poly, None, a + b))
    assert np.array_equal(jump(poly, None, a), jump(poly, None, a % n))
    assert np.array_equal(jump_matrix(poly, n), np.eye(poly[0], dtype=np.uint8))


def test_transition_matrix_is_one_clock():
    poly = (13, 4, 3, 1)
    reg = FibonacciLFSR(poly, "1011001110001")
    before = reg.state.copy()
    reg.clock()
    assert np.array_equal((transition_matrix(poly).astype(int) @ before) & 1, reg.state)


# ----------------------------------------------------------------- Galois form


@given(poly_and_seed())
def test_fibonacci_equals_galois(ps):
    poly, seed = ps
    n = (1 << poly[0]) - 1
    fib = mseq(poly, seed)
    gal_state = fibonacci_to_galois(poly, seed)
    gal, _ = galois_run(poly, gal_state, n)
    assert np.array_equal(gal, fib)
    assert seed_to_str(galois_to_fibonacci(poly, gal_state)) == seed
    # Loaded with the same bits, the Galois register gives a cyclic shift of the same sequence.
    same = GaloisLFSR(poly, seed).step(n)
    doubled = np.concatenate([fib, fib]).tobytes()
    assert doubled.find(same.tobytes()) >= 0


def test_galois_convention_by_hand():
    # (3, 1): o = s1; s1' = s2 ^ o; s2' = s3; s3' = o.
    bits, end = galois_run((3, 1), "100", 3)
    assert bits.tolist() == [1, 1, 1]
    assert seed_to_str(end) == "011"


# ----------------------------------------------------------------- scipy


@given(poly_and_seed())
def test_scipy_max_len_seq_equivalence(ps):
    poly, seed = ps
    kw = scipy_arguments(poly, seed)
    n = (1 << poly[0]) - 1
    seq, state = scipy.signal.max_len_seq(**kw, length=n + 5)
    ours, end = fibonacci_run(poly, seed, n + 5)
    assert np.array_equal(seq.astype(np.uint8), ours)
    assert np.array_equal(state.astype(np.uint8), end[::-1])


@pytest.mark.parametrize("m", sorted(SCIPY_POLYS))
def test_scipy_default_taps_are_our_polynomials(m):
    seq, _ = scipy.signal.max_len_seq(m, length=4000)
    assert np.array_equal(seq.astype(np.uint8), mseq(SCIPY_POLYS[m], chips=4000))


@pytest.mark.parametrize("poly", [(2, 1), (32, 22, 2, 1)])
def test_degree_bounds_work(poly):
    m = poly[0]
    reg = FibonacciLFSR(poly)
    assert np.array_equal(reg.clock_many(100), mseq(poly, chips=100))
    assert np.array_equal(reg.state, jump(poly, None, 100))
    if m == 2:
        assert mseq(poly).tolist() == [1, 1, 0]
