"""Host link and device endpoint in memory: requests, NAKs, replay, scans, diagnoses."""

from __future__ import annotations

import itertools
from collections.abc import Iterator

import numpy as np
import pytest
import serial
from protocol_fixtures import (
    ScriptedPort,
    SteppedDevice,
    SyntheticApp,
    ack,
    capture_expected,
    expected_column,
    hello_fields,
    reply,
    scripted_link,
)

from cdma_lidar.errors import DeviceError, FieldError, LinkError, LinkTimeout
from cdma_lidar.protocol import framing
from cdma_lidar.protocol.config_keys import CONFIG_OPTIONAL, encode_config
from cdma_lidar.protocol.endpoint import FAULT_HEALTH, DeviceEndpoint
from cdma_lidar.protocol.framing import Frame, FrameDecoder, encode_frame
from cdma_lidar.protocol.link import HostLink
from cdma_lidar.protocol.messages import (
    REPLY_TO,
    CaptureKind,
    ErrorCode,
    MsgKind,
    MsgType,
    Status,
    decode_payload,
    encode_payload,
    kind_of,
)
from cdma_lidar.protocol.ports import open_port
from cdma_lidar.protocol.requests import (
    DIAG_GARBAGE,
    DIAG_NO_ANSWER,
    DIAG_NOISY,
    DIAG_SILENT,
    DIAG_WRONG_SESSION,
)
from cdma_lidar.virtual.line import Faults, pipe_pair

#: Reply timeout (s), on the threadless device's fake clock: waited out only by the tests
#: that expect a timeout, and never a matter of the machine's load.
TIMEOUT = 0.5


@pytest.fixture
def rig() -> Iterator[tuple[HostLink, DeviceEndpoint, SyntheticApp]]:
    app = SyntheticApp()
    port = SteppedDevice(app, heartbeat_s=0.05, session_id=0x1234, max_read=500)
    with port as ep:
        link = HostLink(port, timeout_s=TIMEOUT, retries=2, clock=port.clock)
        link.hello()
        yield link, ep, app
        link.close()


class Raw:
    """Talk to a device endpoint frame by frame (no HostLink in between)."""

    def __init__(self, port: SteppedDevice, session: int = 0) -> None:
        self.port = port
        self.session = session
        self.dec = FrameDecoder()

    def send(self, t: int, fields: dict | None = None, seq: int = 1, **kw) -> bytes:
        wire = encode_frame(t, encode_payload(t, fields or {}), seq, self.session, **kw)
        self.port.write(wire)
        return wire

    def recv(self) -> list[Frame]:
        """Every frame the device sends until it falls silent (each read polls it once)."""
        out: list[Frame] = []
        while data := self.port.read(65536):
            out += self.dec.feed(data)
        return out


@pytest.fixture
def raw() -> Iterator[tuple[Raw, DeviceEndpoint, SyntheticApp]]:
    app = SyntheticApp()
    port = SteppedDevice(app, heartbeat_s=10.0, session_id=0xABCD)
    with port as ep:
        r = Raw(port)
        r.send(MsgType.HELLO, hello_fields(5, 65535), seq=100)
        (info,) = r.recv()
        assert info.msg_type == MsgType.INFO and info.session == 0xABCD
        r.session = 0xABCD
        yield r, ep, app


def nak(frame: Frame) -> dict:
    assert frame.msg_type == MsgType.NAK, frame
    return decode_payload(MsgType.NAK, frame.payload)


# ---- requests -------------------------------------------------------------------------------
def test_handshake_gives_identity_limits_and_geometry(rig) -> None:
    link, ep, _app = rig
    info = link.info
    assert info.serial == "SYN-0001" and info.session_id == 0x1234 == link.session
    assert info.channels == 8 and info.column_count == 64 and info.max_frame == 16384
    np.testing.assert_allclose(info.wavelengths_m, 1570e-9 + 0.875e-9 * np.arange(8))
    assert info.tilt_deg is None and info.heartbeat_ms == 50
    assert info.ring_columns == ep.streams.ring_columns


