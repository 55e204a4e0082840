"""Linear-time decoding and a device loop that never stalls (no clocks asserted)."""

from __future__ import annotations

import threading
import time
from collections.abc import Iterator

from hypothesis import given, settings
from hypothesis import strategies as st
from protocol_fixtures import RunningDevice, SyntheticApp, expected_column, hello_fields

from cdma_lidar.protocol.columns import ColumnResult
from cdma_lidar.protocol.framing import FRAME_LIMIT, Frame, FrameDecoder, encode_frame
from cdma_lidar.protocol.messages import MsgType, decode_payload, encode_payload
from cdma_lidar.virtual.line import pipe_pair


def _feed(data: bytes, size: int) -> FrameDecoder:
    dec = FrameDecoder(FRAME_LIMIT)
    for i in range(0, len(data), size):
        dec.feed(data[i:i + size])
    return dec


def test_the_receive_buffer_copies_each_byte_at_most_once_whatever_the_read_size() -> None:
    big = encode_frame(0xC0, bytes(range(1, 256)) * 250, 1, 2)  # one 64 KB frame
    for size in (1, 7, 1000, len(big)):
        dec = _feed(big, size)
        assert dec.stats.frames == 1
        assert dec.copied <= len(big), (size, dec.copied)  # was ~len^2 / (2 size)


@settings(max_examples=60, deadline=None)
@given(st.lists(st.binary(max_size=300), min_size=1, max_size=8), st.integers(1, 64))
def test_any_chunking_gives_the_same_frames_and_linear_copies(payloads, size) -> None:
    wire = b"".join(encode_frame(0xC1, p, k, 9) for k, p in enumerate(payloads))
    whole = FrameDecoder().feed(wire)
    dec = FrameDecoder()
    got: list[Frame] = []
    for i in range(0, len(wire), size):
        got += dec.feed(wire[i:i + size])
    assert got == whole and len(got) == len(payloads)
    assert dec.copied <= len(wire)


class BlockingApp(SyntheticApp):
    """Column 1 of every scan waits until the test releases it."""

    def __init__(self) -> None:
        super().__init__(channels=4, columns=8)
        self.release = threading.Event()
        self.inside = threading.Event()

    def _columns(self, frame: int, first: int, count: int,
                 calibration: bool) -> Iterator[ColumnResult]:
        for col in range(first, first + count):
            if col == 1:
                self.inside.set()
                self.release.wait(30)
            yield expected_column(frame, col, self.channels, self.config["peaks"],
                                  self.config["uid_bits"], calibration)


def test_requests_and_heartbeats_are_served_while_a_column_is_computed() -> None:
    """The spec's timing table: STATUS_GET, CONFIG_GET and heartbeats during a column
    that never finishes until the test says so (no clock is asserted: every answer
    must arrive while the application is still inside the column)."""
    host, dev = pipe_pair()
    app = BlockingApp()
    with RunningDevice(dev, app, heartbeat_s=0.2, session_id=0x5151):
        def send(t: MsgType, fields: dict, seq: int) -> None:
            host.write(encode_frame(t, encode_payload(t, fields), seq, 0x5151))

        dec = FrameDecoder()
        got: list[Frame] = []

        def wait_for(pred, limit_s: float = 20.0) -> Frame:
            deadline = time.monotonic() + limit_s
            while time.monotonic() < deadline:
                for f in got:
                    if pred(f):
                        return f
                got.extend(dec.feed(host.read(max(1, host.in_waiting))))
            raise AssertionError("no answer while the column was being computed")

        send(MsgType.HELLO, hello_fields(1), 1)
        wait_for(lambda f: f.msg_type == MsgType.INFO)
        send(MsgType.SCAN_START, {"frame": 4, "first_column": 0, "columns": 8}, 2)
        assert app.inside.wait(20)
        for seq, (t, reply) in enumerate([(MsgType.STATUS_GET, MsgType.STATUS),
                                          (MsgType.CONFIG_GET, MsgType.CONFIG),
                                          (MsgType.STATUS_GET, MsgType.STATUS),
                                          (MsgType.RESEND, MsgType.ACK)] * 3, start=3):
            fields = {"keys": []} if t == MsgType.CONFIG_GET else \
                {"frame": 4, "columns": [0], "fragments": []} if t == MsgType.RESEND else {}
            send(t, fields, seq)
            f = wait_for(lambda f, s=seq, r=reply: f.seq == s and f.msg_type == r)
            if reply == MsgType.STATUS:
                st = decode_payload(f.msg_type, f.payload)
                assert st["state"] == 1 and st["next_column"] == 1  # still in column 1
        beats = [f for f in got if f.msg_type == MsgType.HEARTBEAT]
        wait_for(lambda f: f.msg_type == MsgType.HEARTBEAT and f not in beats)
        assert not app.release.is_set() and app.inside.is_set()
        app.release.set()
        wait_for(lambda f: f.msg_type == MsgType.SCAN_END)
