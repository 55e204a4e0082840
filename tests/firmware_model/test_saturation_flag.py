"""The record's ``saturated`` flag: streaming reference and fast path agree, and it means a rail.

When the peak's ``out`` word is clipped, the lags of the plateau tie and the
reported lag can be early; ``saturated`` flags exactly the channels whose first
peak sits at a rail of ``out_bits``.
"""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from cdma_lidar.firmware_model.gold import gold_code
from cdma_lidar.firmware_model.output import saturated_flags
from cdma_lidar.firmware_model.pairs import preferred_pairs
from cdma_lidar.firmware_model.receiver import ReceiverConfig, ReferenceReceiver, fast
from cdma_lidar.rounding import ROUNDING_MODES

PAIR = preferred_pairs(5)[0]


@settings(max_examples=40, deadline=None)
@given(data=st.data())
def test_reference_and_fast_agree_on_saturation(data):
    s = data.draw(st.integers(1, 3))
    ns = 31 * s
    cfg = ReceiverConfig(
        adc_bits=data.draw(st.integers(8, 12)), samples_per_chip=s,
        averages=data.draw(st.integers(1, 3)), uid_bits=data.draw(st.integers(1, 2)),
        gate_start=data.draw(st.integers(0, ns - 1)), gate_len=data.draw(st.integers(1, 12)),
        out_shift=data.draw(st.integers(0, 4)),
        rounding=data.draw(st.sampled_from(ROUNDING_MODES)),
        out_bits=data.draw(st.integers(8, 12)), peaks=data.draw(st.integers(1, 2)),
        ghost_windows=((data.draw(st.integers(0, ns - 1)), data.draw(st.integers(1, 3))),)
        if data.draw(st.booleans()) else ())
    codes = np.stack([gold_code(*PAIR, i) for i in (0, 5, 9)])
    lo, hi = -(1 << (cfg.adc_bits - 1)), (1 << (cfg.adc_bits - 1)) - 1
    x = np.array(data.draw(st.lists(st.sampled_from([lo, hi, 0, 1, -1]),
                                    min_size=cfg.column_samples(31),
                                    max_size=cfg.column_samples(31))), dtype=np.int64)
    rx = ReferenceReceiver(cfg, codes)
    cut = data.draw(st.integers(0, len(x)))
    rx.feed(x[:cut])
    rx.feed(x[cut:])
    ref = rx.finish()
    assert not ref.mismatches(fast(cfg, codes, x))
    top = (1 << (cfg.out_bits - 1)) - 1
    want = [lag >= 0 and (p >= top or p <= -top - 1)
            for lag, p in zip(ref.peak_lag, ref.peak, strict=True)]
    assert ref.saturated.tolist() == want


def test_flag_examples():
    assert saturated_flags([3, 3, 3, -1], [127, -128, 126, 127], 8).tolist() == \
        [True, True, False, False]
    assert saturated_flags([[0]], [[-(2**31)]], 32).tolist() == [[True]]
