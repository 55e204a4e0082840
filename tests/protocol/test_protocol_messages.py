"""Every message round-trips; encoders name bad fields; decoders raise only FrameError."""

from __future__ import annotations

import dataclasses

import construct as cs
import numpy as np
import pytest
import wire_oracle
from hypothesis import given
from hypothesis import strategies as st
from protocol_fixtures import expected_column, hello_fields

from cdma_lidar.errors import FieldError, FrameError
from cdma_lidar.protocol.columns import (
    ColumnResult,
    column_payload_size,
    decode_column,
    encode_column,
)
from cdma_lidar.protocol.config_keys import (
    CONFIG_KEYS,
    CONFIG_OPTIONAL,
    config_key,
    decode_config,
    encode_config,
)
from cdma_lidar.protocol.messages import (
    MESSAGES,
    REPLY_TO,
    Info,
    MsgKind,
    MsgType,
    Status,
    decode_payload,
    encode_payload,
)
from cdma_lidar.protocol.schema import INTS, Field, Layout

_LIMITS = {fmt: (lo, hi) for fmt, lo, hi in INTS.values()}


# ---- strategies derived from the declarations ------------------------------------------------
def _field_strategy(f: Field) -> st.SearchStrategy:
    if f.kind == "int":
        return st.integers(f.lo, f.hi)
    if f.kind == "text":
        return st.text(max_size=40).filter(lambda s: len(s.encode()) <= 255)
    if f.kind == "bytes":
        return st.binary(min_size=f.max_items or 1, max_size=f.max_items or 300)
    if f.kind == "klv":
        return st.lists(st.fixed_dictionaries({"key": st.integers(0, 255),
                                                "value": st.binary(max_size=40)}), max_size=6)
    if f.names:
        elem = st.fixed_dictionaries({n: st.integers(*_LIMITS[c])
                                      for n, c in zip(f.names, f.fmt, strict=True)})
    else:
        elem = st.integers(*((f.lo, f.hi) if f.lo is not None else _LIMITS[f.fmt]))
    return st.lists(elem, min_size=f.min_items, max_size=min(f.max_items or 30, 30))


@st.composite
def message_fields(draw, msg: MsgType) -> dict:
    spec = MESSAGES[msg]
    fields = {f.name: draw(_field_strategy(f)) for f in spec.fields if "*" not in f.count}
    for f in spec.fields:
        if "*" in f.count:  # as many as the product of earlier fields (POWER_SET.power)
            a, b = f.count.split("*")
            fields[a], fields[b] = draw(st.integers(1, 6)), draw(st.integers(1, 6))
            fields[f.name] = draw(st.lists(st.integers(*_LIMITS[f.fmt]),
                                           min_size=fields[a] * fields[b],
                                           max_size=fields[a] * fields[b]))
    if msg == MsgType.FRAGMENT:  # a piece of the message: index below count
        fields["index"] = draw(st.integers(0, fields["count"] - 1))
    return fields


CONTROL = [t for t in MESSAGES if t != MsgType.COLUMN_RESULT]


@pytest.mark.parametrize("msg", CONTROL, ids=lambda t: t.name)
@given(data=st.data())
def test_codec_and_construct_oracle_agree_byte_for_byte(msg: MsgType, data) -> None:
    """The run-time codec (struct) and the oracle (construct) build the same bytes from
    random valid fields and read them back alike."""
    fields = data.draw(message_fields(msg))
    payload = encode_payload(msg, fields)
    assert payload == wire_oracle.build(msg, fields)
    assert decode_payload(msg, payload) == wire_oracle.parse(msg, payload)


@pytest.mark.parametrize("msg", CONTROL, ids=lambda t: t.name)
@given(payload=st.binary(max_size=120))
def test_codec_and_oracle_agree_on_random_payloads(msg: MsgType, payload: bytes) -> None:
    """What the oracle cannot parse, the decoder refuses; what the decoder accepts, the
    oracle reads the same."""
    try:
        got = decode_payload(msg, payload)
    except FrameError:
        got = None
    try:
        want = wire_oracle.parse(msg, payload)
    except (cs.ConstructError, UnicodeDecodeError):
        assert got is None
        return
    if got is not None:
        assert got == want


