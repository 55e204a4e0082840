"""UID necklaces, u(n), polarity modulation and the candidate counts of eqs. 52/53."""

from __future__ import annotations

import itertools

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from cdma_lidar.errors import ConfigError
from cdma_lidar.firmware_model.gold import bipolar, gold_code
from cdma_lidar.firmware_model.pairs import PAPER_PAIR
from cdma_lidar.firmware_model.uid import (
    candidates_direct,
    candidates_uid,
    canonical_necklace,
    direct_length,
    necklace_count,
    necklaces,
    polarity_modulate,
    rotations,
    uid_bits,
    uid_length,
    uid_to_str,
)

# OEIS A000031, number of binary necklaces of length n = 1..16
A000031 = [2, 3, 4, 6, 8, 14, 20, 36, 60, 108, 188, 352, 632, 1182, 2192, 4116]


def brute_force_classes(n):
    """Rotation classes of all n-bit strings, by explicit string rotation."""
    classes = set()
    for bits in itertools.product("01", repeat=n):
        s = "".join(bits)
        classes.add(min(s[r:] + s[:r] for r in range(n)))
    return classes


def test_paper_example_three_bits():
    assert necklace_count(3) == 4  # eq. 51
    assert necklaces(3) == [0, 1, 3, 7]
    assert [uid_to_str(u, 3) for u in necklaces(3)] == ["000", "100", "110", "111"]
    # the paper's names 000, 111, 101, 010 are members of the same four classes
    assert sorted(canonical_necklace(int(s[::-1], 2), 3) for s in ("111", "000", "101", "010")) \
        == [0, 1, 3, 7]


@pytest.mark.parametrize("n", range(1, 17))
def test_count_equals_eq50_and_oeis(n):
    assert necklace_count(n) == A000031[n - 1]
    assert len(necklaces(n)) == necklace_count(n)


@pytest.mark.parametrize("n", range(1, 11))
def test_necklaces_match_brute_force_classes(n):
    assert len(brute_force_classes(n)) == len(necklaces(n))


@given(st.integers(1, 12))
def test_necklaces_pairwise_not_rotations(n):
    reps = necklaces(n)
    seen = set()
    for value in reps:
        rots = set(rotations(value, n))
        assert canonical_necklace(value, n) == value == min(rots)
        assert not rots & seen  # no representative is a rotation of another
        seen |= rots
    assert seen == set(range(1 << n))  # every n-bit value lies in exactly one class


@given(st.integers(1, 16), st.data())
def test_canonical_is_rotation_invariant(n, data):
    value = data.draw(st.integers(0, (1 << n) - 1))
    r = data.draw(st.integers(0, n - 1))
    assert canonical_necklace(rotations(value, n)[r], n) == canonical_necklace(value, n)


@given(st.integers(1, 6), st.data())
def test_polarity_modulate_bipolar_product(n, data):
    uid = data.draw(st.integers(0, (1 << n) - 1))
    index = data.draw(st.integers(0, 2048))
    code = gold_code(*PAPER_PAIR, index)
    tx = polarity_modulate(code, uid, n)
    assert tx.shape == (n * 2047,) and tx.dtype == np.uint8
    periods = bipolar(tx).reshape(n, 2047).astype(int)
    signs = (-1) ** uid_bits(uid, n).astype(int)
    assert np.array_equal(periods, signs[:, None] * bipolar(code)[None, :])


def test_polarity_modulate_keeps_leading_axes():
    codes = np.array([[0, 1, 1], [1, 0, 0]], dtype=np.uint8)
    out = polarity_modulate(codes, 0b10, 2)
    assert out.tolist() == [[0, 1, 1, 1, 0, 0], [1, 0, 0, 0, 1, 1]]


def test_candidate_counts_eq52_eq53():
    # main text: 3-bit UID on order 11 ~ order 13 without UID
    assert candidates_uid(11, 0) == 2049 * 2
    assert candidates_direct(11, 2) == 8193
    for m in range(5, 12):
        for l in range(1, 5):  # noqa: E741
            assert candidates_uid(m, l) == ((1 << m) + 1) * necklace_count(1 << l)
            assert candidates_direct(m, l) == (1 << (m + l)) + 1
            assert uid_length(m, l) < direct_length(m, l)
    # Fig. 17, order 9: a UID gives more candidates than direct spreading from l = 2 on
    assert candidates_uid(9, 2) == 513 * 6 > candidates_direct(9, 2) == 2049


def test_errors():
    with pytest.raises(ConfigError, match="uid"):
        polarity_modulate(np.zeros(7, np.uint8), 8, 3)
    with pytest.raises(ConfigError, match="code_bits"):
        polarity_modulate(np.array([0, 2]), 0, 1)
    with pytest.raises(ConfigError, match="n"):
        necklaces(0)
    with pytest.raises(ConfigError, match="n"):
        necklaces(25)
