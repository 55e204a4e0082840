"""Rules of docs/protocol.md that no other test reached (a coverage run over the protocol,
host and virtual tests listed them): what the device refuses and how, what a host refuses
of a device that lies, and what each end survives. Each test fails when its rule goes."""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import replace
from typing import Any

import numpy as np
import pytest
from protocol_fixtures import (
    FakeClock,
    ScriptedPort,
    SteppedDevice,
    SyntheticApp,
    hello_fields,
    reply,
    scripted_link,
)

from cdma_lidar.errors import DeviceError, FieldError, LinkError
from cdma_lidar.protocol import auth
from cdma_lidar.protocol.columns import ColumnResult
from cdma_lidar.protocol.endpoint import DeviceApp, DeviceEndpoint
from cdma_lidar.protocol.framing import Frame, FrameDecoder, encode_frame
from cdma_lidar.protocol.link import HostLink, StreamEnded
from cdma_lidar.protocol.messages import (
    CaptureKind,
    ErrorCode,
    MsgType,
    ScanEndReason,
    decode_payload,
    encode_payload,
    split_message,
)
from cdma_lidar.protocol.trust import DeviceLied
from cdma_lidar.virtual.line import pipe_pair


def _device(app: SyntheticApp | None = None, **kw: Any) -> tuple[SteppedDevice, HostLink]:
    dev = SteppedDevice(app or SyntheticApp(channels=4, columns=10), **kw)
    link = HostLink(dev, timeout_s=0.2, retries=1, clock=dev.clock,
                    max_frame=kw.get("max_frame", 16384))
    link.hello()
    return dev, link


def _refused(link: HostLink, t: MsgType, fields: dict[str, Any]) -> DeviceError:
    with pytest.raises(DeviceError) as exc:
        link.request(t, fields)
    return exc.value


# ---- what the device refuses -------------------------------------------------------------
def test_resend_naming_nothing_is_malformed() -> None:
    dev, link = _device()
    with dev:
        exc = _refused(link, MsgType.RESEND, {"frame": 1, "columns": [], "fragments": []})
    assert (exc.code, exc.field) == (ErrorCode.MALFORMED, "columns")


def test_config_get_of_an_unknown_key_names_its_id() -> None:
    dev, link = _device()
    with dev:
        exc = _refused(link, MsgType.CONFIG_GET, {"keys": [16, 99]})
    assert (exc.code, exc.field) == (ErrorCode.UNKNOWN_KEY, "key 99")


def test_config_set_of_a_key_given_twice_is_malformed_and_changes_nothing() -> None:
    app = SyntheticApp(channels=4, columns=10)
    dev, link = _device(app)
    with dev:
        exc = _refused(link, MsgType.CONFIG_SET, {"items": [{"key": 16, "value": b"\x02"},
                                                            {"key": 16, "value": b"\x03"}]})
    assert (exc.code, exc.field) == (ErrorCode.MALFORMED, "peaks")
    assert app.set_config_calls == 0 and app.config["peaks"] == 1


def test_capture_reads_past_the_start_only_of_the_capture_it_holds() -> None:
    """Offset > 0 needs a capture of the same (kind, column, channel): NOT_AVAILABLE;
    beyond its end: OUT_OF_RANGE; its end itself: an empty chunk."""
    dev, link = _device()
    capture = {"kind": int(CaptureKind.RAW), "column": 1, "channel": 0, "max_count": 100}
    with dev:
        exc = _refused(link, MsgType.CAPTURE, {**capture, "offset": 5})
        assert (exc.code, exc.field) == (ErrorCode.NOT_AVAILABLE, "offset")
        total = link.request(MsgType.CAPTURE, {**capture, "offset": 0})["total"]
        assert link.request(MsgType.CAPTURE, {**capture, "offset": total})["data"] == b""
        exc = _refused(link, MsgType.CAPTURE, {**capture, "offset": total + 1})
        assert (exc.code, exc.field) == (ErrorCode.OUT_OF_RANGE, "offset")
        exc = _refused(link, MsgType.CAPTURE, {**capture, "column": 2, "offset": 5})
        assert exc.code == ErrorCode.NOT_AVAILABLE  # another column's capture is not held


def test_a_reply_longer_than_max_pieces_is_refused_too_large() -> None:
    """POWER_GET of 200 x 200 values (80 kB) at max frame 256: more than 254 FRAGMENTs."""
    dev, link = _device(SyntheticApp(channels=200, columns=200), max_frame=256)
    with dev:
        exc = _refused(link, MsgType.POWER_GET, {"channel_start": 0, "column_start": 0,
                                                 "channels": 200, "columns": 200})
        assert (exc.code, exc.field) == (ErrorCode.TOO_LARGE, "columns")
        assert link.get_power().shape == (200, 200)  # in blocks it fits