@pytest.mark.parametrize("key", CONFIG_KEYS, ids=lambda k: k.name)
@given(data=st.binary(max_size=24))
def test_config_values_agree_with_the_oracle(key, data: bytes) -> None:
    value = wire_oracle.field_construct(key)  # a ConfigKey is the field of its value
    oracle = cs.FocusedSeq("v", "v" / value, cs.Terminated)
    try:
        want = wire_oracle.plain(oracle.parse(data))
    except cs.ConstructError:
        with pytest.raises(FrameError):
            Layout(key).parse(data)
        return
    got = Layout(key).parse(data)[key.name]
    assert got == want and Layout(key).build({key.name: got}) == oracle.build(want)


@pytest.mark.parametrize("msg", CONTROL, ids=lambda t: t.name)
@given(data=st.data())
def test_every_message_round_trips(msg: MsgType, data) -> None:
    fields = data.draw(message_fields(msg))
    payload = encode_payload(msg, fields)
    assert decode_payload(msg, payload) == fields
    assert encode_payload(msg, decode_payload(msg, payload)) == payload


@pytest.mark.parametrize("msg", list(MESSAGES), ids=lambda t: t.name)
@given(payload=st.binary(max_size=400))
def test_decoder_raises_only_frame_error(msg: MsgType, payload: bytes) -> None:
    try:
        decode_payload(msg, payload)
    except FrameError:
        pass


@pytest.mark.parametrize("msg", CONTROL, ids=lambda t: t.name)
def test_decoder_rejects_trailing_and_missing_bytes(msg: MsgType) -> None:
    fields = _minimal(msg)
    payload = encode_payload(msg, fields)
    last = MESSAGES[msg].fields[-1] if MESSAGES[msg].fields else None
    open_ended = last is not None and (last.kind == "klv" or (last.kind == "bytes" and not
                                       last.max_items) or (last.kind == "array" and not last.count))
    if not open_ended:
        with pytest.raises(FrameError):
            decode_payload(msg, payload + b"\x01")
    if payload and not open_ended:
        with pytest.raises(FrameError):
            decode_payload(msg, payload[:-1])


def _minimal(msg: MsgType) -> dict:
    out = {}
    for f in MESSAGES[msg].fields:
        out[f.name] = {"int": f.lo, "text": "x", "array": [f.lo or 0],
                       "bytes": bytes(f.max_items or 0)}.get(f.kind, None)
    if msg in (MsgType.POWER_SET, MsgType.POWER):
        out.update(channels=1, columns=1, power=[7])
    for name in ("keys", "items", "fragments"):
        if name in out:
            out[name] = []
    if "data" in out:
        out["data"] = b"\x01\x02"
    return out


def test_kinds_and_replies() -> None:
    for t, spec in MESSAGES.items():
        expected = (MsgKind.REQUEST if t < 0x80 else MsgKind.REPLY if t < 0xC0
                    else MsgKind.STREAM)
        assert spec.kind is expected
        assert (t in REPLY_TO) == (expected is MsgKind.REQUEST)
        if spec.kind is MsgKind.REQUEST:
            assert REPLY_TO[t] in (MsgType.ACK, MsgType.INFO, MsgType.CONFIG, MsgType.STATUS,
                                   MsgType.CAPTURE_DATA, MsgType.POWER)


@pytest.mark.parametrize(("msg", "fields", "name"), [
    (MsgType.SCAN_START, {"frame": -1, "first_column": 0, "columns": 1}, "SCAN_START.frame"),
    (MsgType.SCAN_START, {"frame": 1, "first_column": 0, "columns": 0}, "SCAN_START.columns"),
    (MsgType.SCAN_START, {"frame": 1, "first_column": 0}, "SCAN_START.columns"),
    (MsgType.SCAN_START, {"frame": 1, "first_column": 0, "columns": 1, "x": 2}, "SCAN_START.x"),
    (MsgType.HELLO, hello_fields(1, 63), "HELLO.host_max_frame"),
    (MsgType.RESEND, {"frame": 1, "columns": list(range(256))}, "RESEND.columns"),
    (MsgType.RESEND, {"frame": 1, "columns": [1, 70000]}, "RESEND.columns[1]"),
    (MsgType.NAK, {"request_type": 1, "code": 4, "field": "é" * 200, "detail": ""},
     "NAK.field"),
    (MsgType.CAPTURE, {"kind": 2, "column": 0, "channel": 0, "offset": 0, "max_count": 1},
     "CAPTURE.kind"),
    (MsgType.POWER_SET, {"channel_start": 0, "column_start": 0, "channels": 2, "columns": 2,
                         "power": [1, 2, 3]}, "POWER_SET.power"),
    (MsgType.POWER_SET, {"channel_start": 0, "column_start": 0, "channels": 1, "columns": 1,
                         "power": [70000]}, "POWER_SET.power"),
])
def test_encoder_names_the_bad_field(msg: MsgType, fields: dict, name: str) -> None:
    with pytest.raises(FieldError) as exc:
        encode_payload(msg, fields)
    assert name in str(exc.value)