def test_config_set_get_and_device_refusal(rig) -> None:
    link, _, app = rig
    link.set_config(peaks=3, uid_bits=2, rounding="half_up", ghost_windows=[(5, 2)])
    got = link.get_config()
    assert got["peaks"] == 3 and got["rounding"] == "half_up"
    assert got["ghost_windows"] == ((5, 2),)
    assert link.get_config("uid_bits", "poly_u") == {"uid_bits": 2, "poly_u": (11, 2)}
    with pytest.raises(DeviceError) as exc:
        link.set_config(code_index=[1, 2, 3])
    assert exc.value.code == ErrorCode.OUT_OF_RANGE and exc.value.field == "code_index"
    assert app.config["peaks"] == 3  # a refused CONFIG_SET changes nothing
    with pytest.raises(FieldError, match="adc_bits"):
        link.set_config(adc_bits=12)
    with pytest.raises(FieldError, match="nonsense"):
        link.set_config(nonsense=1)


def test_a_power_matrix_longer_than_a_frame_goes_as_one_request_in_fragments() -> None:
    app = SyntheticApp(channels=8, columns=300)
    dev = SteppedDevice(app, max_frame=512)
    link = HostLink(dev, clock=dev.clock, timeout_s=TIMEOUT)
    assert link.hello().max_frame == 512
    m = (np.arange(8 * 300).reshape(8, 300) * 7) % 65536
    before, pieces = link.stats.requests, dev.endpoint.decoder.stats.frames
    link.set_power(m)
    assert link.stats.requests - before == 1  # 4808 bytes: one POWER_SET in 10 FRAGMENTs
    assert dev.endpoint.decoder.stats.frames - pieces == 10
    np.testing.assert_array_equal(app.power, m)
    link.set_power(np.full((2, 3), 0.5), channel_start=1, column_start=10)
    assert (app.power[1:3, 10:13] == 32768).all()
    with pytest.raises(DeviceError) as exc:
        link.set_power(np.ones((9, 1), dtype=int))
    assert exc.value.field == "channel_start"
    with pytest.raises(FieldError, match="power"):
        link.set_power(np.full((2, 2), 1.5))


def test_a_request_in_fragments_survives_lost_pieces() -> None:
    """Every fifth frame to the device is lost: the retries fill the gaps (the device
    keeps the pieces it has), and the request is acted on once."""
    app = SyntheticApp(channels=8, columns=300)
    dev = SteppedDevice(app, max_frame=512, faults=Faults(drop=0.2), seed=5)
    link = HostLink(dev, clock=dev.clock, timeout_s=TIMEOUT, retries=10)
    link.hello()
    m = (np.arange(8 * 300).reshape(8, 300) * 3) % 65536
    link.set_power(m)
    np.testing.assert_array_equal(app.power, m)


def test_scan_calibrate_capture_status(rig) -> None:
    link, _ep, _app = rig
    link.set_config(peaks=2, uid_bits=3)
    cols = list(link.scan(first_column=5, columns=20))
    assert [c.column for c in cols] == list(range(5, 25))
    assert all(c == expected_column(c.frame, c.column, 8, 2, 3) for c in cols)
    two = list(link.scan(columns=3, frames=2))
    assert len(two) == 6 and two[0].frame + 1 == two[3].frame
    cal = link.calibrate(4)
    assert [c.column for c in cal] == [0, 1, 2, 3] and all(c.calibration for c in cal)
    assert cal[1] == expected_column(cal[1].frame, 1, 8, 2, 3, calibration=True)
    raw = link.capture("raw", column=3)
    np.testing.assert_array_equal(raw, capture_expected(CaptureKind.RAW, 3, 0))
    corr = link.capture(CaptureKind.CORR, column=2, channel=5)
    assert corr.dtype == np.int64
    np.testing.assert_array_equal(corr, capture_expected(CaptureKind.CORR, 2, 5))
    st = link.status()
    assert st.state_name == "idle" and st.frame == cal[0].frame and st.next_column == 4
    assert st.columns_sent == 20 + 6 + 4 and st.rx_errors == 0
    with pytest.raises(DeviceError) as exc:
        link.capture("raw", column=99)
    assert exc.value.field == "column"


