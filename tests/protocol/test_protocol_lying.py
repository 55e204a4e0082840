"""A device that lies: every lie is a one-line error naming the field, never a crash."""

from __future__ import annotations

import threading
from collections.abc import Callable, Iterator
from dataclasses import replace
from typing import Any

import numpy as np
import pytest
from protocol_fixtures import ScriptedPort, SteppedDevice, SyntheticApp, expected_column

from cdma_lidar.errors import DeviceError, LinkError
from cdma_lidar.protocol.columns import ColumnResult
from cdma_lidar.protocol.config_keys import encode_config
from cdma_lidar.protocol.framing import encode_frame
from cdma_lidar.protocol.link import HostLink
from cdma_lidar.protocol.messages import MESSAGES, MsgType, encode_payload
from cdma_lidar.protocol.trust import DeviceLied, escape

TIMEOUT = 0.2
NASTY = "\x1b]0;pwned\x07\x1b[2J\x1b[31mRED\u202e\r\n"


class LyingApp(SyntheticApp):
    """SyntheticApp whose INFO, CONFIG or columns can be edited by a test."""

    def __init__(self, **kw: Any) -> None:
        super().__init__(channels=4, columns=10)
        self.info_edit: dict[str, Any] = kw.pop("info", {})
        self.config_edit: Callable[[dict], dict] | None = kw.pop("config", None)
        self.column_edit: Callable[[np.ndarray], None] | None = kw.pop("column", None)
        self.column_header: dict[str, Any] = kw.pop("header", {})

    def info(self):  # type: ignore[override]
        return replace(super().info(), **self.info_edit)

    def get_config(self) -> dict[str, Any]:
        cfg = super().get_config()
        return self.config_edit(cfg) if self.config_edit else cfg

    def _columns(self, frame: int, first: int, count: int,
                 calibration: bool) -> Iterator[ColumnResult]:
        for col in super()._columns(frame, first, count, calibration):
            if col.column == first + 2:
                rec = col.records.copy()
                if self.column_edit:
                    self.column_edit(rec)
                col = replace(col, records=rec, **self.column_header)
            yield col


def _run(app: SyntheticApp, body: Callable[[HostLink], Any]) -> Any:
    port = SteppedDevice(app, heartbeat_s=0.05)
    with port:
        link = HostLink(port, timeout_s=TIMEOUT, retries=1, clock=port.clock)
        try:
            return body(link)
        finally:
            link.close()


def _scan(link: HostLink) -> list[ColumnResult]:
    link.hello()
    return list(link.scan(frame=1))


def _set(field: str, value: int, at: tuple = (0,)) -> Callable[[np.ndarray], None]:
    def edit(rec: np.ndarray) -> None:
        rec[field][at] = value
    return edit


@pytest.mark.parametrize(("edit", "field"), [
    (_set("peak_lag", 0xFFFFFFFE), "peak_lag[0]"),
    (_set("peak_lag", 2047 * 4), "peak_lag[0]"),  # N*S: one past the last lag
    (_set("noise_count", 0), "noise_count[0]"),
    (_set("noise_count", 65), "noise_count[0]"),  # above gate_len
    (_set("uid_neg", 2), "uid_neg[0]"),  # n = 1: only bit 0 exists
    (_set("uid_zero", 4), "uid_zero[0]"),
    (_set("uid_observed", 2), "uid_observed[0]"),
    (_set("uid_match", 2), "uid_match[0]"),
], ids=lambda v: v if isinstance(v, str) else "")
def test_a_lying_column_is_a_one_line_error_naming_the_field(edit, field) -> None:
    app = LyingApp(column=edit)
    if field.startswith("uid_zero"):
        app.column_edit = lambda rec: (rec.__setitem__("uid_neg", 0), _set("uid_zero", 4)(rec))
    with pytest.raises(DeviceLied) as exc:
        _run(app, _scan)
    msg = str(exc.value)
    assert field in msg and "column 2" in msg and "\n" not in msg


def test_overlapping_sign_masks_are_a_lie() -> None:
    def edit(rec: np.ndarray) -> None:
        rec["uid_neg"][0] = 1
        rec["uid_zero"][0] = 1
    with pytest.raises(DeviceLied, match="disjoint"):
        _run(LyingApp(column=edit), _scan)


def test_a_column_header_that_contradicts_the_session_is_a_lie() -> None:
    with pytest.raises(DeviceLied, match="uid_bits = 3"):
        _run(LyingApp(header={"uid_bits": 3}), _scan)


def test_a_column_with_other_channel_or_peak_counts_is_a_lie() -> None:
    class Wider(LyingApp):
        def _columns(self, frame, first, count, calibration):
            for c in range(first, first + count):
                yield expected_column(frame, c, 5 if c == first + 1 else 4, 1, 1)
    with pytest.raises(DeviceLied, match="channels = 5"):
        _run(Wider(), _scan)


@pytest.mark.parametrize(("edit", "field"), [
    (lambda c: {k: v for k, v in c.items() if k != "gate_len"}, "gate_len"),
    (lambda c: {**c, "uid": 5}, "uid"),  # uid_bits = 1
    (lambda c: {**c, "code_index": (1, 2)}, "code_index"),  # 4 channels
    (lambda c: {**c, "peaks": 8}, "peaks"),  # INFO: max_peaks 4
    (lambda c: {**c, "gate_start": 2047 * 4}, "gate_start"),
    (lambda c: {**c, "out_bits": 40}, "out_bits"),  # outside its wire range: the decoder's
])
def test_a_lying_config_is_a_one_line_error_naming_the_key(edit, field) -> None:
    with pytest.raises(DeviceLied) as exc:
        _run(LyingApp(config=edit, info={"max_peaks": 4}),
             lambda link: (link.hello(), link.get_config()))
    assert field in str(exc.value) and "\n" not in str(exc.value)