def test_fragments_that_carry_no_request_are_ignored_unanswered() -> None:
    dev, link = _device()
    with dev as ep:
        ignored = ep.stats.ignored
        ack = encode_payload(MsgType.ACK, {"request_type": int(MsgType.STATUS_GET)})
        notice = split_message(MsgType.ACK, ack + bytes(40), 20, seq=7)[0]  # a reply's piece
        short = encode_payload(MsgType.FRAGMENT, {  # a piece whose FRAGMENT header is cut
            "msg_type": 5, "seq": 1, "frame": 0, "column": 0, "index": 0, "count": 2,
            "data": b"x"})[:6]
        for payload in (notice, short):
            dev.write(encode_frame(MsgType.FRAGMENT, payload, 7, link.session))
        link.status()  # answered after both: the loop read them first, in order
        assert ep.stats.ignored == ignored + 2 and ep.stats.naks == 0


# ---- what the device survives of its application --------------------------------------
class _OddApp(SyntheticApp):
    """Columns with another frame id and no calibration flag, a generator that ends after
    ``stop_after`` columns, an abort() that raises."""

    def __init__(self, stop_after: int | None = None) -> None:
        super().__init__(channels=4, columns=10)
        self.stop_after = stop_after

    def _columns(self, frame: int, first: int, count: int,
                 calibration: bool) -> Iterator[ColumnResult]:
        cols = super()._columns(999, first, count, False)
        for k, col in enumerate(cols):
            if k == self.stop_after:
                return
            yield col

    def abort(self) -> None:
        super().abort()
        raise RuntimeError("abort hook failed")


def test_the_device_stamps_its_columns_with_the_stream_frame_and_calibration_flag() -> None:
    dev, link = _device(_OddApp())
    with dev:
        shots = link.calibrate(3, frame=12)
    assert [(c.frame, c.column, c.calibration) for c in shots] == [(12, k, True) for k in range(3)]


def test_an_application_that_ends_early_ends_the_scan_with_an_error_and_survives(caplog) -> None:
    """Its generator stops after 2 of 10 columns: SCAN_END reason 2 after those two; its
    abort() then raises, which is logged; the device answers on."""
    app = _OddApp(stop_after=2)
    dev, link = _device(app)
    got: list[int] = []
    with dev, caplog.at_level(logging.WARNING, logger="cdma_lidar.protocol"):
        with pytest.raises(StreamEnded) as exc:
            got.extend(c.column for c in link.scan(frame=4))
        assert link.status().state_name == "idle"
    assert got == [0, 1]
    assert (exc.value.next_column, exc.value.reason) == (2, ScanEndReason.ERROR)
    assert app.aborts == 1
    assert "ended frame 4 after 2 of 10 columns" in caplog.text
    assert "failed while ending frame 4" in caplog.text


# ---- what a host refuses of a device ---------------------------------------------------
def _hello_script(answer: Callable[[Frame, dict], bytes], **kw: Any) -> HostLink:
    """A link whose device is ``answer(request, its fields)``."""
    port = ScriptedPort(lambda f: answer(f, decode_payload(f.msg_type, f.payload)))
    return HostLink(port, timeout_s=0.2, retries=0, clock=port.clock, **kw)


def _info(**edit: Any) -> dict[str, Any]:
    return replace(SyntheticApp().info(), session_id=0x42, **edit).to_fields()


def test_a_device_that_challenges_the_answer_again_refuses_the_key() -> None:
    link = _hello_script(lambda f, d: reply(MsgType.CHALLENGE, {"device_nonce": bytes(16)},
                                            f.seq, 0), key=bytes(32))
    with pytest.raises(LinkError, match="another CHALLENGE"):
        link.hello()


def test_info_of_another_protocol_version_is_refused_naming_both() -> None:
    link = _hello_script(lambda f, d: reply(MsgType.INFO, _info(protocol_version=3), f.seq))
    with pytest.raises(LinkError, match="protocol version 3, host 4"):
        link.hello()


def test_info_that_asks_for_signed_frames_of_a_host_without_a_key_is_a_lie() -> None:
    link = _hello_script(lambda f, d: reply(MsgType.INFO, _info(auth=1), f.seq))
    with pytest.raises(DeviceLied) as exc:
        link.hello()
    assert exc.value.field == "auth"


