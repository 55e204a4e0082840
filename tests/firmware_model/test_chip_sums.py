"""Integrate-and-dump into the chip domain against its definition, for every S the
doubling path and the prefix-sum path take, both despread signs and narrow inputs whose
window sums need the wider work type."""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from cdma_lidar.firmware_model.correlators.chip_domain import chip_sums
from cdma_lidar.firmware_model.receiver import ReceiverConfig, fast, reference


@settings(max_examples=150, deadline=None)
@given(s=st.integers(1, 12), n=st.integers(1, 9), c=st.integers(1, 3),
       sign=st.sampled_from([1, -1]), kind=st.sampled_from(["uniform", "rails"]),
       seed=st.integers(0, 2**32 - 1), out=st.booleans(), scratch=st.booleans())
def test_chip_sums_equal_the_definition(s, n, c, sign, kind, seed, out, scratch):
    rng = np.random.default_rng(seed)
    ns = n * s
    if kind == "uniform":
        d = rng.integers(-(1 << 15), 1 << 15, (c, ns))
    else:  # every sample at an int16 end: every window sum overflows int16
        d = rng.choice([-(1 << 15), (1 << 15) - 1], (c, ns))
    d = d.astype(np.int16)
    dest = np.empty((c, ns), dtype=np.int32) if out else None
    # a kept scratch array (filled with garbage: whatever a previous call left in it)
    spare = np.full((c, ns), 12345, dtype=np.int32) if scratch else None
    y = chip_sums(d, s, sign, np.int32, out=dest, scratch=spare)
    assert y.shape == (c, s, n) and y.dtype == np.int32
    big = d.astype(np.int64)
    for r in range(s):
        for m in range(n):
            want = sign * sum(big[:, (m * s + r + t) % ns] for t in range(s))
            assert y[:, r, m].tolist() == want.tolist()
    if out:
        assert np.shares_memory(y, dest)


@given(s=st.sampled_from([1, 2, 3, 4]))
@settings(max_examples=4, deadline=None)
def test_the_despread_of_the_lowest_16_bit_code_does_not_wrap(s):
    # b = 16, R = 1: the accumulators are int16 and -(-2^15) needs the wider chip-sum
    # type (this returned -2^15 before the negation was computed in that type)
    cfg = ReceiverConfig(adc_bits=16, samples_per_chip=s, averages=1, uid=1, gate_len=4)
    codes = np.array([[0, 1, 1, 0, 1, 0, 0]])
    x = np.full(cfg.column_samples(7), -(1 << 15), dtype=np.int16)
    x[::3] = 5
    assert fast(cfg, codes, x, method="matmul").mismatches(reference(cfg, codes, x)) == []
