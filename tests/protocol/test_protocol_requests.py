"""The host's waits on its injected clock: retries, RESEND pacing, the silence probe.

A device played by the test (:class:`protocol_fixtures.ScriptedPort`) answers in the
host's own thread; time moves only while the host waits, by its poll. So these tests
state when the host acts to the poll, on any machine, without a real thread or timer.
"""

from __future__ import annotations

import numpy as np
import pytest
from protocol_fixtures import ScriptedPort, ack, expected_column, reply, scripted_link

from cdma_lidar.errors import DeviceError, LinkTimeout
from cdma_lidar.protocol.framing import Frame
from cdma_lidar.protocol.messages import ErrorCode, MsgType, Status, decode_payload
from cdma_lidar.protocol.requests import DIAG_NO_ANSWER, DIAG_SILENT


def _times(port: ScriptedPort, msg_type: MsgType) -> list[float]:
    return [t for t, f in port.log if f.msg_type == msg_type]


def _logged(answer=None, idle=None) -> ScriptedPort:
    """A ScriptedPort that also logs (clock, frame) of every request in ``log``."""
    def log_and_answer(frame: Frame) -> bytes:
        port.log.append((port.clock(), frame))
        return answer(frame) if answer else b""

    port = ScriptedPort(log_and_answer, idle)
    port.log = []
    return port


@pytest.mark.parametrize(("timeout_s", "retries"), [(0.5, 3), (0.2, 0), (2.0, 1)])
def test_a_request_goes_again_after_each_timeout_and_not_sooner(timeout_s, retries) -> None:
    port = _logged()
    link = scripted_link(port, timeout_s=timeout_s, retries=retries)
    with pytest.raises(LinkTimeout) as exc:
        link.status()
    assert exc.value.diagnosis == DIAG_SILENT
    sent = _times(port, MsgType.STATUS_GET)
    assert len(sent) == retries + 1 and link.stats.retries == retries
    poll = port.timeout
    assert all(timeout_s - 1e-9 <= g <= timeout_s + poll + 1e-9 for g in np.diff(sent))
    assert port.clock() - sent[-1] >= timeout_s - 1e-9  # the last try waited its timeout too


def test_a_reply_just_before_the_deadline_is_taken_without_a_retry() -> None:
    asked: list[Frame] = []

    def idle(now: float) -> bytes:  # answers 0.45 s after the request, of a 0.5 s timeout
        if asked and now - port.log[0][0] >= 0.45:
            req = asked.pop()
            return reply(MsgType.STATUS, Status(uptime_ms=7), req.seq)
        return b""

    port = _logged(lambda f: asked.append(f) or b"", idle)
    link = scripted_link(port, timeout_s=0.5, retries=2)
    assert link.status().uptime_ms == 7
    assert link.stats.retries == 0 and len(port.log) == 1


def test_a_lost_column_is_asked_for_again_after_a_round_trip_doubling_per_try() -> None:
    """Columns 0 and 2 arrive, 1 never does: RESENDs a measured round trip apart (at least
    MIN_TIMEOUT_S), twice as long after each try up to a quarter timeout, then a
    LinkTimeout naming column 1; SCAN_ABORT goes out as the scan is left."""
    def answer(req: Frame) -> bytes:
        if req.msg_type != MsgType.SCAN_START:
            return b""
        return ack(req) + b"".join(reply(MsgType.COLUMN_RESULT, expected_column(5, c, 8, 1, 1),
                                         0) for c in (0, 2))

    port = _logged(answer)
    link = scripted_link(port, timeout_s=1.6, retries=1, column_retries=5)
    got = []
    with pytest.raises(LinkTimeout) as exc:
        for c in link.scan(columns=3, frame=5):
            got.append(c.column)
    assert got == [0] and "column 1 of frame 5" in str(exc.value)
    assert exc.value.diagnosis == DIAG_NO_ANSWER
    resends = [f for _, f in port.log if f.msg_type == MsgType.RESEND]
    assert len(resends) == 5
    assert all(decode_payload(MsgType.RESEND, f.payload)["columns"] == [1] for f in resends)
    gaps = np.diff(_times(port, MsgType.RESEND))
    # The ACK came at once: the wait is its floor, 20 ms, then 40, 80, 160 ms (not the
    # quarter timeout, 0.4 s), each as the host's poll (port.timeout) sees it.
    want = [0.02, 0.04, 0.08, 0.16]
    assert all(w - 1e-9 <= g <= w + port.timeout + 1e-9
               for g, w in zip(gaps, want, strict=True)), gaps
    assert _times(port, MsgType.SCAN_ABORT)  # leaving the scan stops it on the device