def test_an_info_with_the_right_proof_but_no_signature_is_refused() -> None:
    """The device proves the key in INFO.device_mac but sends INFO unsigned: a man in the
    middle could have written the rest of it."""
    key, device_nonce = bytes(range(32)), bytes(range(16))

    def answer(f: Frame, d: dict) -> bytes:
        if not any(d["mac"]):
            return reply(MsgType.CHALLENGE, {"device_nonce": device_nonce}, f.seq, 0)
        mac = auth.device_mac(key, d["host_nonce"], device_nonce, 0x42)
        return reply(MsgType.INFO, _info(auth=1, device_mac=mac), f.seq)

    link = _hello_script(answer, key=key)
    with pytest.raises(LinkError, match="not signed with the session key"):
        link.hello()
    assert link.session is None


@pytest.mark.parametrize(("edit", "field"), [
    ({"spc_min": 9, "spc_max": 8}, "spc_min"),
    ({"column_power_cap_uw": 1000, "pixel_power_max_uw": 0}, "pixel_power_max_uw")])
def test_info_that_contradicts_itself_is_a_lie(edit: dict, field: str) -> None:
    link = _hello_script(lambda f, d: reply(MsgType.INFO, _info(**edit), f.seq))
    with pytest.raises(DeviceLied) as exc:
        link.hello()
    assert exc.value.field == field


def test_a_reply_of_the_wrong_type_is_refused_naming_both() -> None:
    link = scripted_link(ScriptedPort(lambda f: reply(MsgType.CONFIG, {"items": []}, f.seq)),
                         retries=0)
    with pytest.raises(LinkError, match="answered STATUS_GET with 0x83"):
        link.status()


def test_a_fragment_that_does_not_parse_is_counted_malformed() -> None:
    port = ScriptedPort(data=encode_frame(MsgType.FRAGMENT, b"\x01\x02", 0, 0x42))
    link = scripted_link(port, retries=0)
    with pytest.raises(LinkError):
        link.status()
    assert link.stats.malformed == 1


def test_a_power_get_answered_with_other_rows_is_a_lie() -> None:
    def answer(f: Frame) -> bytes:
        d = decode_payload(f.msg_type, f.payload)
        return reply(MsgType.POWER, {**d, "channel_start": d["channel_start"] + 1,
                                     "power": np.zeros(d["channels"] * d["columns"], int)},
                     f.seq)

    link = scripted_link(ScriptedPort(answer), retries=0)
    with pytest.raises(DeviceLied, match=r"rows 0\.\.7 with rows 1"):
        link.get_power()


@pytest.mark.parametrize(("edit", "match"), [
    ({"offset": 3}, "out of step: offset 3 \\(wanted 0\\)"),
    ({"elem_bytes": 3}, "3 bytes per element"),
    ({"data": b""}, "empty before the end")])
def test_capture_data_out_of_step_is_refused(edit: dict, match: str) -> None:
    def answer(f: Frame) -> bytes:
        d = decode_payload(f.msg_type, f.payload)
        chunk = {"kind": d["kind"], "column": d["column"], "channel": d["channel"],
                 "elem_bytes": 2, "total": 10, "offset": d["offset"], "data": bytes(4)}
        return reply(MsgType.CAPTURE_DATA, {**chunk, **edit}, f.seq)

    link = scripted_link(ScriptedPort(answer), retries=0)
    with pytest.raises(LinkError, match=match):
        link.capture("raw")


# ---- what a host refuses of its caller and its port ------------------------------------
def test_a_request_longer_than_max_pieces_fragments_is_a_field_error() -> None:
    link = scripted_link(ScriptedPort(), retries=0)
    link.max_frame = 256  # 254 pieces of 229 bytes: 58 kB at most
    with pytest.raises(FieldError, match="fragments") as exc:
        link.request(MsgType.POWER_SET, {"channel_start": 0, "column_start": 0,
                                         "channels": 1, "columns": 30000,
                                         "power": np.zeros(30000, int)})
    assert exc.value.field == "payload"


class _BrokenPort(ScriptedPort):
    def __init__(self, fail: str) -> None:
        super().__init__()
        self.fail = fail

    def write(self, data: bytes) -> int:
        if self.fail == "write":
            raise OSError("I/O error")
        return super().write(data)

    def read(self, n: int = 1) -> bytes:
        if self.fail == "read":
            raise OSError("device disconnected")
        return super().read(n)


@pytest.mark.parametrize("fail", ["write", "read"])
def test_a_failing_port_is_one_line_naming_it(fail: str) -> None:
    link = scripted_link(_BrokenPort(fail), retries=0)
    with pytest.raises(LinkError, match=f"cannot {fail} (to|from) script://device: .*"
                                        "still connected"):
        link.status()


# ---- a device application that implements only what it must ------------------------------
class _MinimalApp(SyntheticApp):
    """INFO, configuration and scans only: DeviceApp's defaults answer the rest."""

    calibrate = DeviceApp.calibrate
    set_power = DeviceApp.set_power
    get_power = DeviceApp.get_power
    capture = DeviceApp.capture


