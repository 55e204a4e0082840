"""The column record is declared once (cdma_lidar.column_record); every view is derived from it.

Receiver output, wire dtype, construct record, spec table, host frame arrays,
ColumnResult properties and the co-simulation decode all list the record's
fields in the record's order, and the wire layout still is the documented one.
"""

from __future__ import annotations

import ast
import dataclasses
from pathlib import Path

import numpy as np
import pytest
from wire_oracle import RECORD_STRUCT, decode_column_construct, encode_column_construct

from cdma_lidar import column_record
from cdma_lidar.column_record import (
    FIELD_NAMES,
    NO_PEAK,
    RECORD,
    RECORD_EXTRA_SIZE,
    RECORD_FIXED_SIZE,
    WIRE_FIELDS,
    record_size,
    wire_layout,
)
from cdma_lidar.firmware_model.gold import gold_family
from cdma_lidar.firmware_model.output import ReceiverOutput
from cdma_lidar.firmware_model.receiver import FastReceiver, ReceiverConfig
from cdma_lidar.hdl_ref import cosim
from cdma_lidar.host.frame import FrameData
from cdma_lidar.protocol.columns import (
    _HEAD,
    _LIMITS,
    COLUMN_HEADER,
    RECORD_FIELDS,
    ColumnResult,
    column_payload_size,
    decode_column,
    encode_column,
    record_dtype,
)

WIRE_NAMES = [w.name for w in WIRE_FIELDS]
PEAKS = range(1, 9)


def _model_output(peaks: int = 3, uid_bits: int = 2, seed: int = 0) -> ReceiverOutput:
    codes = gold_family((5, 2), (5, 4, 3, 2))[:4]
    cfg = ReceiverConfig(samples_per_chip=2, averages=2, uid_bits=uid_bits, gate_len=32,
                         peaks=peaks, peak_exclude=2)
    samples = np.random.default_rng(seed).integers(-300, 300,
                                                   cfg.column_samples(codes.shape[1]))
    return FastReceiver(cfg, codes).column(samples)


def _random_output(rng: np.random.Generator, k: int, n: int, peaks: int) -> dict[str, np.ndarray]:
    """Receiver-form arrays of every record field, with missing peaks and zero signs."""
    e = peaks - 1
    lags = rng.integers(-1, 8188, (k, peaks))
    return {
        "peak_lag": lags[:, 0], "peak": rng.integers(-(2**31), 2**31, k),
        "neighbours": rng.integers(-(2**31), 2**31, (k, 2)),
        "noise_count": rng.integers(0, 2**32, k),
        "noise_sum": rng.integers(-(2**63), 2**63 - 1, k, dtype=np.int64),
        "noise_sumsq": rng.integers(0, 2**63 - 1, k, dtype=np.int64),
        "uid_signs": rng.integers(-1, 2, (k, n)).astype(np.int8),
        "uid_observed": rng.integers(0, 1 << n, k),
        "uid_match": rng.integers(0, 2, k).astype(bool),
        "saturated": rng.integers(0, 2, k).astype(bool),
        "extra_lag": lags[:, 1:], "extra_peak": rng.integers(-(2**31), 2**31, (k, e)),
        "extra_signs": rng.integers(-1, 2, (k, e, n)).astype(np.int8),
    }


# ---- every view lists the record's fields in the record's order ------------------------------
def test_receiver_output_is_corr_then_the_record() -> None:
    assert [f.name for f in dataclasses.fields(ReceiverOutput)] == ["corr", *FIELD_NAMES]


def test_receiver_output_dtypes_and_shapes_are_the_records() -> None:
    for peaks, n in ((1, 1), (3, 2), (2, 4)):
        out = _model_output(peaks, n)
        k = out.corr.shape[0]
        for f in RECORD:
            value = getattr(out, f.name)
            assert value.dtype == f.dtype, f.name
            assert value.shape == (k, *f.shape(n, peaks)), f.name


@pytest.mark.parametrize("peaks", PEAKS)
def test_wire_dtype_and_construct_record_list_the_wire_fields(peaks: int) -> None:
    assert list(record_dtype(peaks).names) == WIRE_NAMES
    assert [f.name for f in RECORD_FIELDS] == WIRE_NAMES
    assert [sc.name for sc in RECORD_STRUCT.subcons] == WIRE_NAMES