def test_info_with_more_channels_than_its_maximum_is_a_lie() -> None:
    with pytest.raises(DeviceLied, match="max_channels"):
        _run(LyingApp(info={"max_channels": 2}), lambda link: link.hello())


def test_strings_from_the_device_are_escaped() -> None:
    info = _run(LyingApp(info={"serial": NASTY, "firmware_version": NASTY}),
                lambda link: link.hello())
    for text in (info.serial, info.firmware_version):
        assert not any(ord(ch) < 0x20 or ch in "\x7f\u202e" for ch in text)
        assert "\\x1b]0;pwned" in text
    assert escape("plain text: µm, ±1") == "plain text: µm, ±1"


def _raw_device(answer: Callable[[Any], bytes]) -> tuple[HostLink, threading.Event]:
    """A device the test plays: ``answer(frame)`` gives the wire reply (b"": none);
    threadless, on the port's fake clock. The event is set when the test is done."""
    port = ScriptedPort(answer)
    return HostLink(port, timeout_s=TIMEOUT, retries=1, clock=port.clock), threading.Event()


def test_info_with_zero_channels_and_a_nak_with_escapes_are_one_line_errors() -> None:
    fields = SyntheticApp().info().to_fields()
    spec = MESSAGES[MsgType.INFO]
    fields["wavelengths_pm"] = []
    payload = spec.build(fields)  # what the encoder itself would refuse to send

    link, stop = _raw_device(lambda f: encode_frame(MsgType.INFO, payload, f.seq, 5))
    try:
        with pytest.raises(LinkError) as exc:
            link.hello()
        assert "wavelengths_pm" in str(exc.value) and "\n" not in str(exc.value)
    finally:
        stop.set()

    nak = encode_payload(MsgType.NAK, {"request_type": MsgType.HELLO, "code": 4,
                                       "field": NASTY[:20], "detail": NASTY})
    link, stop = _raw_device(lambda f: encode_frame(MsgType.NAK, nak, f.seq, 5))
    try:
        with pytest.raises(DeviceError) as exc2:
            link.hello()
        msg = str(exc2.value)
        assert "\x1b" not in msg and "\r" not in msg and "\n" not in msg and "\\x1b" in msg
    finally:
        stop.set()


@pytest.mark.parametrize(("field", "value"), [("max_degree", 40), ("max_frame", 100)])
def test_info_outside_a_wire_range_is_refused_where_it_is_decoded(field, value) -> None:
    """Fields whose wire range is their physical one: one check, by the decoder."""
    fields = replace(SyntheticApp().info(), session_id=5).to_fields()
    payload = MESSAGES[MsgType.INFO].build({**fields, field: value})
    link, _ = _raw_device(lambda f: encode_frame(MsgType.INFO, payload, f.seq, 5))
    with pytest.raises(LinkError) as exc:
        link.hello()
    assert field in str(exc.value) and "\n" not in str(exc.value)
    assert ("2..32" if field == "max_degree" else "256..65535") in str(exc.value)


def test_a_config_reply_with_garbage_values_is_a_one_line_error() -> None:
    good = SyntheticApp(4, 10)
    items = encode_config(good.get_config())
    items = [dict(i, value=b"\xff" * 7) if i["key"] == 16 else i for i in items]  # peaks
    cfg = encode_payload(MsgType.CONFIG, {"items": items})
    info = encode_payload(MsgType.INFO, replace(good.info(), session_id=5).to_fields())

    def answer(f):
        if f.msg_type == MsgType.HELLO:
            return encode_frame(MsgType.INFO, info, f.seq, 5)
        if f.msg_type == MsgType.CONFIG_GET:
            return encode_frame(MsgType.CONFIG, cfg, f.seq, 5)
        return encode_frame(MsgType.ACK, bytes([f.msg_type]), f.seq, 5)

    link, stop = _raw_device(answer)
    try:
        link.hello()
        with pytest.raises(LinkError) as exc:
            link.get_config()
        assert "CONFIG" in str(exc.value) and "\n" not in str(exc.value)
    finally:
        stop.set()


def test_a_peak_outside_the_signed_out_bits_range_is_a_lie() -> None:
    """out_bits = 16: the synthetic columns' 32-bit peaks cannot be true."""
    app = LyingApp(config=lambda cfg: {**cfg, "out_bits": 16})
    with pytest.raises(DeviceLied, match=r"peak\[0\] = .*-32768 to 32767") as exc:
        _run(app, _scan)
    assert "\n" not in str(exc.value)


def test_noise_sums_beyond_what_out_bits_outputs_can_add_up_to_are_a_lie() -> None:
    def edit(rec: np.ndarray) -> None:
        rec["noise_count"][1] = 1
        rec["noise_sumsq"][1] = 2**62 + 1  # one output of at most 2^31 in magnitude
    with pytest.raises(DeviceLied, match=r"noise_sumsq\[1\]"):
        _run(LyingApp(column=edit), _scan)


@pytest.mark.parametrize(("field", "value"), [
    ("chip_rate_hz", 1), ("chip_rate_hz", 999), ("wavelengths_pm", (5, 6, 7, 8)),
    ("incidence_udeg", 95_000_000), ("grooves_per_mm_milli", 999),
    ("column_step_udeg", 2**31 - 1)])
def test_info_outside_its_physical_range_is_a_lie(field: str, value: Any) -> None:
    app = LyingApp(info={field: value})
    with pytest.raises(DeviceLied, match=f"{field} = .*physical range") as exc:
        _run(app, lambda link: link.hello())
    assert exc.value.field == field