# ---- INFO / STATUS views ------------------------------------------------------------------------
def test_info_and_status_mirror_their_declarations() -> None:
    info_fields = {f.name for f in dataclasses.fields(Info)}
    assert info_fields == {f.name for f in MESSAGES[MsgType.INFO].fields}
    status_fields = {f.name for f in dataclasses.fields(Status)}
    assert status_fields == {f.name for f in MESSAGES[MsgType.STATUS].fields}
    assert status_fields == {f.name for f in MESSAGES[MsgType.HEARTBEAT].fields}


def test_info_nominal_units() -> None:
    info = Info.nominal(serial="S", firmware_version="F", wavelengths_m=[1570e-9, 1570.875e-9],
                        grooves_per_mm=600.0, incidence_deg=60.0, tilt_deg=-1.25,
                        reference_wavelength_m=1587e-9, chip_rate_hz=2.5e8,
                        column_start_deg=-20.0, column_step_deg=0.05, column_count=5)
    back = Info.from_fields(decode_payload(MsgType.INFO, encode_payload(MsgType.INFO,
                                                                       info.to_fields())))
    assert back == info
    assert back.wavelengths_pm == (1_570_000, 1_570_875)
    np.testing.assert_allclose(back.wavelengths_m, [1570e-9, 1570.875e-9])
    np.testing.assert_allclose(back.column_angles_deg, [-20, -19.95, -19.9, -19.85, -19.8])
    assert back.tilt_deg == pytest.approx(-1.25)
    assert back.grooves_per_mm == 600.0 and back.incidence_deg == 60.0
    assert dataclasses.replace(back, tilt_udeg=-(2**31)).tilt_deg is None


# ---- CONFIG key-length-value -------------------------------------------------------------------
CONFIG_EXAMPLES = {
    "poly_u": (11, 2), "poly_v": (11, 8, 5, 2), "code_index": (0, 5, 2049, 7),
    "uid_bits": 3, "uid": 5, "samples_per_chip": 4, "averages": 100_000, "adc_bits": 12,
    "gate_start": 123, "gate_len": 4000, "peak_exclude": 8,
    "ghost_windows": ((10, 3), (4000, 20)), "out_shift": 7, "rounding": "convergent",
    "out_bits": 24, "peaks": 8, "columns_per_frame": 500, "mode": "calibration",
    "cancel_rounds": 4, "cancel_snr_q8": 5731,
}


def test_config_examples_cover_every_key() -> None:
    assert set(CONFIG_EXAMPLES) == {k.name for k in CONFIG_KEYS}
    assert len({k.id for k in CONFIG_KEYS}) == len(CONFIG_KEYS)
    assert all(0 < k.id < CONFIG_OPTIONAL for k in CONFIG_KEYS)


def test_config_round_trip_through_config_set() -> None:
    items = encode_config(CONFIG_EXAMPLES)
    payload = encode_payload(MsgType.CONFIG_SET, {"items": items})
    got = decode_config(decode_payload(MsgType.CONFIG_SET, payload)["items"])
    assert got.values == CONFIG_EXAMPLES and got.unknown == [] and got.ignored == []


@pytest.mark.parametrize(("name", "value"), [
    ("uid_bits", 0), ("uid_bits", 9), ("peaks", 9), ("out_bits", 7), ("out_bits", 33),
    ("rounding", "nearest"), ("mode", "sleep"), ("poly_u", (40, 2)), ("poly_u", (3, 3)),
    ("code_index", [1, -1]), ("ghost_windows", [(1, 2, 3)]), ("out_shift", 64),
    ("averages", 0), ("samples_per_chip", 70000), ("bogus_key", 1), ("cancel_rounds", 5),
    ("cancel_rounds", -1), ("cancel_snr_q8", 2**32), ("cancel_snr_q8", -1),
])
def test_config_encoder_names_the_key(name: str, value: object) -> None:
    with pytest.raises(FieldError, match=name.split("_key")[0]):
        encode_config({name: value})


