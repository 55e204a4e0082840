r"""Noise generators of many columns at once, equal to ``numpy.random.default_rng(key)``.

Every rendered column draws its noise from its own generator, seeded with the key
``(seed, stream, frame, column)`` (:class:`cdma_lidar.scene.instrument.Instrument`), so
columns can be rendered in any order. ``default_rng(key)`` spends about 15 us per column
hashing the key (numpy's ``SeedSequence``, in Python-level loops): a sixth of a warm
``accumulated`` frame of 160 columns. The hash is the same arithmetic for every key of the
same length, so it is done here once for all keys, on arrays::

    key (ints) --32-bit words--> entropy (n, E) --mix_entropy--> pool (n, 4)
        --generate_state(4, uint64)--> (n, 4) uint64 --PCG64 seeding (numpy, C)--> Generator

(:func:`seed_words` stops at the (n, 4) words, which the compiled noise kernels seed
their own copy of PCG64 with: :mod:`cdma_lidar.scene.noise_kernel`.)

``SeedSequence``'s algorithm (numpy/random/bit_generator.pyx, pool size 4): each word
is ``hashmix``-ed with a running constant (INIT_A, times MULT_A per use) into the pool,
every pool word is mixed into every other, any further words into each, and the state
is read out with a second running constant (INIT_B, MULT_B). All arithmetic modulo
2**32. tests/scene/test_streams.py checks the generators' states against
``default_rng`` for arbitrary keys, bit for bit.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from numpy.typing import NDArray

from cdma_lidar.errors import ConfigError

__all__ = ["from_seed_words", "generators", "seed_words"]

_INIT_A, _MULT_A = 0x43B0D7E5, 0x931E8875
_INIT_B, _MULT_B = 0x8B51F9DD, 0x58F38DED
_MIX_MULT_L, _MIX_MULT_R = 0xCA01F9DD, 0x4973F715
_POOL = 4
_MASK = 0xFFFFFFFF


def _words(value: int) -> list[int]:
    """The 32-bit words of a non-negative int, least significant first (0: one word)."""
    if value < 0:
        raise ConfigError(f"a key must be non-negative integers, not {value}", "key")
    out = [value & _MASK]
    value >>= 32
    while value:
        out.append(value & _MASK)
        value >>= 32
    return out


class _Hash:
    """``hashmix`` with its running constant (advanced by ``mult`` on every use)."""

    def __init__(self, init: int, mult: int) -> None:
        self.const, self.mult = init, mult

    def __call__(self, value: NDArray[np.uint32]) -> NDArray[np.uint32]:
        value = value ^ np.uint32(self.const)
        self.const = (self.const * self.mult) & _MASK
        value = value * np.uint32(self.const)
        return value ^ (value >> np.uint32(16))


def _mix(x: NDArray[np.uint32], y: NDArray[np.uint32]) -> NDArray[np.uint32]:
    r = np.uint32(_MIX_MULT_L) * x - np.uint32(_MIX_MULT_R) * y
    return r ^ (r >> np.uint32(16))


def _states(entropy: NDArray[np.uint32]) -> NDArray[np.uint64]:
    """(n, 4) uint64 ``SeedSequence(row).generate_state(4, np.uint64)`` of (n, E) words."""
    n, e = entropy.shape
    h = _Hash(_INIT_A, _MULT_A)
    zero = np.zeros(n, dtype=np.uint32)
    pool = [h(entropy[:, i] if i < e else zero) for i in range(_POOL)]
    for src in range(_POOL):
        for dst in range(_POOL):
            if src != dst:
                pool[dst] = _mix(pool[dst], h(pool[src]))
    for src in range(_POOL, e):
        for dst in range(_POOL):
            pool[dst] = _mix(pool[dst], h(entropy[:, src]))
    out = _Hash(_INIT_B, _MULT_B)
    words = np.stack([out(pool[i % _POOL]) for i in range(8)], axis=1).astype("<u4")
    return words.view("<u8").astype(np.uint64)


class _State(np.random.bit_generator.ISeedSequence):
    """A seed sequence that hands PCG64 the state words computed for it."""

    def __init__(self, words: NDArray[np.uint64]) -> None:
        self.words = words

    def generate_state(self, n_words: int, dtype: type = np.uint32) -> NDArray[np.uint64]:
        if n_words != 4 or (dtype is not np.uint64 and np.dtype(dtype) != np.uint64):
            raise NotImplementedError("only PCG64's seeding (4 uint64 words) is precomputed")
        return self.words


def generators(keys: Sequence[Sequence[int]]) -> list[np.random.Generator]:
    """``[numpy.random.default_rng(list(key)) for key in keys]``, the hashing done once
    for all keys of the same word length (non-negative ints, any size): PCG64 generators
    seeded with :func:`seed_words`."""
    return from_seed_words(seed_words(keys))


def from_seed_words(words: NDArray[np.uint64]) -> list[np.random.Generator]:
    """A numpy PCG64 Generator seeded with each row of (n, 4) :func:`seed_words`."""
    return [np.random.Generator(np.random.PCG64(_State(row))) for row in words]


def seed_words(keys: Sequence[Sequence[int]]) -> NDArray[np.uint64]:
    """(n, 4) uint64: the words ``numpy.random.default_rng(list(key))`` seeds its PCG64
    with (``SeedSequence(key).generate_state(4, np.uint64)``: state high, low, increment
    high, low), for each key.

    Keys of one length whose values all fit in 32 bits (a frame's render keys) are
    their own entropy words, read in one array; any other keys are split into words
    value by value."""
    try:
        flat = np.array(keys)
    except (ValueError, OverflowError, TypeError):  # ragged keys: the word-by-word path
        flat = None
    if (flat is not None and flat.ndim == 2 and flat.size and flat.dtype.kind in "iu"
            and flat.min() >= 0 and flat.max() <= _MASK):
        return _states(flat.astype(np.uint32))
    entropy = [[w for v in key for w in _words(int(v))] for key in keys]
    out = np.empty((len(keys), 4), dtype=np.uint64)
    for length in {len(e) for e in entropy}:
        where = [i for i, e in enumerate(entropy) if len(e) == length]
        out[where] = _states(np.array([entropy[i] for i in where], dtype=np.uint32)
                             .reshape(len(where), length))
    return out