def test_leaving_a_scan_early_aborts_it(rig) -> None:
    link, _ep, app = rig
    for c in link.scan():
        if c.column == 3:
            break
    assert link.status().state_name == "idle"
    assert app.aborts == 1
    assert len(list(link.scan(columns=5))) == 5  # the link is usable again


def test_busy_and_too_large(rig) -> None:
    link, _ep, _app = rig
    it = link.scan()
    next(it)
    with pytest.raises(DeviceError) as exc:
        link.set_config(peaks=2)
    assert exc.value.code == ErrorCode.BUSY
    it.close()
    big = SteppedDevice(SyntheticApp(channels=40, columns=6), max_frame=2048)
    with big:  # a 4419-byte column: three fragments
        link2 = HostLink(big, timeout_s=TIMEOUT, clock=big.clock)
        link2.set_config(peaks=8)
        assert list(link2.scan(frame=4)) == [expected_column(4, c, 40, 8, 1) for c in range(6)]
    huge = SteppedDevice(SyntheticApp(channels=1500, columns=2), max_frame=256)
    with huge:  # INFO itself comes in 27 fragments
        link3 = HostLink(huge, timeout_s=TIMEOUT, max_frame=256, clock=huge.clock)
        assert link3.hello().channels == 1500
        link3.set_config(peaks=8)  # a column of 1500 x 110 bytes: 721 fragments
        with pytest.raises(DeviceError) as exc:
            list(link3.scan())
        assert exc.value.code == ErrorCode.TOO_LARGE and exc.value.field == "peaks"


def test_resend_of_a_column_no_longer_kept(rig) -> None:
    link, ep, _app = rig
    ep.streams.ring_columns = 4
    cols = list(link.scan(columns=10))
    with pytest.raises(DeviceError) as exc:
        link.request(MsgType.RESEND, {"frame": cols[0].frame, "columns": [9, 0],
                                       "fragments": []})
    assert exc.value.code == ErrorCode.NOT_AVAILABLE and exc.value.field == "columns[1]"


# ---- device behaviour, frame by frame ------------------------------------------------------------
def test_retransmitted_request_is_replayed_not_repeated(raw) -> None:
    r, ep, app = raw
    items = encode_config({"peaks": 4})
    wire = r.send(MsgType.CONFIG_SET, {"items": items}, seq=101)
    first = r.recv()
    r.port.write(wire)
    r.port.write(wire)
    again = r.recv()
    assert [f.msg_type for f in first] == [MsgType.ACK]
    assert again == first * 2
    assert app.set_config_calls == 1 and ep.stats.replays == 2
    r.send(MsgType.SCAN_START, {"frame": 9, "first_column": 0, "columns": 3}, seq=102)
    r.send(MsgType.SCAN_START, {"frame": 9, "first_column": 0, "columns": 3}, seq=102)
    frames = r.recv()
    assert app.scan_calls == 1
    cols = [f for f in frames if f.msg_type == MsgType.COLUMN_RESULT]
    assert len(cols) == 3


def test_late_duplicate_of_an_older_request_is_dropped(raw) -> None:
    r, ep, app = raw
    r.send(MsgType.STATUS_GET, seq=110)
    assert len(r.recv()) == 1
    r.send(MsgType.CONFIG_SET, {"items": encode_config({"peaks": 5})}, seq=105)
    assert r.recv() == []
    assert ep.stats.stale == 1 and app.config["peaks"] == 1


