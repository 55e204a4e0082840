"""Preferred-pair table: every entry proven three-valued; construction reproduces it."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from cdma_lidar.errors import ConfigError
from cdma_lidar.firmware_model.gold import periodic_xcorr, t_value
from cdma_lidar.firmware_model.lfsr import is_primitive, mseq
from cdma_lidar.firmware_model.pairs import (
    DECIMATIONS,
    PAIR_TABLE,
    PAPER_PAIR,
    berlekamp_massey,
    decimate,
    derive_pair,
    pair_degrees,
    pair_table,
    preferred_pairs,
)

ENTRIES = pair_table()
FAST = [p for p in ENTRIES if p.degree <= 13]
SLOW = [p for p in ENTRIES if p.degree > 13]


def three_valued(u, v):
    """Periodic cross-correlation of the two m-sequences: its value set and t(m)."""
    theta = periodic_xcorr(mseq(u), mseq(v))
    return set(np.unique(theta).tolist()), t_value(u[0])


def ident(p):
    return f"{p.degree}:{p.u}-{p.v}"


def check_entry(entry):
    assert entry.u[0] == entry.v[0] == entry.degree
    assert entry.u != entry.v
    assert is_primitive(entry.u) and is_primitive(entry.v)
    values, t = three_valued(entry.u, entry.v)
    assert values == {-1, -t, t - 2}, (entry, values)


@pytest.mark.parametrize("entry", FAST, ids=ident)
def test_table_pair_is_preferred(entry):
    check_entry(entry)


@pytest.mark.slow
@pytest.mark.parametrize("entry", SLOW, ids=ident)
def test_table_pair_is_preferred_high_degree(entry):
    check_entry(entry)


def test_every_degree_has_pairs():
    assert pair_degrees() == [m for m in range(5, 21) if m % 4]
    for m in pair_degrees():
        assert preferred_pairs(m), m


@pytest.mark.parametrize("degree", [8, 12, 16, 20])
def test_multiples_of_four_rejected(degree):
    with pytest.raises(ConfigError, match="multiple of 4"):
        preferred_pairs(degree)


@pytest.mark.parametrize("degree", [4, 21, 2.5, "x"])
def test_out_of_range_degree(degree):
    with pytest.raises(ConfigError, match="degree"):
        preferred_pairs(degree)


def test_paper_pairs_present_and_first():
    assert PAPER_PAIR == ((11, 2), (11, 8, 5, 2))
    assert preferred_pairs(11)[0] == PAPER_PAIR
    assert preferred_pairs(10)[0] == ((10, 3), (10, 8, 3, 2))
    assert preferred_pairs(13)[:3] == [
        ((13, 4, 3, 1), (13, 10, 9, 7, 5, 4)),
        ((13, 10, 9, 7, 5, 4), (13, 12, 8, 7, 6, 5)),
        ((13, 11, 8, 7, 4, 1), (13, 11, 10, 5, 4, 3, 2, 1)),
    ]


@pytest.mark.parametrize("pair", [((10, 7), (10, 9, 8, 5)), ((11, 9), (11, 10, 9, 7))])
def test_failing_paper_pairs_kept_out(pair):
    u, v = pair
    assert is_primitive(u) and is_primitive(v)
    values, t = three_valued(u, v)
    assert not values <= {-1, -t, t - 2}
    assert pair not in preferred_pairs(u[0])


def test_derived_rows_reproduce():
    for entry in ENTRIES:
        if "decimation of u by" in entry.source:
            q = int(entry.source.rsplit(" ", 1)[1])
            kind = "odd" if entry.degree % 2 else "2 mod 4"
            assert q in DECIMATIONS[kind]
            assert derive_pair(entry.u, q) == (entry.u, entry.v), entry


@pytest.mark.parametrize("m", [m for m in sorted(PAIR_TABLE) if m <= 11])
def test_decimation_construction_gives_preferred_pairs(m):
    kind = "odd" if m % 2 else "2 mod 4"
    u = PAIR_TABLE[m][0].u
    for q in DECIMATIONS[kind]:
        pu, pv = derive_pair(u, q)
        values, t = three_valued(pu, pv)
        assert values == {-1, -t, t - 2}, (m, q)
        # the decimated sequence is a shift of v's m-sequence
        d = decimate(u, q)
        assert np.concatenate([mseq(pv)] * 2).tobytes().find(d.tobytes()) >= 0


def test_decimation_by_non_coprime_rejected():
    with pytest.raises(ConfigError, match="q"):
        derive_pair((10, 3), 3)


@given(st.sampled_from([p.u for p in FAST] + [p.v for p in FAST]), st.integers(0, 4000))
def test_berlekamp_massey_recovers_polynomial(poly, offset):
    m = poly[0]
    bits = mseq(poly, chips=offset + 2 * m)[offset:]
    assert berlekamp_massey(bits) == poly
