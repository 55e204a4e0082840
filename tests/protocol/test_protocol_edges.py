"""Edges of the link: version skew, spinning waits, end of file, stream clean-up order."""

from __future__ import annotations

import os
import threading
import time
from collections.abc import Iterator

import pytest
from protocol_fixtures import (
    RunningDevice,
    ScriptedPort,
    SteppedDevice,
    SyntheticApp,
    ack,
    hello_fields,
    reply,
    scripted_link,
)

from cdma_lidar.errors import DeviceError, LinkError, LinkTimeout
from cdma_lidar.protocol import framing
from cdma_lidar.protocol.columns import ColumnResult
from cdma_lidar.protocol.endpoint import DeviceEndpoint, Engine
from cdma_lidar.protocol.framing import Frame, FrameDecoder, encode_frame
from cdma_lidar.protocol.link import HostLink
from cdma_lidar.protocol.messages import ErrorCode, MsgType, Status, decode_payload, encode_payload
from cdma_lidar.protocol.ports import FdPort
from cdma_lidar.protocol.requests import DIAG_GARBAGE, DIAG_VERSION
from cdma_lidar.virtual.line import pipe_pair


def test_reply_in_another_protocol_version_fails_at_once_naming_both() -> None:
    """A device of another version NAKs VERSION in that version: the host says so, no
    timeout."""
    nak = encode_payload(MsgType.NAK, {"request_type": MsgType.HELLO,
                                       "code": int(ErrorCode.VERSION), "field": "version",
                                       "detail": ""})
    port = ScriptedPort(lambda f: encode_frame(MsgType.NAK, nak, f.seq, 0x99, version=5))
    link = HostLink(port, retries=3, clock=port.clock)
    with pytest.raises(LinkError, match="protocol version 5") as exc:
        link.hello()
    assert not isinstance(exc.value, LinkTimeout)
    assert "version 4" in str(exc.value)
    assert link.stats.retries == 0  # at once: no retry, so no timeout was waited for


def test_only_frames_of_another_version_are_diagnosed_as_such() -> None:
    """Frames that pass the CRC but carry another version, none answering us."""
    hb = encode_payload(MsgType.HEARTBEAT, Status().to_fields())
    port = ScriptedPort(idle=lambda now: encode_frame(MsgType.HEARTBEAT, hb, 1, 0x600D,
                                                      version=5))
    link = scripted_link(port, 0x600D, retries=1)
    with pytest.raises(LinkTimeout) as exc:
        link.status()
    assert exc.value.diagnosis == DIAG_VERSION and DIAG_VERSION in str(exc.value)
    assert link.decoder.stats.version >= 1 and link.decoder.stats.frames == 0


def test_garbage_is_still_garbage_with_the_version_diagnosis_in_place() -> None:
    link = scripted_link(ScriptedPort(data=b"\x00\x03\x01\x02\x00" * 10), 1, retries=0)
    with pytest.raises(LinkTimeout) as exc:
        link.status()
    assert exc.value.diagnosis == DIAG_GARBAGE


@pytest.mark.parametrize(("kw", "name"), [
    ({"poll_s": 1.5}, "poll_s"), ({"poll_s": -1.0}, "poll_s"),
    ({"heartbeat_s": 0}, "heartbeat_s"), ({"heartbeat_s": 100.0}, "heartbeat_s"),
    ({"ring_columns": -1}, "ring_columns"),
    ({"ring_columns": 70000}, "ring_columns"),
    ({"max_frame": 100}, "max_frame"), ({"session_id": 2**32}, "session_id"),
])
def test_device_endpoint_names_a_bad_argument(kw: dict, name: str) -> None:
    _, dev = pipe_pair()
    with pytest.raises(ValueError, match=name):
        DeviceEndpoint(dev, SyntheticApp(), **kw)


def test_fd_port_raises_at_end_of_file_instead_of_returning_nothing() -> None:
    r, w = os.pipe()
    port = FdPort(r, timeout=None)  # no timeout: only end of file can end this read
    os.write(w, b"abc")
    assert port.read(3) == b"abc"
    os.close(w)
    with pytest.raises(OSError, match="end of file"):
        port.read(1)
    port.close()


def test_device_endpoint_stops_when_its_fd_reaches_end_of_file() -> None:
    """serve_forever ends (it would otherwise spin on an always-readable empty fd)."""
    r, w = os.pipe()
    port = FdPort(r)
    port.write = lambda data: len(data)  # type: ignore[method-assign]  # write side unused
    ep = DeviceEndpoint(port, SyntheticApp())
    stop = threading.Event()
    t = threading.Thread(target=ep.serve_forever, args=(stop,), daemon=True)
    t.start()
    os.close(w)
    t.join(2.0)
    assert not t.is_alive()
    stop.set()
    port.close()


