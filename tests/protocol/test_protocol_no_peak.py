"""A receiver result with missing peaks (lag -1) crosses the wire and comes back as -1."""

from __future__ import annotations

import numpy as np

from cdma_lidar.firmware_model.receiver import ReceiverConfig, fast
from cdma_lidar.protocol.columns import NO_PEAK, ColumnResult, decode_column, encode_column


def test_missing_extra_peaks_round_trip_as_minus_one():
    rng = np.random.default_rng(7)
    codes = rng.integers(0, 2, size=(3, 31), dtype=np.uint8)
    # a 4-lag gate with W = 8 leaves room for one peak only: peaks 2 and 3 are missing
    cfg = ReceiverConfig(adc_bits=8, samples_per_chip=1, averages=1, gate_start=5, gate_len=4,
                         peak_exclude=8, peaks=3, out_bits=24)
    samples = rng.integers(-100, 100, size=31, dtype=np.int64)
    out = fast(cfg, codes, samples)
    assert np.all(out.extra_lag == -1)

    col = ColumnResult.from_receiver(4, 17, 1.25, out)
    assert np.all(col.records["extra_lag"] == NO_PEAK)
    back = decode_column(encode_column(col))
    np.testing.assert_array_equal(back.extra_lag, out.extra_lag)
    np.testing.assert_array_equal(back.peak_lag, out.peak_lag)
    assert back.peak_lag.dtype == np.int64


def test_all_lags_ghosted_gives_no_primary_peak_on_the_wire():
    rng = np.random.default_rng(8)
    codes = rng.integers(0, 2, size=(2, 15), dtype=np.uint8)
    cfg = ReceiverConfig(adc_bits=8, samples_per_chip=2, averages=1, gate_start=0, gate_len=6,
                         ghost_windows=((0, 6),), out_bits=24)
    out = fast(cfg, codes, rng.integers(-50, 50, size=30, dtype=np.int64))
    assert np.all(out.peak_lag == -1)
    back = decode_column(encode_column(ColumnResult.from_receiver(0, 0, 0.0, out)))
    np.testing.assert_array_equal(back.peak_lag, [-1, -1])