def test_wire_fields_follow_the_record_order() -> None:
    """Each logical field becomes its wire field(s) in place: signs become two masks."""
    assert WIRE_NAMES == [
        "peak_lag", "peak", "neighbours", "noise_count", "noise_sum", "noise_sumsq",
        "uid_neg", "uid_zero", "uid_observed", "uid_match", "saturated", "extra_lag",
        "extra_peak", "extra_neg", "extra_zero"]
    assert [w.name for f in RECORD for w in f.wire] == WIRE_NAMES


def test_frame_arrays_are_the_record_then_angle_done_frame() -> None:
    names = [f.name for f in dataclasses.fields(FrameData)]
    assert names == [*FIELD_NAMES, "angle_deg", "done", "timestamp_us", "frame"]
    frame = FrameData.empty(3, 5, uid_bits=2, peaks=4)
    for f in RECORD:
        arr = getattr(frame, f.name)
        assert arr.dtype == f.dtype and arr.shape == (3, 5, *f.shape(2, 4)), f.name


def test_column_result_has_one_property_per_field_in_receiver_form() -> None:
    out = _model_output(3, 2)
    col = decode_column(encode_column(ColumnResult.from_receiver(1, 2, 0.5, out)))
    for f in RECORD:
        assert isinstance(getattr(ColumnResult, f.name), property), f.name
        np.testing.assert_array_equal(getattr(col, f.name), getattr(out, f.name), f.name)
        assert getattr(col, f.name).shape == getattr(out, f.name).shape, f.name


def test_cosim_decode_lists_the_record_and_builds_the_model_output() -> None:
    params = cosim.RxParams()
    ow, lw, uw = params.out_w, params.lag_w, params.max_uid
    n, peaks, gate = 3, 3, 4
    ports = {"cfg_uid_bits": n, "cfg_peaks": peaks, "cfg_gate_len": gate}
    res = {  # peak 0 at lag 17 (value -5), peak 1 at lag 40 (value 9), peak 2 missing
        "res_found": 0b011, "res_lag": 17 | 40 << lw, "res_peak": ((1 << ow) - 5) | 9 << ow,
        "res_neg": 0b010 | 0b001 << uw, "res_nz": 0b111 | 0b101 << uw,
        "res_nb_lo": (1 << ow) - 2, "res_nb_hi": 3, "res_noise_count": 2,
        "res_noise_sum": (1 << (ow + params.g_w)) - 7, "res_noise_sumsq": 29,
        "res_uid_observed": 0b010, "res_uid_match": 1, "res_saturated": 0,
    }
    raw = {"corr": [[j, j] for j in range(gate)], "res": res}
    decoded = cosim.decode_rx_result(raw, ports, params)
    assert list(decoded) == ["corr", *FIELD_NAMES]
    out = cosim.to_receiver_output(decoded)
    assert isinstance(out, ReceiverOutput)
    for f in RECORD:
        value = getattr(out, f.name)
        assert value.dtype == f.dtype and value.shape == (1, *f.shape(n, peaks)), f.name
    assert out.peak_lag.tolist() == [17] and out.peak.tolist() == [-5]
    assert out.uid_signs.tolist() == [[1, -1, 1]]
    assert out.extra_lag.tolist() == [[40, -1]] and out.extra_peak.tolist() == [[9, 0]]
    assert out.extra_signs[0, 0].tolist() == [-1, 0, 1]
    assert out.neighbours.tolist() == [[-2, 3]] and out.noise_sum.tolist() == [-7]
    assert out.uid_match.tolist() == [True] and out.saturated.tolist() == [False]


def test_spec_table_lists_the_wire_fields_with_their_offsets() -> None:
    from cdma_lidar.protocol.spec import column_table

    text = column_table().split("Channel record")[1]
    rows = [line.split(" | ") for line in text.splitlines() if line.startswith("| ")][2:]
    assert [r[1].strip("`") for r in rows] == WIRE_NAMES
    for p in PEAKS:  # "40 + 4(P-1)" evaluated at P gives the dtype's offset
        dt = record_dtype(p)
        for r in rows:
            base, _, per = r[0].lstrip("| ").partition(" + ")
            offset = int(base) + (int(per.removesuffix("(P-1)")) * (p - 1) if per else 0)
            assert offset == dt.fields[r[1].strip("`")][1], (p, r)
    assert f"`{RECORD_FIXED_SIZE} + {RECORD_EXTRA_SIZE} (P-1)` bytes" in column_table()