class _RecordingApp(SyntheticApp):
    """Logs scan(), generator close and abort() in the order the application sees them.

    A column takes 0.1 s, so a scan of 50 columns is still running 5 s after it started:
    the requests these tests send while it runs are in time even on a loaded machine.
    """

    def __init__(self) -> None:
        super().__init__(column_delay_s=0.1)
        self.log: list[tuple[str, int]] = []

    def scan(self, frame: int, first_column: int, columns: int) -> Iterator[ColumnResult]:
        self.log.append(("scan", frame))
        inner = super().scan(frame, first_column, columns)

        def gen() -> Iterator[ColumnResult]:
            try:
                yield from inner
            finally:
                self.log.append(("close", frame))

        return gen()

    def abort(self) -> None:
        super().abort()
        self.log.append(("abort", self.log[-1][1] if self.log else -1))


def _until_a_column_is_out(ep: DeviceEndpoint) -> None:
    """Wait (a condition, not a time) until the scan's generator has produced a column."""
    deadline = time.monotonic() + 10.0
    streams = ep.streams
    while (streams.latest is None or streams.latest.produced == 0) and time.monotonic() < deadline:
        time.sleep(0.005)
    assert streams.latest is not None and streams.latest.produced > 0


def test_an_ended_stream_is_cleaned_up_before_the_next_one_starts() -> None:
    """SCAN_ABORT then SCAN_START at once: the app closes scan 1 before it is asked for scan 2."""
    host, dev = pipe_pair()
    host.timeout = 0.02
    app = _RecordingApp()
    with RunningDevice(dev, app, heartbeat_s=10.0, session_id=0xABCD) as ep:
        def send(t: MsgType, fields: dict, seq: int) -> bytes:
            return encode_frame(t, encode_payload(t, fields), seq, 0xABCD)

        host.write(send(MsgType.HELLO, hello_fields(1, 65535), 1))
        host.write(send(MsgType.SCAN_START, {"frame": 1, "first_column": 0, "columns": 50}, 2))
        _until_a_column_is_out(ep)  # the worker is inside a later column of frame 1
        host.write(send(MsgType.SCAN_ABORT, {}, 3) +
                   send(MsgType.SCAN_START, {"frame": 2, "first_column": 0, "columns": 2}, 4))
        dec = FrameDecoder()
        got: list[Frame] = []
        deadline = time.monotonic() + 20.0  # a condition to wait for, not a timing
        while time.monotonic() < deadline and not any(
                f.msg_type == MsgType.SCAN_END and f.payload[:4] == b"\x02\x00\x00\x00"
                for f in got):
            got += dec.feed(host.read(max(1, host.in_waiting)))
    acks = [f for f in got if f.msg_type == MsgType.ACK]
    assert [f.seq for f in acks] == [2, 3, 4]  # the second scan was not refused BUSY
    assert app.log.index(("close", 1)) < app.log.index(("scan", 2))
    assert app.log.index(("abort", 1)) < app.log.index(("scan", 2))
    assert app.log.count(("close", 1)) == 1 and app.aborts == 1


def test_back_to_back_scans_are_never_refused_busy() -> None:
    """The stream ends in the step that queued its last column (no BUSY window): a
    SCAN_START read in the very next poll finds the device idle. Threadless, one poll at
    a time, so the window is looked at exactly."""
    host, dev = pipe_pair()
    app = SyntheticApp(columns=4)
    ep = DeviceEndpoint(dev, app, session_id=0x77, poll_s=0.0, engine=Engine(threaded=False))
    dec = FrameDecoder()

    def send(t: MsgType, fields: dict, seq: int) -> None:
        host.write(encode_frame(t, encode_payload(t, fields), seq, 0x77))

    def received() -> list[Frame]:
        return dec.feed(host.read(host.in_waiting)) if host.in_waiting else []

    send(MsgType.HELLO, hello_fields(1), 1)
    ep.poll()
    assert [f.msg_type for f in received()] == [MsgType.INFO]
    for k in range(20):
        seq = 2 + k
        send(MsgType.SCAN_START, {"frame": k, "first_column": 0, "columns": 4}, seq)
        columns = 0
        for _ in range(50):  # until the last column is out, one poll at a time
            ep.poll()
            got = received()
            assert not [f for f in got if f.msg_type == MsgType.NAK], got
            columns += sum(f.msg_type == MsgType.COLUMN_RESULT for f in got)
            if columns == 4:
                break
        assert columns == 4
    assert app.aborts == 0 and ep.stats.naks == 0 and app.scan_calls == 20