def test_config_read_only_refused_when_asked() -> None:
    with pytest.raises(FieldError, match="adc_bits"):
        encode_config({"adc_bits": 12}, allow_read_only=False)


def test_config_unknown_and_optional_keys() -> None:
    items = [{"key": 99, "value": b"\x01"}, {"key": 99 | CONFIG_OPTIONAL, "value": b""},
             {"key": 16, "value": b"\x02"}]
    got = decode_config(items)
    assert got.values == {"peaks": 2}
    assert got.unknown == [99] and got.ignored == [99 | CONFIG_OPTIONAL]


@pytest.mark.parametrize(("key", "value"), [(16, b""), (16, b"\x01\x02"), (16, b"\x09"),
                                            (3, b"\x01"), (14, b"\x03"), (19, b"\x05"),
                                            (20, b"\x01\x02")])
def test_config_decoder_names_key_of_bad_value(key: int, value: bytes) -> None:
    with pytest.raises(FrameError) as exc:
        decode_config([{"key": key, "value": value}])
    assert exc.value.field == {16: "peaks", 3: "code_index", 14: "rounding", 19: "cancel_rounds",
                               20: "cancel_snr_q8"}[key]


@given(st.sets(st.integers(1, 32), min_size=1, max_size=8))
def test_poly_mask_round_trip_up_to_degree_32(exps: set[int]) -> None:
    key = config_key("poly_u")
    poly = tuple(sorted(exps, reverse=True))
    assert key.decode(key.encode(poly)) == poly
    assert key.encode((11, 2)) == (0x402).to_bytes(4, "little")
    assert key.encode((32, 22, 2, 1)) == (0x80200003).to_bytes(4, "little")


# ---- COLUMN_RESULT: numpy codec == construct oracle ------------------------------------------
@given(st.integers(0, 2**32 - 1), st.integers(0, 65535), st.integers(1, 40),
       st.integers(1, 8), st.integers(1, 8), st.booleans())
def test_column_fast_and_construct_paths_agree(frame: int, column: int, k: int, p: int, n: int,
                                               cal: bool) -> None:
    col = expected_column(frame, column, k, p, n, cal)
    fast = encode_column(col)
    assert fast == wire_oracle.encode_column_construct(col)
    assert len(fast) == column_payload_size(k, p)
    assert decode_column(fast) == col == wire_oracle.decode_column_construct(fast)
    back = decode_column(fast)
    assert back.uid_signs.shape == (k, n) and back.extra_signs.shape == (k, p - 1, n)
    np.testing.assert_array_equal(back.uid_signs, col.uid_signs)
    assert back.calibration == cal and back.peaks == p and back.channels == k


def test_column_from_arrays_keeps_every_receiver_field() -> None:
    rng = np.random.default_rng(3)
    k, n, p = 5, 3, 3
    arrays = dict(
        peak_lag=rng.integers(0, 100, k), peak=rng.integers(-9, 9, k),
        neighbours=rng.integers(-9, 9, (k, 2)), noise_count=rng.integers(0, 9, k),
        noise_sum=rng.integers(-9, 9, k), noise_sumsq=rng.integers(0, 99, k),
        uid_signs=rng.integers(-1, 2, (k, n)), uid_observed=rng.integers(0, 8, k),
        uid_match=rng.integers(0, 2, k).astype(bool), saturated=rng.integers(0, 2, k).astype(bool),
        extra_lag=rng.integers(0, 100, (k, 2)),
        extra_peak=rng.integers(-9, 9, (k, 2)), extra_signs=rng.integers(-1, 2, (k, 2, n)))
    col = decode_column(encode_column(ColumnResult.from_arrays(1, 2, 12.345678, **arrays)))
    for name, value in arrays.items():
        np.testing.assert_array_equal(getattr(col, name), value, err_msg=name)
    assert col.angle_udeg == 12_345_678 and col.peaks == p and col.uid_bits == n


@pytest.mark.parametrize(("name", "bad"), [
    ("peak_lag", -2), ("peak", 2**31), ("neighbours", -(2**31) - 1), ("noise_count", 2**32),
    ("uid_observed", 8), ("uid_signs", 2), ("uid_match", 3), ("noise_sumsq", -1),
])
def test_column_from_arrays_names_bad_field(name: str, bad: int) -> None:
    k, n = 3, 3
    arrays = dict(peak_lag=np.zeros(k, int), peak=np.zeros(k, int),
                  neighbours=np.zeros((k, 2), int), noise_count=np.zeros(k, int),
                  noise_sum=np.zeros(k, int), noise_sumsq=np.zeros(k, int),
                  uid_signs=np.ones((k, n), int), uid_observed=np.zeros(k, int),
                  uid_match=np.zeros(k, int), saturated=np.zeros(k, int))
    arr = np.array(arrays[name], dtype=object)
    arr.flat[0] = bad
    arrays[name] = arr.astype(np.int64) if abs(bad) < 2**63 else arr
    with pytest.raises(FieldError, match=name):
        ColumnResult.from_arrays(0, 0, 0.0, **arrays)