def test_a_minimal_application_refuses_what_it_does_not_implement() -> None:
    """CALIBRATE and POWER_SET: UNKNOWN_TYPE; POWER_GET and CAPTURE: NOT_AVAILABLE; a new
    session still starts (no boot power to restore) and scans."""
    app = _MinimalApp(channels=4, columns=10)
    dev, link = _device(app)
    with dev:
        for t, fields, code in (
                (MsgType.CALIBRATE, {"frame": 1, "shots": 2}, ErrorCode.UNKNOWN_TYPE),
                (MsgType.POWER_SET, {"channel_start": 0, "column_start": 0, "channels": 1,
                                     "columns": 1, "power": [7]}, ErrorCode.UNKNOWN_TYPE),
                (MsgType.POWER_GET, {"channel_start": 0, "column_start": 0, "channels": 1,
                                     "columns": 1}, ErrorCode.NOT_AVAILABLE),
                (MsgType.CAPTURE, {"kind": 0, "column": 0, "channel": 0, "offset": 0,
                                   "max_count": 10}, ErrorCode.NOT_AVAILABLE)):
            assert _refused(link, t, fields).code == code, t.name
        link.hello()  # a new session: configuration restored, no power matrix to restore
        assert [c.column for c in link.scan(columns=2, frame=3)] == [0, 1]


def test_a_new_session_starts_even_when_the_boot_configuration_cannot_be_restored(
        caplog) -> None:
    app = SyntheticApp(channels=4, columns=10)
    dev, link = _device(app)
    with dev, caplog.at_level(logging.ERROR, logger="cdma_lidar.protocol"):
        link.set_config(peaks=2)
        app.set_config = _raise  # type: ignore[method-assign]
        assert link.hello().channels == 4
        assert link.get_config("peaks") == {"peaks": 2}  # kept, and said in the log
    assert "cannot restore the boot configuration" in caplog.text


def _raise(*args: Any) -> None:
    raise RuntimeError("configuration store is read-only now")


class _GatedApp(SyntheticApp):
    """Each column waits for ``go`` (set by the test): the engine is busy until then."""

    def __init__(self) -> None:
        super().__init__(channels=4, columns=10)
        self.go = threading.Event()

    def _columns(self, frame: int, first: int, count: int,
                 calibration: bool) -> Iterator[ColumnResult]:
        for col in super()._columns(frame, first, count, calibration):
            assert self.go.wait(30.0), "the test never let the column go"
            yield col


def test_a_request_retransmitted_while_it_is_held_is_answered_once() -> None:
    """POWER_GET needs the application, so it is held while the engine computes a column;
    its retransmission meanwhile is not held a second time: one POWER answers both, and a
    later copy is answered from the replay cache (docs/protocol.md 6.1 and 6.6)."""
    app = _GatedApp()
    host, port = pipe_pair()
    # The engine on its thread; the endpoint's clock stands still (no heartbeat, no idle
    # expiry): only the Event moves the test on.
    ep = DeviceEndpoint(port, app, session_id=0x42, poll_s=0.0, clock=FakeClock())
    decoder = FrameDecoder()
    got: list[Frame] = []

    def send(t: MsgType, fields: dict[str, Any], seq: int) -> None:
        host.write(encode_frame(t, encode_payload(t, fields), seq, 0x42))

    def until(done: Callable[[], bool]) -> None:
        deadline = time.monotonic() + 30.0  # a condition to wait for, not a timing
        while not done():
            assert time.monotonic() < deadline, "the device never got there"
            ep.poll()
            got.extend(decoder.feed(host.read(host.in_waiting or 1)))

    try:
        host.write(encode_frame(MsgType.HELLO, encode_payload(MsgType.HELLO, hello_fields(1)),
                                1, 0))
        send(MsgType.SCAN_START, {"frame": 5, "first_column": 0, "columns": 3}, 2)
        until(lambda: ep.streams.stream is not None and ep.streams.stream.job is not None)
        rect = {"channel_start": 0, "column_start": 0, "channels": 2, "columns": 2}
        send(MsgType.POWER_GET, rect, 3)
        send(MsgType.POWER_GET, rect, 3)  # the host's retry, before the first is answered
        until(lambda: ep.stats.rx_requests == 4)  # HELLO, SCAN_START, POWER_GET twice
        assert len(ep.session.held) == 1
        app.go.set()
        until(lambda: any(f.msg_type == MsgType.POWER for f in got))
        send(MsgType.POWER_GET, rect, 3)  # once more, now answered: from the replay cache
        until(lambda: sum(f.msg_type == MsgType.POWER for f in got) == 2)
        assert ep.stats.replays == 1
        assert [f.seq for f in got if f.msg_type == MsgType.POWER] == [3, 3]
    finally:
        app.go.set()
        ep.close()