def test_worker_failure_outside_the_application_ends_the_stream() -> None:
    """A column too large for 254 fragments: SCAN_END reason 2, and the device stays usable."""

    class Growing(SyntheticApp):
        def _columns(self, frame, first, count, calibration):  # type: ignore[override]
            yield from super()._columns(frame, first, 1, calibration)
            self.channels = 1500  # a misbehaving app: columns grow beyond what was checked
            yield from super()._columns(frame, first + 1, count - 1, calibration)

    app = Growing(channels=8, columns=10)
    port = SteppedDevice(app, max_frame=256, heartbeat_s=0.02)
    with port:
        link = HostLink(port, timeout_s=0.05, retries=2, clock=port.clock)
        got = []
        with pytest.raises(LinkError):
            for c in link.scan(columns=5):
                got.append(c.column)
        assert got == [0]
        st = link.status()
        assert st.state_name == "idle" and st.last_end == 2
        app.channels = 8
        app._columns = SyntheticApp._columns.__get__(app)  # type: ignore[method-assign]
        assert [c.column for c in link.scan(columns=3)] == [0, 1, 2]


def test_zero_length_decoded_frame_is_counted_as_short() -> None:
    """COBS of zero bytes (``01``) between delimiters is a frame of 0 bytes: an error event."""
    dec = FrameDecoder()
    assert framing.cobs_decode(b"\x01") == b""
    good = encode_frame(MsgType.ACK, b"\x05", 1, 2)
    assert dec.feed(b"\x00\x01\x00" + good) == [Frame(MsgType.ACK, 1, 2, b"\x05")]
    assert dec.stats.short == 1 and dec.stats.errors == 1
    assert framing.OVERHEAD == 16


def test_heartbeats_of_another_frame_do_not_keep_a_scan_waiting_forever() -> None:
    """The device is busy with someone else's frame: the silence probe says so."""
    other = Status(state=1, frame=999, next_column=3)
    port = ScriptedPort(  # a heartbeat every poll: many per host timeout
        lambda f: reply(MsgType.STATUS, other, f.seq) if f.msg_type == MsgType.STATUS_GET
        else ack(f), lambda now: reply(MsgType.HEARTBEAT, other, 1))
    link = scripted_link(port, retries=1)
    with pytest.raises(LinkError, match="frame 999"):
        list(link.scan(columns=5, frame=7))


@pytest.mark.parametrize("frames", [0, -1, 1.5])
def test_scan_names_a_bad_frame_count(frames) -> None:
    link = HostLink(ScriptedPort())
    with pytest.raises(ValueError, match="frames"):
        next(link.scan(frames=frames))


def test_hello_during_a_scan_ends_it_for_the_application_before_it_answers() -> None:
    """A new host takes over mid-scan: by the time INFO arrives the app has aborted it."""
    host, dev = pipe_pair()
    host.timeout = 0.02
    app = _RecordingApp()

    def send(t: MsgType, fields: dict, seq: int, session: int) -> None:
        host.write(encode_frame(t, encode_payload(t, fields), seq, session))

    with RunningDevice(dev, app, heartbeat_s=10.0, session_id=0xABCD) as ep:
        send(MsgType.HELLO, hello_fields(1, 65535), 1, 0)
        send(MsgType.SCAN_START, {"frame": 5, "first_column": 0, "columns": 50}, 2, 0xABCD)
        _until_a_column_is_out(ep)
        send(MsgType.HELLO, hello_fields(2, 65535, flags=1), 900, 0)  # take over
        dec = FrameDecoder()
        info: list[Frame] = []
        deadline = time.monotonic() + 20.0  # a condition to wait for, not a timing
        while not info and time.monotonic() < deadline:
            info = [f for f in dec.feed(host.read(max(1, host.in_waiting)))
                    if f.msg_type == MsgType.INFO and f.seq == 900]
        assert info, "no INFO for the second HELLO"
        assert app.aborts == 1 and ("close", 5) in app.log


