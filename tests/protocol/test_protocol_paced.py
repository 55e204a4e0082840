"""A line with a UART's pace: the pipe keeps it, the device sends replies and repairs
first, the host repairs without waiting for RESEND's ACK.

No test here asserts a duration: the paced pipe is checked by what can and cannot
have arrived yet (at 1000 baud ten bytes take 100 ms), and the device's priorities by
the order of the frames it writes.
"""

from __future__ import annotations

import threading
from collections import deque

import pytest
from protocol_fixtures import RunningDevice, SyntheticApp, expected_column

from cdma_lidar.errors import ConfigError, DeviceError
from cdma_lidar.protocol import auth
from cdma_lidar.protocol.columns import encode_column
from cdma_lidar.protocol.endpoint import DeviceEndpoint
from cdma_lidar.protocol.framing import COMPAT_RETRANSMIT, FrameDecoder
from cdma_lidar.protocol.link import HostLink
from cdma_lidar.protocol.messages import ErrorCode, MsgType, decode_payload, encode_payload
from cdma_lidar.protocol.transmit import CONTROL, FRESH, REPAIR
from cdma_lidar.virtual.line import BytePipe, Faults, pipe_pair


# ---- the paced pipe ---------------------------------------------------------------------------
def test_paced_pipe_holds_bytes_for_their_time_on_the_line() -> None:
    pipe = BytePipe(baud=1000)  # 100 bytes/s: 10 bytes take 100 ms
    pipe.write(b"0123456789")
    assert pipe.read(10, 0) == b""  # still on the line
    assert pipe.read(10, 5.0) == b"0123456789"  # all of it, in order, once it arrived


def test_paced_writer_waits_while_the_driver_buffer_is_full() -> None:
    pipe = BytePipe(baud=100, tx_buffer=4)
    pipe.write(b"abcd")  # fills the buffer: returns at once
    done = threading.Event()
    threading.Thread(target=lambda: (pipe.write(b"efgh"), done.set()), daemon=True).start()
    # 4 bytes are 0.4 s on the line (long enough that a loaded machine's scheduling delay
    # cannot drain them first): the writer still waits
    assert not done.wait(0.01)
    assert pipe.read(8, 5.0) == b"abcdefgh"
    assert done.wait(5.0)


@pytest.mark.parametrize(("kw", "field"), [({"baud": 0}, "baud"), ({"baud": 1.5}, "baud"),
                                            ({"tx_buffer": 0}, "tx_buffer")])
def test_paced_pipe_refuses_bad_settings(kw, field) -> None:
    with pytest.raises(ConfigError) as exc:
        BytePipe(**kw)
    assert exc.value.field == field


# ---- device: the transmit queue ---------------------------------------------------------------
class _Recorder:
    """Port that keeps what the device writes."""

    def __init__(self) -> None:
        self.timeout = 0.01
        self.out = bytearray()

    def write(self, data: bytes) -> int:
        self.out += data
        return len(data)

    def frames(self, max_frame: int = 65535):
        return FrameDecoder(max_frame).feed(bytes(self.out))

    def lengths(self) -> list[int]:
        """Bytes of each frame on the wire (COBS and both delimiters)."""
        return [len(c) + 2 for c in bytes(self.out).split(b"\0") if c]


def _device(max_frame: int = 256, key: bytes | None = None) -> tuple[DeviceEndpoint, _Recorder]:
    port = _Recorder()
    ep = DeviceEndpoint(port, SyntheticApp(channels=40, columns=4), max_frame=max_frame, key=key)
    ep.session.open = True
    return ep, port


_NOTICE = encode_payload(MsgType.LINE_ERROR, {"rx_errors": 1})


def _column(frame: int, column: int) -> bytes:
    return encode_column(expected_column(frame, column, 40, 1, 1))


def test_replies_then_repairs_then_new_columns_in_signature_order() -> None:
    ep, port = _device(key=bytes(range(32)))
    ep.tx.signer = auth.FrameMac(bytes(32))
    verifier = auth.FrameMac(bytes(32))
    ep.tx.send(FRESH, MsgType.COLUMN_RESULT, _column(1, 0), key=(1, 0))  # several fragments
    ep.tx.send(REPAIR, MsgType.COLUMN_RESULT, _column(1, 9), key=(1, 9))  # a repair
    ep.tx.send(CONTROL, MsgType.LINE_ERROR, _NOTICE)  # a notice, queued last
    ep.tx.flush()
    frames = list(port.frames())
    kinds = [("notice" if f.msg_type == MsgType.LINE_ERROR else
              "repair" if f.compat & COMPAT_RETRANSMIT else "new") for f in frames]
    n = kinds.count("new")
    assert n > 1 and kinds == ["notice"] + ["repair"] * n + ["new"] * n
    assert all(verifier.check(f) for f in frames)  # counters rise in wire order


def test_the_loop_sends_a_bounded_share_of_repairs() -> None:
    ep, port = _device()
    for c in range(10):
        ep.tx.send(REPAIR, MsgType.COLUMN_RESULT, _column(1, c), key=(1, c))
    ep.tx.send(CONTROL, MsgType.LINE_ERROR, _NOTICE)
    ep.tx.flush(budget=1000)
    sent = list(port.frames())
    assert sent[0].msg_type == MsgType.LINE_ERROR
    assert 1 < len(sent) < 1 + 80  # some repairs, not all 80 fragments
    ep.tx.flush()
    assert len(list(port.frames())) == 1 + 80