def test_device_naks_what_it_cannot_act_on(raw) -> None:
    r, ep, app = raw
    r.send(MsgType.CONFIG_SET, {"items": [{"key": 99, "value": b"\x01"}]}, seq=120)
    (f,) = r.recv()
    assert nak(f)["code"] == ErrorCode.UNKNOWN_KEY and nak(f)["field"] == "key 99"
    assert f.seq == 120 and f.session == 0xABCD
    r.send(MsgType.CONFIG_SET, {"items": [{"key": 99 | CONFIG_OPTIONAL, "value": b"\x01"},
                                          {"key": 16, "value": b"\x02"}]}, seq=121)
    (f,) = r.recv()
    assert f.msg_type == MsgType.ACK and app.config["peaks"] == 2
    r.send(MsgType.CONFIG_SET, {"items": [{"key": 8, "value": b"\x0c"}]}, seq=122)
    assert nak(r.recv()[0])["code"] == ErrorCode.READ_ONLY
    r.send(MsgType.CONFIG_SET, {"items": [{"key": 16, "value": b"\x02\x00"}]}, seq=123)
    n = nak(r.recv()[0])
    assert n["code"] == ErrorCode.MALFORMED and n["field"] == "peaks"
    r.port.write(encode_frame(MsgType.SCAN_START, b"\x01\x02", 124, r.session))
    assert nak(r.recv()[0])["code"] == ErrorCode.MALFORMED
    r.port.write(encode_frame(0x7E, b"", 125, r.session))
    assert nak(r.recv()[0])["code"] == ErrorCode.UNKNOWN_TYPE
    r.port.write(encode_frame(MsgType.STATUS_GET, b"", 126, r.session, version=5))
    assert r.recv() == []  # the NAK is in the request's version: this decoder rejects it
    (f,) = r.dec.rejected
    r.dec.rejected.clear()
    assert nak(f)["code"] == ErrorCode.VERSION and f.version == 5 != framing.PROTOCOL_VERSION
    r.port.write(encode_frame(MsgType.STATUS_GET, b"", 127, r.session, incompat=0x80))
    assert nak(r.recv()[0])["code"] == ErrorCode.UNSUPPORTED_FLAGS
    r.port.write(encode_frame(MsgType.STATUS_GET, b"", 128, 0x5555))
    assert nak(r.recv()[0])["code"] == ErrorCode.WRONG_SESSION
    r.port.write(encode_frame(MsgType.ACK, b"\x01", 129, r.session))  # not a request
    assert r.recv() == [] and ep.stats.ignored == 1


def test_device_survives_an_application_crash(raw) -> None:
    r, _ep, app = raw

    def boom(values: dict) -> None:
        raise RuntimeError("firmware bug")

    app.set_config = boom
    r.send(MsgType.CONFIG_SET, {"items": encode_config({"peaks": 2})}, seq=130)
    n = nak(r.recv()[0])
    assert n["code"] == ErrorCode.INTERNAL and "firmware bug" in n["detail"]
    r.send(MsgType.STATUS_GET, seq=131)
    assert r.recv()[0].msg_type == MsgType.STATUS


def test_device_survives_line_garbage(raw) -> None:
    r, _ep, _app = raw
    noise = np.random.default_rng(11).integers(1, 256, 5000, dtype=np.uint8).tobytes()
    r.port.write(noise + b"\x00\x00")
    r.send(MsgType.STATUS_GET, seq=140)
    got = r.recv()
    assert any(f.msg_type == MsgType.LINE_ERROR for f in got)  # damage is reported at once
    (f,) = [f for f in got if f.msg_type != MsgType.LINE_ERROR]
    assert f.msg_type == MsgType.STATUS
    assert decode_payload(MsgType.STATUS, f.payload)["rx_errors"] >= 1