def test_device_falling_silent_mid_scan_is_diagnosed_not_waited_on() -> None:
    """The device end goes dead after a few columns: the STATUS probe fails with a diagnosis."""
    from cdma_lidar.protocol.requests import DIAG_SILENT
    from cdma_lidar.virtual.line import Faults

    port = SteppedDevice(SyntheticApp(columns=40), heartbeat_s=0.02)
    dev = port.endpoint.port
    with port:
        link = HostLink(port, timeout_s=0.05, retries=1, clock=port.clock)
        link.hello()
        got = []
        with pytest.raises(LinkTimeout) as exc:
            for c in link.scan():
                got.append(c.column)
                if c.column == 2:
                    dev.tx.faults = Faults(drop=1.0)  # nothing reaches the host any more
    assert got[:3] == [0, 1, 2] and len(got) < 40
    assert exc.value.diagnosis == DIAG_SILENT and "STATUS_GET" in str(exc.value)


def test_a_capture_chunk_fills_the_frame_exactly() -> None:
    """The CAPTURE_DATA header size comes from its declaration: a chunk is as long as the
    session's frame allows, never longer."""
    port = SteppedDevice(SyntheticApp(channels=4, columns=8))
    with port:
        link = HostLink(port, timeout_s=0.2, max_frame=256, clock=port.clock)
        link.hello()
        sent = []
        write = port.endpoint.port.write
        port.endpoint.port.write = lambda data: (sent.append(bytes(data)), write(data))[1]
        link.capture("raw", column=1)
        sizes = [len(framing.cobs_decode(c)) for w in sent for c in w.split(b"\0") if c]
        assert max(sizes) == 256


def test_a_small_host_frame_cuts_every_column_to_it() -> None:
    """HELLO.host_max_frame bounds the device's frames: 1.6 kB columns come in pieces."""
    port = SteppedDevice(SyntheticApp(channels=40, columns=3))
    with port:
        link = HostLink(port, timeout_s=0.2, max_frame=96, clock=port.clock)
        link.hello()
        sent: list[bytes] = []
        write = port.endpoint.port.write
        port.endpoint.port.write = lambda data: (sent.append(bytes(data)), write(data))[1]
        assert [c.column for c in link.scan(frame=4)] == [0, 1, 2]
        sizes = [len(framing.cobs_decode(c)) for w in sent for c in w.split(b"\0") if c]
        assert len(sizes) > 3 * 20 and max(sizes) <= 96  # 1.6 kB columns in pieces


class _InsideColumn(SyntheticApp):
    """Its engine stays inside column 1 of every scan until ``release`` is set."""

    def __init__(self) -> None:
        super().__init__(channels=4, columns=8)
        self.release = threading.Event()

    def _columns(self, frame, first, count, calibration):  # type: ignore[override]
        for col in super()._columns(frame, first, count, calibration):
            if col.column == 1:
                self.release.wait(60.0)
            yield col


def test_the_loop_answers_within_50_ms_while_the_engine_is_inside_a_column() -> None:
    """STATUS_GET, the BUSY refusals and SCAN_ABORT are answered, and heartbeats keep
    coming, while the engine's thread is inside a column that ends only when the test
    says so. Times on the device's injected clock: one poll of its loop per 1 ms."""
    now = [0.0]
    host, dev = pipe_pair()
    app = _InsideColumn()
    ep = DeviceEndpoint(dev, app, session_id=0x77, poll_s=0.0, heartbeat_s=0.2,
                        clock=lambda: now[0])
    dec = FrameDecoder()
    heard: list[tuple[float, Frame]] = []

    def step(until) -> float:
        """Poll (1 ms a turn) until ``until()``; the device time it took (s)."""
        t0 = now[0]
        for _ in range(100_000):  # a bound on turns, not a time
            ep.poll()
            if host.in_waiting:
                heard.extend((now[0], f) for f in dec.feed(host.read(host.in_waiting)))
            if until():
                return now[0] - t0
            now[0] += 0.001
        raise AssertionError("no answer")

    def ask(t: MsgType, fields: dict, seq: int) -> tuple[Frame, float]:
        host.write(encode_frame(t, encode_payload(t, fields), seq, 0x77))
        n = len(heard)
        took = step(lambda: any(f.seq == seq and f.msg_type in (MsgType.ACK, MsgType.NAK,
                                                                MsgType.STATUS, MsgType.INFO)
                                for _, f in heard[n:]))
        return next(f for _, f in heard[n:] if f.seq == seq and
                    f.msg_type in (MsgType.ACK, MsgType.NAK, MsgType.STATUS, MsgType.INFO)), took

    try:
        assert ask(MsgType.HELLO, hello_fields(1), 1)[0].msg_type == MsgType.INFO
        assert ask(MsgType.SCAN_START, {"frame": 1, "first_column": 0, "columns": 8},
                   2)[0].msg_type == MsgType.ACK
        st = ep.streams.latest
        step(lambda: st.produced == 1 and st.job is not None)  # the engine is in column 1
        start = now[0]
        status, took = ask(MsgType.STATUS_GET, {}, 3)
        assert took <= 0.05
        assert decode_payload(MsgType.STATUS, status.payload)["state"] == 1  # scanning
        for seq, (t, fields) in enumerate([
                (MsgType.CONFIG_SET, {"items": []}),
                (MsgType.SCAN_START, {"frame": 2, "first_column": 0, "columns": 1})], 4):
            busy, took = ask(t, fields, seq)
            assert busy.msg_type == MsgType.NAK
            assert decode_payload(MsgType.NAK, busy.payload)["code"] == ErrorCode.BUSY
            assert took <= 0.05
        step(lambda: now[0] >= start + 1.0)  # a second inside the column
        beats = [t for t, f in heard if f.msg_type == MsgType.HEARTBEAT and t >= start]
        gaps = [b - a for a, b in zip([start, *beats[:-1]], beats, strict=True)]
        assert len(beats) >= 5 and max(gaps) <= 0.2
        aborted, took = ask(MsgType.SCAN_ABORT, {}, 6)
        assert aborted.msg_type == MsgType.ACK and took <= 0.05
        assert any(f.msg_type == MsgType.SCAN_END for _, f in heard[-3:])
        assert not st.job.done()  # all of it while the engine was inside the column
    finally:
        app.release.set()
    step(lambda: ep.core.engine.idle)
    assert app.aborts == 1
    ep.close()