# ---- wire layout --------------------------------------------------------------------------
@pytest.mark.parametrize("peaks", PEAKS)
def test_payload_size_formula_matches_the_dtype(peaks: int) -> None:
    dt = record_dtype(peaks)
    assert record_size(peaks) == dt.itemsize == 41 + 10 * (peaks - 1)
    for k in (1, 7, 40):
        assert column_payload_size(k, peaks) == 19 + k * dt.itemsize
    for at in wire_layout():
        assert dt.fields[at.wire.name][1] == at.offset + at.offset_per_extra * (peaks - 1)
        assert dt[at.wire.name].itemsize == at.wire.item_size * int(
            np.prod(at.wire.shape(peaks)))


def test_header_struct_is_the_declared_header() -> None:
    assert COLUMN_HEADER.sizeof() == _HEAD.size == 19


def test_encoder_limits_are_the_wire_types() -> None:
    for f in RECORD:
        if f.encoding in ("int", "lag"):
            info = np.iinfo(np.dtype(f.wire[0].numpy_type))
            assert _LIMITS[f.name] == (int(info.min), int(info.max)), f.name
    assert NO_PEAK == np.iinfo(np.uint32).max


# ---- round trip -----------------------------------------------------------------------------
@pytest.mark.parametrize("peaks", PEAKS)
def test_record_round_trips_through_both_codecs(peaks: int) -> None:
    rng = np.random.default_rng(peaks)
    for n in (1, 3, 8):
        k = int(rng.integers(1, 9))
        arrays = _random_output(rng, k, n, peaks)
        col = ColumnResult.from_arrays(5, 6, -2.5, timestamp_us=9, **arrays)
        payload = encode_column(col)
        assert payload == encode_column_construct(col)
        for back in (decode_column(payload), decode_column_construct(payload)):
            assert back == col and back.peaks == peaks and back.uid_bits == n
            for f in RECORD:
                got = getattr(back, f.name)
                np.testing.assert_array_equal(got, arrays[f.name], err_msg=f.name)
                assert got.shape == (k, *f.shape(n, peaks)), f.name


def test_missing_lag_travels_as_no_peak() -> None:
    arrays = _random_output(np.random.default_rng(1), 2, 2, 2)
    arrays["peak_lag"] = np.array([-1, 5])
    col = ColumnResult.from_arrays(0, 0, 0.0, **arrays)
    assert col.records["peak_lag"].tolist() == [NO_PEAK, 5]
    assert col.peak_lag.tolist() == [-1, 5]


def test_from_arrays_wants_exactly_the_record_fields() -> None:
    arrays = _random_output(np.random.default_rng(2), 2, 2, 1)
    with pytest.raises(TypeError, match="corr"):
        ColumnResult.from_arrays(0, 0, 0.0, corr=np.zeros((2, 4)), **arrays)
    del arrays["noise_sum"]
    with pytest.raises(TypeError, match="noise_sum"):
        ColumnResult.from_arrays(0, 0, 0.0, **arrays)


# ---- the module stays a core leaf ----------------------------------------------------------
def test_column_record_imports_only_numpy_and_the_standard_library() -> None:
    tree = ast.parse(Path(column_record.__file__).read_text(encoding="utf-8"))
    imported = {alias.name.split(".")[0] for node in ast.walk(tree)
                if isinstance(node, ast.Import) for alias in node.names}
    imported |= {node.module.split(".")[0] for node in ast.walk(tree)
                 if isinstance(node, ast.ImportFrom) and node.module}
    assert imported <= {"__future__", "collections", "dataclasses", "inspect", "itertools",
                        "typing", "numpy"}


# ---- the classes that hold the record write its fields out ------------------------------
def test_frame_data_writes_out_the_record_fields_in_order_with_their_dtypes() -> None:
    """FrameData's fields are written out (no generated annotations): they must be the
    record's, in its order and with its dtypes, before the frame's own fields."""
    import dataclasses
    import typing

    from cdma_lidar.column_record import FIELD_NAMES
    from cdma_lidar.host.frame import FrameData

    names = [f.name for f in dataclasses.fields(FrameData)]
    assert tuple(names[:len(FIELD_NAMES)]) == FIELD_NAMES
    assert names[len(FIELD_NAMES):] == ["angle_deg", "done", "timestamp_us", "frame"]
    hints = typing.get_type_hints(FrameData)
    for f in RECORD:
        (dtype,) = typing.get_args(typing.get_args(hints[f.name])[1])
        assert np.dtype(dtype) == np.dtype(f.dtype), f.name
    empty = FrameData.empty(3, 2, uid_bits=2, peaks=3)
    for f in RECORD:
        assert getattr(empty, f.name).shape == (3, 2, *f.shape(2, 3)), f.name