# ---- the host's view of a bad line ----------------------------------------------------
@pytest.mark.parametrize(("diag", "make"), [
    (DIAG_SILENT, None),
    (DIAG_GARBAGE, lambda k: bytes([0x55, k & 0xFF, 0x00, 0x03, 0x77])),
    (DIAG_WRONG_SESSION, lambda k: encode_frame(
        MsgType.HEARTBEAT, encode_payload(MsgType.HEARTBEAT,
                                          Status(uptime_ms=k).to_fields()), k, 0x0BAD)),
    (DIAG_NO_ANSWER, lambda k: encode_frame(MsgType.ACK, b"\x0a", 9999, 0x600D)),
])
def test_silent_link_gets_a_specific_diagnosis(diag: str, make) -> None:
    k = itertools.count()
    port = ScriptedPort(idle=lambda now: b"" if make is None else make(next(k)))
    link = scripted_link(port, 0x600D, retries=1)  # as if HELLO had succeeded before
    with pytest.raises(LinkTimeout) as exc:
        link.status()
    assert exc.value.diagnosis == diag
    assert diag in str(exc.value) and "STATUS_GET" in str(exc.value)
    assert link.stats.retries == 1


def test_device_restart_is_reported_at_once(rig) -> None:
    link, ep, _app = rig
    ep.tx.session = 0x7777  # the device rebooted and chose a new session
    with pytest.raises(DeviceError) as exc:  # a NAK, not a LinkTimeout after the retries
        link.status()
    assert exc.value.code == ErrorCode.WRONG_SESSION
    assert link.stats.retries == 0
    assert link.hello().session_id not in (0, 0x7777)  # a fresh session per HELLO
    assert link.status().state_name == "idle"


def test_open_port_errors_say_what_to_do() -> None:
    with pytest.raises(LinkError, match="cannot open port '/dev/nonexistent-cdma'"):
        open_port("/dev/nonexistent-cdma")
    with pytest.raises(LinkError, match="unknown URL scheme 'bogus'"):
        open_port("bogus://x")
    port = open_port("loop://", timeout=0.01)
    # The timeout runs on an injected clock that moves 0.1 s per look, not on real time.
    link = HostLink(port, timeout_s=0.5, retries=0, clock=itertools.count(0.0, 0.1).__next__)
    with pytest.raises(LinkTimeout) as exc:  # a loopback only echoes our own requests
        link.hello()
    assert exc.value.diagnosis == DIAG_NO_ANSWER and link.stats.ignored >= 1
    link.close()


def test_open_port_names_the_scheme_without_a_handler_and_registers_none() -> None:
    before = list(serial.protocol_handler_packages)
    with pytest.raises(LinkError) as exc:
        open_port("nosuchscheme://x")
    text = str(exc.value)
    assert "'nosuchscheme'" in text and "no handler is registered for nosuchscheme://" in text
    assert "virtual" not in text  # the wire layer knows no device package
    assert serial.protocol_handler_packages == before


def test_every_request_type_has_a_handler_and_nothing_else_does() -> None:
    requests = {t for t in MsgType if kind_of(t) is MsgKind.REQUEST}
    ep = DeviceEndpoint(pipe_pair()[1], SyntheticApp())
    assert set(ep.handlers) == requests == set(REPLY_TO)


def test_host_link_checks_its_arguments() -> None:
    host, _ = pipe_pair()
    with pytest.raises(ValueError, match="timeout_s"):
        HostLink(host, timeout_s=0)
    with pytest.raises(ValueError, match="retries"):
        HostLink(host, retries=-1)


def test_failing_health_sensor_sets_a_fault_bit_not_a_dead_link(rig) -> None:
    link, _, app = rig

    def broken() -> tuple[int, int]:
        raise RuntimeError("i2c timeout")

    app.health = broken
    st = link.status()
    assert st.faults & FAULT_HEALTH and st.temperature_c != st.temperature_c  # NaN
    assert len(list(link.scan(columns=3))) == 3  # heartbeats call health() too