def test_scan_start_refused_busy_waits_for_the_previous_stream_then_asks_once_more() -> None:
    """Only our own previous stream can hold the device (repairs still going out): the
    host asks STATUS until it is idle, then sends SCAN_START again (docs/protocol.md 6.2)."""
    statuses = iter([Status(state=1, frame=6, next_column=3), Status(state=0, frame=6)])
    starts: list[Frame] = []

    def answer(f: Frame) -> bytes:
        if f.msg_type == MsgType.STATUS_GET:
            return reply(MsgType.STATUS, next(statuses), f.seq)
        if f.msg_type != MsgType.SCAN_START:
            return ack(f)
        starts.append(f)
        if len(starts) == 1:
            return reply(MsgType.NAK, {"request_type": int(MsgType.SCAN_START),
                                       "code": int(ErrorCode.BUSY), "field": "", "detail": ""},
                         f.seq)
        cols = [reply(MsgType.COLUMN_RESULT, _column(7, c), 0) for c in range(3)]
        end = reply(MsgType.SCAN_END, {"frame": 7, "first_column": 0, "columns": 3,
                                       "calibration": 0, "reason": 0}, 0)
        return ack(f) + b"".join(cols) + end

    link = scripted_link(ScriptedPort(answer), retries=1)
    assert [c.column for c in link.scan(columns=3, frame=7)] == [0, 1, 2]
    assert len(starts) == 2 and starts[0].seq != starts[1].seq


def _column(frame: int, column: int) -> ColumnResult:
    from protocol_fixtures import expected_column

    app = SyntheticApp()
    cfg = app.get_config()
    return expected_column(frame, column, app.info().channels, int(cfg["peaks"]),
                           int(cfg["uid_bits"]))


def test_scan_start_refused_busy_stands_when_the_device_stays_busy() -> None:
    """The previous stream does not end within the reply timeout times the tries: the BUSY
    is the caller's error, and the host sends one SCAN_ABORT as it leaves (the stream that
    holds the device can only be its own previous one)."""
    busy = Status(state=1, frame=6, next_column=3)
    port = ScriptedPort(lambda f: reply(MsgType.STATUS, busy, f.seq)
                        if f.msg_type == MsgType.STATUS_GET else
                        reply(MsgType.NAK, {"request_type": int(f.msg_type),
                                            "code": int(ErrorCode.BUSY), "field": "",
                                            "detail": "a scan is running"}, f.seq))
    link = scripted_link(port, retries=1, timeout_s=0.2)
    with pytest.raises(DeviceError) as exc:
        next(link.scan(columns=3, frame=7))
    assert exc.value.code == ErrorCode.BUSY
    assert 0.4 <= port.clock.now < 0.6  # (retries + 1) x timeout_s on the fake clock, no more
    sent = [f.msg_type for f in port.requests]
    assert sent.count(MsgType.SCAN_START) == 1 and sent.count(MsgType.STATUS_GET) >= 2
    assert sent.count(MsgType.SCAN_ABORT) == 1