def test_a_repair_already_queued_is_not_queued_twice() -> None:
    ep, port = _device()
    ep.streams.ring[(1, 2)] = _column(1, 2)
    ep.tx.send(FRESH, MsgType.COLUMN_RESULT, _column(1, 2), key=(1, 2))  # first cut: 8 fragments
    ep.tx.flush()
    port.out.clear()
    for _ in range(3):  # the host asked three times before the first answer reached it
        ep.tx.send(REPAIR, MsgType.COLUMN_RESULT, _column(1, 2), key=(1, 2), only=[3, 5])
    ep.tx.flush()
    got = [decode_payload(f.msg_type, f.payload)["index"] for f in port.frames()]
    assert got == [3, 5]
    ep.tx.send(REPAIR, MsgType.COLUMN_RESULT, _column(1, 2), key=(1, 2), only=[3])  # sent: again
    ep.tx.flush()
    assert len(list(port.frames())) == 3


def test_a_piece_asked_by_index_is_the_piece_first_sent() -> None:
    """A session's frame size is fixed, so a piece asked for again is cut as before; an
    index that is no piece of the column gets the whole column again."""
    ep, port = _device(max_frame=256)
    payload = _column(1, 0)
    ep.tx.send(FRESH, MsgType.COLUMN_RESULT, payload, key=(1, 0))
    ep.tx.flush()
    first = {b["index"]: b for b in (decode_payload(f.msg_type, f.payload)
                                     for f in port.frames())}
    port.out.clear()
    ep.tx.send(REPAIR, MsgType.COLUMN_RESULT, payload, key=(1, 0), only=[2])
    ep.tx.flush()
    (again,) = [decode_payload(f.msg_type, f.payload) for f in port.frames()]
    assert (again["index"], again["count"], again["data"]) == \
        (2, first[2]["count"], first[2]["data"])
    port.out.clear()
    ep.tx.send(REPAIR, MsgType.COLUMN_RESULT, payload, key=(1, 0), only=[len(first)])
    ep.tx.flush()
    assert sorted(decode_payload(f.msg_type, f.payload)["index"] for f in port.frames()) == \
        sorted(first)


def test_a_frame_that_cannot_be_encoded_is_dropped_not_fatal(caplog) -> None:
    ep, port = _device()
    ep.tx.send(CONTROL, MsgType.LINE_ERROR, _NOTICE, seq=0x10000)  # seq is a u16
    ep.tx.send(CONTROL, MsgType.LINE_ERROR, _NOTICE)
    ep.tx.flush()
    assert [f.msg_type for f in port.frames()] == [MsgType.LINE_ERROR]
    assert "cannot send" in caplog.text


def test_heartbeat_counts_a_queued_column_as_not_sent() -> None:
    ep, _port = _device()
    ep.streams.stream = ep.streams.latest = type(
        "S", (), {"next_column": 5, "frame": 1, "calibration": False})()
    assert ep.status().next_column == 5
    ep.tx.send(FRESH, MsgType.COLUMN_RESULT, _column(1, 4), key=(1, 4))  # waits in the queue
    assert ep.status().next_column == 4
    ep.streams.stream = None


# ---- host: unawaited RESEND -----------------------------------------------------------
def test_a_refused_resend_fails_the_scan_with_the_device_reason() -> None:
    """The host does not wait for RESEND's ACK, but a NAK still reaches the caller."""
    host, dev = pipe_pair()
    app = SyntheticApp(channels=4, columns=6)
    with RunningDevice(dev, app, ring_columns=0):
        link = HostLink(host, timeout_s=2.0)  # then 100 reads of 0.05 s at most for the NAK
        link.hello()
        link.get_config()
        link.stream = deque()
        link.send_unawaited(MsgType.RESEND, {"frame": 77, "columns": [3], "fragments": []})
        with pytest.raises(DeviceError) as exc:
            for _ in range(100):
                link.pump()  # raises the NAK when it reads it
        assert exc.value.code == ErrorCode.NOT_AVAILABLE
        link.end_stream()
        link.close()


@pytest.mark.parametrize("ber", [3e-4, 1e-3])
def test_scan_on_a_paced_noisy_line_is_byte_identical(ber: float) -> None:
    """A UART at 4 Mbaud with bit errors both ways: every column arrives intact, once."""
    f = Faults(bit_error_rate=ber)
    host, dev = pipe_pair(f, f, seed=11, baud=4_000_000)
    app = SyntheticApp(channels=40, columns=30)
    with RunningDevice(dev, app, heartbeat_s=0.2):
        link = HostLink(host, timeout_s=2.0, retries=20, fec=True)
        link.hello()
        assert link.coded  # Reed-Solomon coded frames
        cols = list(link.scan(frame=3))
        link.close()
    assert [encode_column(c) for c in cols] == \
        [encode_column(expected_column(3, c, 40, 1, 1)) for c in range(30)]
    assert link.decoder.stats.corrected > 0


def test_status_overtakes_the_column_stream_on_a_slow_line() -> None:
    """At 921600 baud a column is 18 ms on the wire; STATUS must not wait for the scan.

    Real threads on a paced line, so counted loosely: the answer comes while the device
    still scans, with fewer stream frames before it than 2 s of the line carries (the
    exact order, reply before queued columns, is checked frame by frame by
    test_replies_then_repairs_then_new_columns_in_signature_order).
    """
    host, dev = pipe_pair(baud=921_600)
    app = SyntheticApp(channels=40, columns=140)  # 2.5 s on the wire
    with RunningDevice(dev, app, heartbeat_s=0.5):
        link = HostLink(host, timeout_s=2.0)
        link.hello()
        scan = link.scan(frame=6)
        first = [next(scan) for _ in range(3)]
        before = len(link.stream)
        status = link.status()
        between = len(link.stream) - before
        rest = list(scan)
        link.close()
    assert status.state_name == "scanning" and status.frame == 6
    assert between < 110, f"{between} stream frames arrived before the STATUS reply"
    assert [c.column for c in first + rest] == list(range(140))