def test_device_stays_responsive_while_a_column_takes_long() -> None:
    """Columns slower than the host's whole retry budget: heartbeats and STATUS keep it alive."""
    started: list[float] = []
    sent = [0]

    def status() -> Status:
        return Status(state=1, frame=3, next_column=sent[0])

    def answer(req: Frame) -> bytes:
        if req.msg_type == MsgType.STATUS_GET:
            return reply(MsgType.STATUS, status(), req.seq)
        started.append(port.clock())
        return ack(req)

    def idle(now: float) -> bytes:  # a column every 0.15 s, a heartbeat every poll
        out = b""
        if started and sent[0] < 3 and now - started[0] >= 0.15 * (sent[0] + 1):
            out = reply(MsgType.COLUMN_RESULT, expected_column(3, sent[0], 8, 1, 1), 0)
            sent[0] += 1
        return out + reply(MsgType.HEARTBEAT, status(), 0)

    port = ScriptedPort(answer, idle)
    link = scripted_link(port, timeout_s=0.04, retries=1)  # budget 0.08 s < 0.15 s per column
    cols = list(link.scan(columns=3, frame=3))
    assert [c.column for c in cols] == [0, 1, 2]
    assert link.stats.resend_requests == 0
    assert link.last_status is not None and link.last_status.state_name == "scanning"


@pytest.mark.parametrize("lost_end", [False, True])
def test_device_failure_mid_scan_delivers_what_was_sent_then_raises(lost_end: bool) -> None:
    """Also when SCAN_END is lost: the STATUS probe says how the scan ended."""
    app = SyntheticApp()
    app.fail_at = 7
    port = SteppedDevice(app, seed=4, heartbeat_s=0.02)
    if lost_end:
        push = port.rx.write  # what the device writes

        def drop_scan_end(data: bytes) -> None:
            frames = FrameDecoder().feed(data)
            if not (frames and frames[0].msg_type == MsgType.SCAN_END):
                push(data)

        port.rx.write = drop_scan_end
    with port:
        link = HostLink(port, timeout_s=TIMEOUT, clock=port.clock)
        got = []
        with pytest.raises(DeviceError) as exc:
            for c in link.scan(columns=20):
                got.append(c.column)
        assert exc.value.code == ErrorCode.INTERNAL
        assert got == list(range(7))
        app.fail_at = None
        assert len(list(link.scan(columns=5))) == 5


def test_power_before_hello_uses_the_session_frame_size() -> None:
    app = SyntheticApp(channels=8, columns=300)
    port = SteppedDevice(app, max_frame=512)
    with port as ep:
        link = HostLink(port, timeout_s=TIMEOUT, clock=port.clock)
        link.set_power(np.full((8, 300), 3))  # hello() happens first, implicitly
        assert (app.power == 3).all() and ep.decoder.stats.oversize == 0


def test_reply_echoing_another_request_type_is_not_taken() -> None:
    """An ACK with the right seq but another request's type (e.g. from a previous link)."""
    port = ScriptedPort(lambda f: b"".join(  # wrong echo first
        encode_frame(MsgType.ACK, bytes([rtype]), f.seq, 0x42)
        for rtype in (MsgType.CONFIG_SET, f.msg_type)))
    link = scripted_link(port, retries=0)
    link.abort()  # takes the second ACK, which echoes SCAN_ABORT
    assert link.stats.stale_replies == 1


def test_column_that_never_arrives_intact_fails_after_its_budget() -> None:
    """Short frames pass, every copy of column 2 is damaged: a clear timeout, no hang."""
    port = SteppedDevice(SyntheticApp(), heartbeat_s=0.02)
    push = port.rx.write  # what the device writes

    def damage_column_2(data: bytes) -> None:
        frames = FrameDecoder().feed(data)
        if frames and frames[0].msg_type == MsgType.COLUMN_RESULT and \
                frames[0].payload[4:6] == b"\x02\x00":
            data = data[:40] + bytes([data[40] ^ 0x10]) + data[41:]
        push(data)

    port.rx.write = damage_column_2
    with port:
        link = HostLink(port, timeout_s=TIMEOUT, column_retries=3, clock=port.clock)
        got = []
        with pytest.raises(LinkTimeout) as exc:
            for c in link.scan(columns=6):
                got.append(c.column)
        assert got == [0, 1]
        assert exc.value.diagnosis == DIAG_NOISY and "column 2" in str(exc.value)
        assert "damaged frames of" in str(exc.value)
        assert link.stats.resent_columns >= 3