def test_a_silent_stream_is_probed_with_status_after_one_timeout() -> None:
    """Nothing at all after the ACK: STATUS_GET goes out one timeout later (no RESEND:
    nothing was shown sent), and says the scan went on to column 3 of 3."""
    def answer(req: Frame) -> bytes:
        if req.msg_type == MsgType.STATUS_GET:
            st = Status(state=0, frame=5, next_column=3, last_end=1)
            return reply(MsgType.STATUS, st, req.seq)
        if req.msg_type == MsgType.RESEND:  # the repairs, once the probe showed them sent
            cols = decode_payload(MsgType.RESEND, req.payload)["columns"]
            return b"".join(reply(MsgType.COLUMN_RESULT, expected_column(5, c, 8, 1, 1), 0)
                            for c in cols)
        return ack(req)

    port = _logged(answer)
    link = scripted_link(port, timeout_s=0.4, retries=1)
    cols = list(link.scan(columns=3, frame=5))
    assert [c.column for c in cols] == [0, 1, 2]
    start, probe = _times(port, MsgType.SCAN_START)[0], _times(port, MsgType.STATUS_GET)[0]
    assert 0.4 - 1e-9 <= probe - start <= 0.4 + port.timeout + 1e-9


def test_a_new_stream_of_the_same_frame_id_joins_none_of_the_last_ones_pieces() -> None:
    """Scan 1 of frame 5 ends (aborted) with half of column 0 held; scan 2 of frame 5, with
    two peaks a column, sends the other half first: it must not complete the old half."""
    from cdma_lidar.protocol.columns import encode_column
    from cdma_lidar.protocol.framing import encode_frame
    from cdma_lidar.protocol.messages import ScanEndReason, split_message
    from cdma_lidar.protocol.reassembly import StreamEnded

    def pieces(peaks: int) -> list[bytes]:
        data = encode_column(expected_column(5, 0, 8, peaks, 1))
        return [encode_frame(MsgType.FRAGMENT, p, 0, 0x42) for p in
                split_message(MsgType.COLUMN_RESULT, data, len(data) // 2 + 1, 0, (5, 0))]

    def end(reason: ScanEndReason, columns: int) -> bytes:
        return reply(MsgType.SCAN_END, {"frame": 5, "first_column": 0, "columns": columns,
                                        "calibration": 0, "reason": int(reason)}, 0)

    scans = iter([pieces(1)[0] + end(ScanEndReason.ABORTED, 0),
                  pieces(2)[1] + pieces(2)[0] + end(ScanEndReason.COMPLETE, 1)])
    port = ScriptedPort(lambda req: ack(req) + next(scans)
                        if req.msg_type == MsgType.SCAN_START else ack(req))
    link = scripted_link(port, timeout_s=0.4)
    with pytest.raises(StreamEnded):
        list(link.scan(columns=1, frame=5))
    link.config = {**link.config, "peaks": 2}
    assert list(link.scan(columns=1, frame=5)) == [expected_column(5, 0, 8, 2, 1)]
    assert link.stats.malformed == 0


@pytest.mark.parametrize(("code", "named"), [(ErrorCode.BUSY, "BUSY"), (999, "error 999")])
def test_a_nak_names_its_code_and_a_code_the_host_does_not_know_by_its_number(code,
                                                                           named) -> None:
    def answer(req: Frame) -> bytes:
        return reply(MsgType.NAK, {"request_type": req.msg_type, "code": code,
                                   "field": "x", "detail": "d"}, req.seq)

    link = scripted_link(ScriptedPort(answer))
    with pytest.raises(DeviceError) as exc:
        link.status()
    assert exc.value.code == code
    assert str(exc.value) == f"device refused STATUS_GET: {named} (field x): d"