@pytest.mark.parametrize("cut", [0, 5, 18, 19, 20, -1])
def test_column_decoder_rejects_wrong_lengths(cut: int) -> None:
    payload = encode_column(expected_column(1, 1, 4, 2, 2))
    with pytest.raises(FrameError):
        decode_column(payload[:cut] if cut >= 0 else payload + b"\x00")


@given(st.lists(st.fixed_dictionaries({"key": st.integers(0, 255),
                                       "value": st.binary(max_size=24)}), max_size=8))
def test_config_decoder_raises_only_frame_error_naming_the_key(items: list[dict]) -> None:
    try:
        got = decode_config(items)
    except FrameError as exc:
        assert exc.field in {k.name for k in CONFIG_KEYS}
    else:
        known = {k.id for k in CONFIG_KEYS}
        assert set(got.unknown) | set(got.ignored) == \
            {it["key"] for it in items if it["key"] & 0x7F not in known}


@pytest.mark.parametrize(("values", "text"), [
    ({"peaks": 9}, "peaks must be 1..max_peaks (1..8 on the wire), not 9"),
    ({"code_index": [1, 70000]}, "(each 0..65535 on the wire)"),
    ({"rounding": "nearest"}, "rounding must be one of truncate, half_up, convergent"),
    ({"code_index": 5}, "code_index must be 0..2^m (N+1), K items, not 5"),  # not a list
])
def test_config_encoder_message_says_the_wire_range(values: dict, text: str) -> None:
    with pytest.raises(FieldError) as exc:
        encode_config(values)
    assert text in str(exc.value) and exc.value.field == next(iter(values))


@pytest.mark.parametrize(("index", "data"), [(2, b"x"), (3, b"x"), (0, b"")])
def test_a_fragment_outside_its_count_or_empty_does_not_decode(index: int, data: bytes) -> None:
    payload = encode_payload(MsgType.FRAGMENT, {"msg_type": 0x82, "seq": 1, "frame": 0,
                                                "column": 0, "index": index, "count": 2,
                                                "data": data})
    with pytest.raises(FrameError, match="FRAGMENT"):
        decode_payload(MsgType.FRAGMENT, payload)


def test_column_result_declares_one_view_per_record_field() -> None:
    """The views are written out in the class (no setattr at import): the same list as
    the record's fields, in order."""
    from cdma_lidar.column_record import RECORD
    from cdma_lidar.protocol.columns import ColumnResult

    views = [n for n, v in vars(ColumnResult).items()
             if isinstance(v, property) and n not in ("channels", "peaks")]
    assert views[:len(RECORD)] == [f.name for f in RECORD]


@given(st.sampled_from(["int8", "uint8", "int16", "uint16", "int32", "uint32", "int64",
                        "uint64"]), st.data())
def test_a_numpy_array_of_integers_is_checked_as_its_list_is(dtype, data) -> None:
    """Field.check takes a numpy integer array in one range check: the same values, and
    the same error naming the first element outside the range, as item by item."""
    from hypothesis.extra.numpy import arrays

    info = np.iinfo(dtype)
    edges = [v for v in (-4, -3, 0, 300, 301, 65535, 65536) if info.min <= v <= info.max]
    edge = data.draw(st.lists(st.sampled_from(edges), max_size=4))
    drawn = data.draw(arrays(np.dtype(dtype), st.integers(0, 12)))
    arr = np.concatenate([drawn, np.array(edge, dtype=dtype)])
    for f in (MESSAGES[MsgType.POWER_SET].field("power"),  # u16 items, no declared range
              Field("v", "u16 x n", "", lo=-3, hi=300, kind="array", fmt="h")):
        try:
            want: object = f.check("v", arr.tolist())
        except FieldError as exc:
            want = str(exc)
        try:
            got: object = f.check("v", arr)
        except FieldError as exc:
            got = str(exc)
        assert got == want
