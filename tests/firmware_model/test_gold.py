"""Gold families: definition, vectorised family, FPGA seeds, correlation bounds."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from cdma_lidar.errors import ConfigError
from cdma_lidar.firmware_model.gold import (
    bipolar,
    family_size,
    gold_code,
    gold_codes,
    gold_family,
    gold_seeds,
    is_preferred_pair,
    periodic_xcorr,
    t_value,
    xcorr_values,
)
from cdma_lidar.firmware_model.lfsr import fibonacci_run, jump, mseq
from cdma_lidar.firmware_model.pairs import PAPER_PAIR, preferred_pairs

SMALL_PAIRS = [pair for m in (5, 6, 7, 9, 10, 11) for pair in preferred_pairs(m)]


def direct_member(u, v, k):
    """Member k straight from the definition, chip by chip."""
    n = len(u)
    if k == n:
        return u.copy()
    if k == n + 1:
        return v.copy()
    return np.array([u[i] ^ v[(i - k) % n] for i in range(n)], dtype=np.uint8)


@st.composite
def pair_and_index(draw):
    pu, pv = draw(st.sampled_from(SMALL_PAIRS))
    n = (1 << pu[0]) - 1
    return pu, pv, draw(st.integers(0, n + 1))


def test_constants():
    assert t_value(11) == 65
    assert t_value(10) == 65
    assert t_value(13) == 129
    assert family_size(11) == 2049


@given(pair_and_index())
def test_gold_code_matches_definition(pik):
    pu, pv, k = pik
    u, v = mseq(pu), mseq(pv)
    assert np.array_equal(gold_code(pu, pv, k), direct_member(u, v, k))


@given(pair_and_index(), st.integers(0, 5000))
def test_gold_code_chips_repeat_periodically(pik, chips):
    pu, pv, k = pik
    code = gold_code(pu, pv, k)
    long = gold_code(pu, pv, k, chips=chips)
    assert np.array_equal(long, code[np.arange(chips) % len(code)])


@settings(max_examples=10)
@given(st.sampled_from(SMALL_PAIRS))
def test_family_rows_equal_members(pair):
    pu, pv = pair
    fam = gold_family(pu, pv)
    n = (1 << pu[0]) - 1
    assert fam.shape == (n + 2, n) and fam.dtype == np.uint8
    for k in (0, 1, 2, n // 2, n - 1, n, n + 1):
        assert np.array_equal(fam[k], gold_code(pu, pv, k)), k
    assert len({row.tobytes() for row in fam}) == n + 2  # all members distinct


def test_family_with_seeds():
    pu, pv = PAPER_PAIR
    fam = gold_family(pu, pv, seed_u="10000000000", seed_v="01010101010")
    for k in (0, 7, 2047, 2048):
        assert np.array_equal(
            fam[k], gold_code(pu, pv, k, seed_u="10000000000", seed_v="01010101010"))


@given(pair_and_index())
def test_gold_seeds_two_free_running_registers(pik):
    pu, pv, k = pik
    seed_u, seed_v = gold_seeds(pu, pv, k)
    n = (1 << pu[0]) - 1
    u = fibonacci_run(pu, seed_u, 2 * n, allow_zero=True)[0]
    v = fibonacci_run(pv, seed_v, 2 * n, allow_zero=True)[0]
    expected = gold_code(pu, pv, k, chips=2 * n)
    assert np.array_equal(u ^ v, expected)


def test_gold_seeds_paper_pair_member_zero():
    assert gold_seeds(*PAPER_PAIR, 0) == ("1" * 11, "1" * 11)
    assert gold_seeds(*PAPER_PAIR, 2047) == ("1" * 11, "0" * 11)
    assert gold_seeds(*PAPER_PAIR, 2048) == ("0" * 11, "1" * 11)


@pytest.mark.parametrize("pair", [p for m in (5, 6, 7) for p in preferred_pairs(m)])
def test_whole_family_max_correlation_is_t(pair):
    pu, pv = pair
    m = pu[0]
    fam = gold_family(pu, pv)
    spec = np.fft.rfft(bipolar(fam).astype(float), axis=1)
    theta = np.rint(np.fft.irfft(np.conj(spec)[:, None, :] * spec[None, :, :],
                                 n=fam.shape[1], axis=2)).astype(int)
    t = t_value(m)
    allowed = {-1, -t, t - 2}
    auto = theta[np.arange(len(fam)), np.arange(len(fam))]
    assert (auto[:, 0] == fam.shape[1]).all()
    assert set(np.unique(auto[:, 1:]).tolist()) <= allowed
    off = ~np.eye(len(fam), dtype=bool)
    cross = theta[off]
    assert set(np.unique(cross).tolist()) <= allowed
    assert np.abs(cross).max() == t


@given(st.sampled_from([p for m in (9, 10, 11) for p in preferred_pairs(m)]), st.data())
def test_sampled_members_cross_correlation_bound(pair, data):
    pu, pv = pair
    n = (1 << pu[0]) - 1
    i = data.draw(st.integers(0, n + 1))
    j = data.draw(st.integers(0, n + 1).filter(lambda x: x != i))
    theta = periodic_xcorr(gold_code(pu, pv, i), gold_code(pu, pv, j))
    t = t_value(pu[0])
    assert set(theta.tolist()) <= {-1, -t, t - 2}
    assert np.abs(theta).max() <= t


def test_periodic_xcorr_definition():
    rng = np.random.default_rng(7)
    a = rng.integers(0, 2, 31).astype(np.uint8)
    b = rng.integers(0, 2, 31).astype(np.uint8)
    direct = [int(np.sum(bipolar(a) * np.roll(bipolar(b), -k))) for k in range(31)]
    assert periodic_xcorr(a, b).tolist() == direct


def test_paper_pair_three_valued_counts():
    values = xcorr_values(*PAPER_PAIR)
    assert values == {-65: 496, -1: 1023, 63: 528}
    assert is_preferred_pair(*PAPER_PAIR)
    assert not is_preferred_pair((11, 9), (11, 10, 9, 7))
    assert not is_preferred_pair((11, 2), (11, 2))


def test_prefix_of_a_degree_32_member_without_a_whole_period():
    # member N - 3 is u[n] ^ v[n + 3]: checkable from two short m-sequence prefixes
    pu, pv = (32, 22, 2, 1), (32, 7, 5, 3, 2, 1)
    n = (1 << 32) - 1
    want = mseq(pu, chips=64) ^ mseq(pv, chips=67)[3:]
    assert np.array_equal(gold_code(pu, pv, n - 3, chips=64), want)
    assert np.array_equal(gold_code(pu, pv, n + 1, chips=10), mseq(pv, chips=10))


def test_errors():
    with pytest.raises(ConfigError, match="poly_u"):
        gold_family((17, 3), (17, 3, 2, 1))  # 17 GB: refused, not attempted
    with pytest.raises(ConfigError, match="chips"):
        gold_code(*PAPER_PAIR, 0, chips=-1)
    with pytest.raises(ConfigError, match="index"):
        gold_code(*PAPER_PAIR, 2049)
    with pytest.raises(ConfigError, match="index"):
        gold_seeds(*PAPER_PAIR, -1)
    with pytest.raises(ConfigError, match="poly_v"):
        gold_code((11, 2), (10, 3), 0)
    with pytest.raises(ConfigError, match="primitive"):
        gold_family((11, 1), (11, 2))


@pytest.mark.parametrize("pair", [p for m in (5, 6) for p in preferred_pairs(m)])
def test_every_family_row_matches_definition(pair):
    pu, pv = pair
    u, v = mseq(pu), mseq(pv)
    fam = gold_family(pu, pv)
    for k in range(len(fam)):
        assert np.array_equal(fam[k], direct_member(u, v, k)), k


@pytest.mark.parametrize(("pair", "indices"), [
    (((5, 2), (5, 4, 3, 2)), (0, 1, 30, 31, 32, 7, 0)),
    (((11, 2), (11, 8, 5, 2)), (0, 5, 2046, 2047, 2048)),
    (((7, 1), (7, 5, 3, 1)), ()),
])
def test_gold_codes_stack_the_requested_members(pair, indices):
    fam = gold_family(*pair)
    got = gold_codes(*pair, indices)
    assert got.dtype == np.uint8 and got.shape == (len(indices), fam.shape[1])
    np.testing.assert_array_equal(got, fam[list(indices)])
    got[:] = 1  # the caller owns the result; the cached m-sequences are untouched
    np.testing.assert_array_equal(gold_codes(*pair, indices), fam[list(indices)])


def test_gold_codes_name_the_bad_index():
    with pytest.raises(ConfigError, match=r"code_index must be an integer in 0\.\.32"):
        gold_codes((5, 2), (5, 4, 3, 2), (0, 33), field="code_index")
    with pytest.raises(ConfigError, match="index"):
        gold_codes((5, 2), (5, 4, 3, 2), (-1,))


def recurrence_member(pu, pv, k, chips, seed_u=None, seed_v=None):
    """Member k the way gold_code made it before it shared m-sequences: one Fibonacci
    recurrence per member, v's register jumped ahead by (N - k) mod N clocks."""
    n = (1 << pu[0]) - 1
    if k == n + 1:
        return mseq(pv, seed_v, chips)
    u = mseq(pu, seed_u, chips)
    return u if k == n else u ^ mseq(pv, jump(pv, seed_v, (n - k) % n), chips)


