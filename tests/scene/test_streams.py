"""The batched noise generators against numpy's default_rng, bit for bit."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from cdma_lidar.scene.streams import generators

_INT = st.one_of(st.integers(0, 3), st.integers(0, 2**32 - 1), st.integers(0, 2**80))


@settings(max_examples=60, deadline=None)
@given(keys=st.lists(st.lists(_INT, min_size=0, max_size=7), min_size=1, max_size=6))
def test_generators_equal_default_rng_for_any_keys(keys):
    """Keys of any length (shorter and longer than the pool of 4 words, ints beyond 32
    and 64 bits, mixed lengths in one call): the same PCG64 state as default_rng(key) and
    the same draws."""
    got = generators(keys)
    assert len(got) == len(keys)
    for key, g in zip(keys, got, strict=True):
        ref = np.random.default_rng(key)
        assert g.bit_generator.state == ref.bit_generator.state
        np.testing.assert_array_equal(g.standard_normal(5), ref.standard_normal(5))


_WORD = st.one_of(st.integers(0, 3), st.integers(0, 2**32 - 1), st.just(2**32 - 1))


@settings(max_examples=60, deadline=None)
@given(data=st.data(), length=st.integers(1, 7), n=st.integers(1, 9))
def test_keys_of_one_length_in_32_bits_equal_default_rng(data, length, n):
    """The one-array path (every key the same length, every value a single 32-bit word,
    the render's keys): the same states as default_rng, the extremes 0 and 2**32 - 1
    included; as numpy ints too."""
    keys = data.draw(st.lists(st.lists(_WORD, min_size=length, max_size=length),
                              min_size=n, max_size=n))
    if data.draw(st.booleans()):
        keys = [tuple(np.int64(v) for v in key) for key in keys]
    for key, g in zip(keys, generators(keys), strict=True):
        assert g.bit_generator.state == np.random.default_rng(
            [int(v) for v in key]).bit_generator.state


def test_the_scan_keys_of_a_frame_give_distinct_streams():
    """The render's keys (seed, stream, frame, column): every column its own stream, and
    a different frame a different one (not merely the same as default_rng's, which the
    property covers)."""
    first = [g.bit_generator.random_raw(2) for g in generators([(7, 0, 3, c) for c in range(64)])]
    assert len({tuple(x) for x in first}) == 64
    other = generators([(7, 0, 4, 0)])[0].bit_generator.random_raw(2)
    assert tuple(other) != tuple(first[0])


@pytest.mark.parametrize("keys", [[(0, -1)], [(0, 1), (0, -1)], [(0, np.int64(-1))]])
def test_negative_key_is_refused(keys):
    with pytest.raises(ValueError, match="non-negative"):
        generators(keys)
