"""FrameData: column results in, (K, C) arrays out, and back through NPZ."""

from __future__ import annotations

import io

import numpy as np
import pytest

from cdma_lidar.column_record import RECORD
from cdma_lidar.errors import ConfigError
from cdma_lidar.firmware_model.gold import gold_family
from cdma_lidar.firmware_model.receiver import FastReceiver, ReceiverConfig
from cdma_lidar.host.frame import FrameData
from cdma_lidar.protocol.columns import ColumnResult, decode_column, encode_column


def _receiver_output(seed: int, peaks: int = 3, uid_bits: int = 2):
    codes = gold_family((5, 2), (5, 4, 3, 2))[:4]
    cfg = ReceiverConfig(samples_per_chip=2, averages=2, uid_bits=uid_bits, gate_len=32,
                         peaks=peaks, peak_exclude=2)
    rng = np.random.default_rng(seed)
    samples = rng.integers(-300, 300, cfg.column_samples(codes.shape[1]))
    return FastReceiver(cfg, codes).column(samples)


def test_columns_from_receiver_and_wire_land_in_place():
    f = FrameData.empty(4, 3, uid_bits=2, peaks=3)
    outs = [_receiver_output(s) for s in range(3)]
    for col, out in enumerate(outs):
        wire = decode_column(encode_column(ColumnResult.from_receiver(0, col, 0.5 * col, out)))
        f.set_column(wire.column, wire)
    assert f.done.all() and f.angle_deg.tolist() == [0.0, 0.5, 1.0]
    for col, out in enumerate(outs):
        np.testing.assert_array_equal(f.peak_lag[:, col], out.peak_lag)
        np.testing.assert_array_equal(f.neighbours[:, col], out.neighbours)
        np.testing.assert_array_equal(f.extra_signs[:, col], out.extra_signs)
        np.testing.assert_array_equal(f.noise_sumsq[:, col], out.noise_sumsq)


def test_npz_round_trip():
    f = FrameData.empty(4, 2, uid_bits=2, peaks=3, frame=9)
    f.set_column(1, _receiver_output(5), angle_deg=-1.5)
    buf = io.BytesIO()
    np.savez(buf, **f.to_arrays())
    buf.seek(0)
    with np.load(buf) as z:
        g = FrameData.from_arrays(z)
    assert g.frame == 9 and g.done.tolist() == [False, True]
    for name, value in f.to_arrays().items():
        np.testing.assert_array_equal(getattr(g, name), value)


def test_shape_and_field_checks():
    f = FrameData.empty(4, 2, uid_bits=2, peaks=3)
    with pytest.raises(ConfigError, match="column"):
        f.set_column(2, _receiver_output(1))
    with pytest.raises(ConfigError, match="uid_signs shape"):
        f.set_column(0, _receiver_output(1, uid_bits=1))
    with pytest.raises(ConfigError, match="lacks"):
        f.set_column(0, {"peak_lag": np.zeros(4)})
    with pytest.raises(ConfigError, match="channels"):
        FrameData.empty(0, 2)
    with pytest.raises(ConfigError, match="lacks"):
        FrameData.from_arrays({"peak": np.zeros((1, 1))})


def test_column_timestamps_are_kept_and_old_partial_files_still_load():
    data = FrameData.empty(2, 3)
    data.set_column(1, {**{f.name: np.zeros((2, *f.shape(1, 1)), f.dtype) for f in RECORD},
                        "timestamp_us": 123456, "angle_deg": 0.5})
    assert data.timestamp_us.tolist() == [0, 123456, 0]
    arrays = data.to_arrays()
    back = FrameData.from_arrays(arrays)
    assert back.timestamp_us.tolist() == [0, 123456, 0]
    del arrays["timestamp_us"]                 # a partial scan saved before the field
    assert FrameData.from_arrays(arrays).timestamp_us.tolist() == [0, 0, 0]


def test_noise_sums_wider_than_the_wire_saturate_and_the_host_gives_them_no_snr():
    """The model carries noise_sumsq past 63 bits as exact ints (docs/firmware.md section 3):
    the wire's u64 carries it saturated, the host clamps to SUMSQ_UNKNOWN and such a pixel
    is rejected and flagged 16 instead of getting an SNR from a wrong floor."""
    import dataclasses

    from cdma_lidar.host.frame import SUMSQ_UNKNOWN
    from cdma_lidar.host.ranging import (
        FLAG_REJECTED,
        FLAG_SATURATED,
        RangingConfig,
        estimate_ranges,
    )

    out = _receiver_output(0, peaks=1, uid_bits=1)
    wide = np.array([2**70, 2**64 - 1, 2**63, int(out.noise_sumsq[3])], dtype=object)
    out = dataclasses.replace(out, noise_sumsq=wide)
    wire = decode_column(encode_column(ColumnResult.from_receiver(0, 0, 0.0, out)))
    assert wire.noise_sumsq.tolist()[:3] == [2**64 - 1, 2**64 - 1, 2**63]
    f = FrameData.empty(4, 1, uid_bits=1, peaks=1)
    f.set_column(0, wire)
    assert f.noise_sumsq[:, 0].tolist() == [SUMSQ_UNKNOWN] * 3 + [int(wide[3])]
    img = estimate_ranges(f, RangingConfig(samples_per_chip=2, chip_rate_hz=62.5e6,
                                           snr_threshold_db=-100.0, min_support=0))
    unknown = img.flags[:3, 0]
    assert np.all(unknown & FLAG_REJECTED) and np.all(unknown & FLAG_SATURATED)
    assert np.all(np.isnan(img.range_m[:3, 0]))