SHARED_PAIRS = [preferred_pairs(m)[0] for m in (5, 6, 7, 9, 10, 11, 13, 14, 15)]


@st.composite
def shared_cases(draw):
    pu, pv = draw(st.sampled_from(SHARED_PAIRS))
    m = pu[0]
    n = (1 << m) - 1
    k = draw(st.one_of(st.sampled_from([0, 1, 2, n - 1, n, n + 1, 1 << m]),
                       st.integers(0, n + 1)))
    chips = draw(st.sampled_from([None, 0, 1, n - 1, n, n + 1, 2 * n + 5]))
    seeds = draw(st.sampled_from([(None, None), ("1" + "0" * (m - 1), "0" * (m - 1) + "1"),
                                  ("01" * m, "110" * m)]))
    return pu, pv, k, chips, tuple(None if s is None else s[:m] for s in seeds)


@settings(max_examples=120, deadline=None)
@given(shared_cases())
def test_shared_msequences_equal_one_recurrence_per_member(case):
    # index 2^m is the last member (v); N = 2^m - 1 is u; degrees 3..15, default and
    # other seeds, a prefix, one period and more than one
    pu, pv, k, chips, (seed_u, seed_v) = case
    n = (1 << pu[0]) - 1
    got = gold_code(pu, pv, k, chips=chips, seed_u=seed_u, seed_v=seed_v)
    want = recurrence_member(pu, pv, k, n if chips is None else chips, seed_u, seed_v)
    assert got.dtype == np.uint8 and got.flags.writeable
    np.testing.assert_array_equal(got, want)


def test_degree_15_code_set_of_1200_members_equals_the_recurrence():
    pu, pv = preferred_pairs(15)[0]
    n = (1 << 15) - 1
    indices = [0, 1, 2, *range(1000, 1000 + 1195), n, n + 1]
    codes = np.stack([gold_code(pu, pv, k) for k in indices])
    np.testing.assert_array_equal(codes, gold_codes(pu, pv, indices))
    for row in (0, 1, 2, 600, len(indices) - 2, len(indices) - 1):
        np.testing.assert_array_equal(codes[row], recurrence_member(pu, pv, indices[row], n))
