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
