"""The host's column reassembler on its own: fed by hand, timed by the ``now`` it is given."""

from __future__ import annotations

from protocol_fixtures import SyntheticApp, expected_column

from cdma_lidar.protocol.columns import encode_column
from cdma_lidar.protocol.framing import COMPAT_RETRANSMIT, Frame
from cdma_lidar.protocol.messages import MsgType, ScanEndReason, decode_payload, encode_payload
from cdma_lidar.protocol.reassembly import ColumnReassembler, StreamEnded
from cdma_lidar.protocol.requests import LinkStats
from cdma_lidar.protocol.trust import ColumnChecker

RESEND_S = 0.125


def _asm(first: int = 0, end: int = 6) -> ColumnReassembler:
    app = SyntheticApp(channels=4, columns=8)
    checker = ColumnChecker(app.info(), app.get_config(), False)
    return ColumnReassembler(9, first, end, checker, lambda tries: RESEND_S * 2 ** (tries - 1),
                             LinkStats())


def _col(c: int):
    return expected_column(9, c, 4, 1, 1)


def _frame(mtype: MsgType, item, again: bool = False) -> tuple[Frame, object]:
    """The stream frame carrying ``item`` (a column, a Status or a dict of fields), and its
    decoded payload (what the host's receive path queues for the reassembler)."""
    fields = item.to_fields() if hasattr(item, "to_fields") else item
    payload = encode_payload(mtype, fields)
    return Frame(mtype, 0, 1, payload, COMPAT_RETRANSMIT if again else 0), \
        decode_payload(mtype, payload)


def _pieces(c: int, count: int = 3) -> list[dict]:
    data = encode_column(_col(c))
    size = -(-len(data) // count)
    return [{"frame": 9, "column": c, "index": k, "count": count, "msg_type": 0xC0, "seq": 0,
             "data": data[k * size:(k + 1) * size]} for k in range(count)]


def test_columns_come_out_in_order_once_and_gaps_are_due_at_once_then_after_resend_s() -> None:
    asm = _asm()
    for c in (0, 2, 3):
        assert asm.feed(*_frame(MsgType.COLUMN_RESULT, _col(c)))
    assert [c.column for c in asm.ready()] == [0]
    assert asm.due(10.0) == [1]  # column 2 arrived: 1 was sent and lost
    asm.ask([1], 10.0)
    assert asm.due(10.0 + RESEND_S / 2) == []  # asked, not yet due again
    assert asm.due(10.0 + RESEND_S) == [1]
    assert asm.tries(1) == 1
    assert asm.feed(*_frame(MsgType.COLUMN_RESULT, _col(1), again=True))  # the repair asked for
    assert [c.column for c in asm.ready()] == [1, 2, 3]
    asm.feed(*_frame(MsgType.COLUMN_RESULT, _col(3)))
    assert asm.stats.duplicates == 1 and asm.stats.columns == 4  # delivered, once each


def test_a_missing_fragment_is_asked_for_alone_and_a_late_repair_is_not_taken() -> None:
    asm = _asm()
    p = _pieces(0)
    asm.feed(*_frame(MsgType.FRAGMENT, p[0]))
    asm.feed(*_frame(MsgType.FRAGMENT, p[2]))
    assert asm.due(0.0) == [(0, 1)]
    # Not asked for: an older scan's.
    assert not asm.feed(*_frame(MsgType.FRAGMENT, p[1], again=True))
    asm.ask([(0, 1)], 0.0)
    asm.feed(*_frame(MsgType.FRAGMENT, p[1], again=True))
    assert [c.column for c in asm.ready()] == [0]


def test_heartbeat_and_scan_end_show_what_was_sent_and_an_early_end_fails_after_delivery() -> None:
    from cdma_lidar.protocol.messages import Status

    asm = _asm()
    asm.feed(*_frame(MsgType.HEARTBEAT, Status(frame=9, next_column=2)))
    assert asm.due(0.0) == [0, 1]
    asm.feed(*_frame(MsgType.COLUMN_RESULT, _col(0)))
    asm.feed(*_frame(MsgType.SCAN_END, {"frame": 9, "first_column": 0, "columns": 1,
                                       "calibration": 0, "reason": int(ScanEndReason.ABORTED)}))
    assert [c.column for c in asm.ready()] == [0] and asm.done
    assert isinstance(asm.failure, StreamEnded) and asm.failure.next_column == 1


def test_progress_changes_only_when_something_of_the_stream_moves() -> None:
    asm = _asm()
    before = asm.progress
    asm.feed(*_frame(MsgType.HEARTBEAT, _status(9, 0)))
    assert asm.progress == before  # alive, but nothing moved
    asm.feed(*_frame(MsgType.FRAGMENT, _pieces(0)[0]))
    assert asm.progress != before


def _status(frame: int, nxt: int):
    from cdma_lidar.protocol.messages import Status
    return Status(frame=frame, next_column=nxt)


def test_a_joiner_drops_the_oldest_message_when_one_more_starts() -> None:
    """At most ``limit`` messages in pieces: the oldest unfinished one goes, the newer ones
    still complete, and the dropped one's last piece no longer does."""
    from cdma_lidar.protocol.reassembly import Joiner

    joiner = Joiner(limit=2)
    cols = {c: _pieces(c, 2) for c in (0, 1, 2)}
    for c in (0, 1, 2):  # column 2's first piece pushes column 0 out
        assert joiner.add(_frame(MsgType.FRAGMENT, cols[c][0])[0], cols[c][0]) is None
    for c in (1, 2):
        whole = joiner.add(_frame(MsgType.FRAGMENT, cols[c][1])[0], cols[c][1])
        assert whole is not None and decode_payload(MsgType.COLUMN_RESULT, whole[0].payload) \
            == _col(c)
    assert joiner.add(_frame(MsgType.FRAGMENT, cols[0][1])[0], cols[0][1]) is None


def test_a_piece_of_a_column_already_delivered_is_a_duplicate_and_is_not_kept() -> None:
    asm = _asm()
    asm.feed(*_frame(MsgType.COLUMN_RESULT, _col(0)))
    assert [c.column for c in asm.ready()] == [0]
    stored = asm.stored
    assert asm.feed(*_frame(MsgType.FRAGMENT, _pieces(0)[1]))  # of this stream: alive
    assert asm.stats.duplicates == 1 and asm.stored == stored
    assert not asm.joiner.held


def test_a_joined_column_that_does_not_decode_is_counted_malformed_and_asked_for_again() -> None:
    asm = _asm()
    data = encode_column(_col(0))[:-3]  # three bytes short of its records: does not decode
    half = len(data) // 2
    for k, part in enumerate((data[:half], data[half:])):
        asm.feed(*_frame(MsgType.FRAGMENT, {"frame": 9, "column": 0, "index": k, "count": 2,
                                            "msg_type": 0xC0, "seq": 0, "data": part}))
    assert asm.stats.malformed == 1 and list(asm.ready()) == []
    asm.feed(*_frame(MsgType.COLUMN_RESULT, _col(1)))  # column 0 was sent: its repair is due
    assert asm.due(0.0) == [0]


def test_a_retransmitted_frame_that_is_no_column_is_taken_as_any_other() -> None:
    """COMPAT_RETRANSMIT marks repairs; on a HEARTBEAT it says nothing about asking."""
    asm = _asm()
    assert asm.feed(*_frame(MsgType.HEARTBEAT, _status(9, 2), again=True))
    assert asm.stats.duplicates == 0 and asm.due(0.0) == [0, 1]
