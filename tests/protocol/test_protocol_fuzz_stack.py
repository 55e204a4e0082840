"""Fuzzing the whole stack, not just the decoder: CRC-valid frames with hostile contents.

Line noise rarely passes the CRC, but a buggy or foreign peer sends well-formed
frames of any type, seq, session and payload. Neither end may raise anything but
its own error family, or stop answering afterwards.
"""

from __future__ import annotations

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from protocol_fixtures import SteppedDevice, SyntheticApp, hello_fields

from cdma_lidar.errors import CdmaLidarError, FrameError
from cdma_lidar.protocol.endpoint import DeviceEndpoint, Engine
from cdma_lidar.protocol.framing import FrameDecoder, encode_frame
from cdma_lidar.protocol.link import HostLink
from cdma_lidar.protocol.messages import REPLY_TO, MsgType, Status, decode_payload, encode_payload
from cdma_lidar.virtual.line import pipe_pair

SESSION = 0xABCD
REQUESTS = sorted(int(t) for t in REPLY_TO)

hostile_requests = st.lists(st.tuples(
    st.one_of(st.sampled_from(REQUESTS), st.integers(0, 255)),  # msg_type
    st.integers(0, 0xFFFF),                                        # seq
    st.sampled_from([SESSION, 0, 0x5555]),                         # session
    st.binary(max_size=48),                                        # payload
    st.sampled_from([0, 0, 0x80]),                                 # incompat flags
), max_size=12)


def _drain(ep: DeviceEndpoint, port) -> None:
    for _ in range(100):
        ep.poll()
        if not port.in_waiting:
            break


@settings(max_examples=60, deadline=None)
@given(frames=hostile_requests, noise=st.binary(max_size=200))
def test_device_survives_hostile_frames_and_still_answers(frames: list, noise: bytes) -> None:
    host, dev = pipe_pair()
    host.timeout = 0.01
    app = SyntheticApp(channels=4, columns=16)
    # Threadless: each poll also handles the queued requests (no worker thread to wait for).
    ep = DeviceEndpoint(dev, app, session_id=SESSION, poll_s=0.0, engine=Engine(threaded=False),
                        heartbeat_s=10.0)
    try:
        wire = noise + b"".join(encode_frame(t, p, seq, sess, incompat=inc)
                                for t, seq, sess, p, inc in frames)
        host.write(wire)
        _drain(ep, dev)  # any exception escaping poll() fails the test
        # A new host: HELLO is always answered, then STATUS_GET in its session.
        dec = FrameDecoder()
        host.write(encode_frame(MsgType.HELLO, encode_payload(
            MsgType.HELLO, hello_fields(77, 65535)), 40000, 0))
        host.write(encode_frame(MsgType.STATUS_GET, b"", 40001, SESSION))
        got = []
        for _ in range(50):
            _drain(ep, dev)
            got += [f for f in dec.feed(host.read(max(1, host.in_waiting)))
                    if f.seq in (40000, 40001) and f.msg_type < 0xC0]
            if len(got) >= 2:
                break
        assert [f.msg_type for f in got] == [MsgType.INFO, MsgType.STATUS], got
        assert ep.stats.rx_requests >= 2
    finally:
        ep.close()


hostile_replies = st.lists(st.tuples(
    st.integers(0x80, 0xFF),                         # reply and stream types, known or not
    st.sampled_from(["pending", "other"]),           # seq: the pending request's or not
    st.sampled_from([0x1234, 0x4321]),               # session: right or wrong
    st.binary(max_size=60),
), max_size=10)


@settings(max_examples=40, deadline=None)
@given(frames=hostile_replies, other_seq=st.integers(0, 0xFFFF))
def test_host_raises_only_its_own_errors_on_hostile_frames(frames: list, other_seq: int) -> None:
    port = SteppedDevice(SyntheticApp(), session_id=0x1234, heartbeat_s=0.05)
    dev = port.endpoint.port
    with port:
        link = HostLink(port, timeout_s=0.05, retries=1, clock=port.clock)
        link.hello()
        pending = (link.seq + 1) & 0xFFFF  # the seq of the next request
        if other_seq in (pending, (pending + 1) & 0xFFFF):
            other_seq = (pending + 2) & 0xFFFF
        dev.write(b"".join(
            encode_frame(t, p, pending if which == "pending" else other_seq, sess)
            for t, which, sess, p in frames))
        try:
            st_ = link.status()
            assert isinstance(st_, Status)
        except CdmaLidarError:
            pass  # e.g. a well-formed but wrong reply to this seq: a clear LinkError
        # Whatever came before, the next request gets its real answer.
        assert link.status().state_name == "idle"


def test_hostile_stream_frames_during_a_scan_are_counted_not_raised() -> None:
    """Malformed COLUMN_RESULT / HEARTBEAT / unknown stream frames in the device's session,
    injected on the line while every column is computed (threadless, on the fake clock)."""
    app = SyntheticApp(channels=4, columns=30)
    port = SteppedDevice(app, session_id=0x1234, heartbeat_s=0.05)
    line = port.endpoint.port  # the device's end: what it writes, the host reads
    injected = [0]

    def inject() -> None:  # runs inside each column, before it goes out
        k = injected[0]
        for t, p in ((MsgType.COLUMN_RESULT, bytes(25)), (MsgType.HEARTBEAT, b"\x07"),
                     (0xEE, b"x"), (MsgType.SCAN_END, bytes(9))):
            line.write(encode_frame(int(t), p, k & 0xFFFF, 0x1234))
        injected[0] += 1

    app.tick = inject
    with port:
        link = HostLink(port, timeout_s=2.0, clock=port.clock)
        link.hello()
        cols = list(link.scan())
    assert injected[0] == 30
    assert [c.column for c in cols] == list(range(30))
    assert link.stats.malformed >= 3
    with pytest.raises(FrameError):  # the injected SCAN_END really was malformed
        decode_payload(MsgType.SCAN_END, bytes(9))
