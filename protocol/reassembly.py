"""Host side of what comes in pieces: FRAGMENTs joined by key, a stream's columns in order.

:class:`Joiner`: FRAGMENTs by key (docs/protocol.md section 6.3). :class:`ColumnReassembler`:
one scan or calibration stream (no port, no clock: the caller passes ``now``). ``edge`` =
(column, k): every column below it was sent whole, and its fragments below k (moved by a
later column or fragment, a HEARTBEAT's ``next_column``, SCAN_END's count). An early end
(SCAN_END aborted or error, a lying column) keeps the columns before it and sets ``failure``.
"""

from __future__ import annotations

import math
from collections import OrderedDict
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from typing import Any

from cdma_lidar.errors import DeviceError, FrameError
from cdma_lidar.protocol.columns import ColumnResult, decode_column
from cdma_lidar.protocol.framing import COMPAT_RETRANSMIT, Frame
from cdma_lidar.protocol.messages import ErrorCode, MsgType, ScanEndReason
from cdma_lidar.protocol.trust import ColumnChecker, DeviceLied

__all__ = ["ColumnReassembler", "Joiner", "Pieces", "StreamEnded", "early_end"]


class StreamEnded(DeviceError):
    """A scan or calibration (frame id ``frame``) ended before its last column; every
    column before ``next_column`` was delivered, none from it on. ``reason``: the
    device's ScanEndReason (ABORTED, ERROR; then ``code`` INTERNAL), None when the host
    gave up (``ScanStalled``)."""

    def __init__(self, message: str, *, frame: int, next_column: int,
                 reason: int | None, code: int = 0) -> None:
        super().__init__(message, code=code)
        self.frame, self.next_column, self.reason = frame, next_column, reason


def early_end(fid: int, reason: int, sent: int) -> StreamEnded:
    """The error of a stream the device ended after ``sent`` columns for ``reason``."""
    if reason == ScanEndReason.ERROR:
        return StreamEnded(f"device failed during frame {fid} after {sent} columns",
                           frame=fid, next_column=sent, reason=reason, code=ErrorCode.INTERNAL)
    return StreamEnded(f"frame {fid} was stopped on the device at column {sent}",
                       frame=fid, next_column=sent, reason=reason)


@dataclass
class Pieces:
    """FRAGMENTs of one message (a column, a reply, a notice, a request) received so far;
    ``checked``: every piece that came was (session, signature)."""

    count: int
    data: dict[int, bytes] = field(default_factory=dict)  # index -> the piece's data
    frames: list[Frame] = field(default_factory=list)  # the pieces as they came
    checked: bool = True


class Joiner:
    """FRAGMENTs of at most ``limit`` messages at once, each kept under its key (type,
    seq, frame, column; the device's requests: type, seq, session, so that no piece of
    another session joins); the oldest message is dropped when one more starts."""

    def __init__(self, limit: int = 64) -> None:
        self.limit = limit
        self.held: OrderedDict[tuple[int, ...], Pieces] = OrderedDict()

    def add(self, frame: Frame, body: dict[str, Any], key: tuple[int, ...] | None = None,
            checked: bool = True) -> tuple[Frame, list[Frame]] | None:
        """Keep one piece (``body``: the decoded FRAGMENT ``frame``, ``checked`` or not);
        the last one gives the whole message (type and seq from the pieces, their session,
        ``joined`` when every piece was checked) and its pieces."""
        key = key or (body["msg_type"], body["seq"], body["frame"], body["column"])
        pc = self.held.get(key)
        if pc is None or pc.count != body["count"]:  # the first piece, or of another cut
            pc = self.held[key] = Pieces(body["count"])
            while len(self.held) > self.limit:
                self.held.popitem(last=False)
        pc.checked = pc.checked and checked
        if body["index"] not in pc.data:
            pc.frames.append(frame)
        pc.data[body["index"]] = body["data"]
        if len(pc.data) < pc.count:
            return None
        del self.held[key]
        payload = b"".join(pc.data[i] for i in range(pc.count))
        return Frame(key[0], key[1], frame.session, payload, version=frame.version,
                     fec=frame.fec, joined=pc.checked), pc.frames


class ColumnReassembler:
    """Columns ``first .. end - 1`` of frame ``fid``, checked by ``checker``; their
    pieces joined in its own :class:`Joiner` (they go with the stream); a key asked for
    ``tries`` times is due again after ``resend_wait(tries)`` (s); ``stats`` (the link's
    LinkStats) counts ``duplicates``, ``malformed`` and the ``columns`` delivered."""

    def __init__(self, fid: int, first: int, end: int, checker: ColumnChecker,
                 resend_wait: Callable[[int], float], stats: Any) -> None:
        self.fid, self.first, self.end, self.checker = fid, first, end, checker
        self.resend_wait, self.stats = resend_wait, stats
        self.joiner = Joiner()
        self.nxt = first  # next column to deliver
        self.edge = (first, 0)  # (column, fragment) the device sent up to
        self.received: dict[int, ColumnResult] = {}
        self.asked: dict[Any, tuple[float, int]] = {}  # key -> (last asked, tries)
        self.stored = 0  # columns and fragments kept (progress)
        self.failure: Exception | None = None

    @property
    def done(self) -> bool:
        """Every column up to the end (or an early end) was delivered."""
        return self.nxt >= self.end

    @property
    def progress(self) -> tuple:
        """Changes whenever anything of the stream moves."""
        return (self.nxt, self.edge, self.stored)

    def _stop(self, column: int, exc: Exception) -> None:
        if self.failure is None:
            self.end, self.failure = column, exc

    def sent(self, count: int, idle_reason: int | None = None) -> None:
        """The device sent columns below ``count``; ``idle_reason``: it is idle (a STATUS
        probe), the stream ended for that reason."""
        sent = min(self.end, count)
        self.edge = max(self.edge, (sent, 0))
        if idle_reason is not None and sent < self.end:
            self._stop(sent, early_end(self.fid, idle_reason, sent))

    def feed(self, frame: Frame, item: Any) -> bool:
        """One COLUMN_RESULT, FRAGMENT, HEARTBEAT or SCAN_END and its decoded payload
        ``item``; True when of this stream (a sign of life)."""
        mtype = frame.msg_type
        if frame.compat & COMPAT_RETRANSMIT and not self._asked_for(item):
            self.stats.duplicates += 1  # a repair this stream did not ask for: a late one
            return False
        if mtype == MsgType.FRAGMENT:
            return item["frame"] == self.fid and self._piece(frame, item)
        if mtype == MsgType.COLUMN_RESULT:
            return self._column(item)
        if mtype == MsgType.HEARTBEAT and item["frame"] == self.fid:
            self.sent(item["next_column"])
            return True
        if mtype == MsgType.SCAN_END and item["frame"] == self.fid:
            sent = min(self.end, item["first_column"] + item["columns"])
            self.sent(sent)
            if item["reason"] != ScanEndReason.COMPLETE:
                self._stop(sent, early_end(self.fid, item["reason"], sent))
            return True
        return False

    def _piece(self, frame: Frame, item: dict[str, Any]) -> bool:
        c, k = item["column"], item["index"]
        self.asked.pop((c, k), None)
        self.edge = max(self.edge, (c, k + 1))
        if not self.nxt <= c < self.end or c in self.received:
            self.stats.duplicates += 1
            return True
        self.stored += 1
        if (whole := self.joiner.add(frame, item)) is not None:
            try:
                self._column(decode_column(whole[0].payload))
            except FrameError:
                self.stats.malformed += 1
        return True

    def _column(self, c: ColumnResult) -> bool:
        if c.frame != self.fid or not self.nxt <= c.column < self.end or \
                c.column in self.received:
            self.stats.duplicates += 1
            return c.frame == self.fid
        try:
            self.checker.check(c)
        except DeviceLied as exc:  # deliver the columns before it, then fail
            self._stop(c.column, exc)
            return True
        self.asked.pop(c.column, None)
        self.received[c.column] = c
        self.stored += 1
        self.joiner.held.pop((MsgType.COLUMN_RESULT, 0, self.fid, c.column), None)
        self.edge = max(self.edge, (c.column + 1, 0))
        return True

    def _asked_for(self, item: Any) -> bool:
        if isinstance(item, ColumnResult):
            return item.column in self.asked
        if isinstance(item, dict) and "index" in item:
            return item["column"] in self.asked or (item["column"], item["index"]) in self.asked
        return True

    def ready(self) -> Iterator[ColumnResult]:
        """The columns complete in order from the next one to deliver, each once."""
        while self.nxt in self.received:
            self.stats.columns += 1
            yield self.received.pop(self.nxt)
            self.nxt += 1

    def _waiting(self, key: Any, now: float) -> bool:
        """``key`` was asked for and its answer may still come."""
        at, tries = self.asked.get(key, (-math.inf, 1))  # never asked: not waiting
        return now - at < self.resend_wait(tries)

    def due(self, now: float) -> list[Any]:
        """Columns (int) and fragments ((column, index)) sent, missing and due to be asked
        for (the search stops once 255 are found)."""
        col, sent_k = self.edge  # columns below col sent whole, its fragments below sent_k
        due: list[Any] = []
        for c in range(self.nxt, min(self.end, col + 1)):
            if c in self.received or self._waiting(c, now):  # asked whole: pieces coming
                continue
            if (pc := self.joiner.held.get((MsgType.COLUMN_RESULT, 0, self.fid, c))) is None:
                keys: list[Any] = [c] if c < col else []  # else: nothing sent yet
            else:
                sent = pc.count if c < col else min(pc.count, sent_k)
                keys = [(c, k) for k in range(sent) if k not in pc.data]
            due += [k for k in keys if not self._waiting(k, now)]
            if len(due) >= 255:
                break
        return due

    def tries(self, key: Any) -> int:
        """How often ``key`` (of :meth:`due`) was asked for."""
        return self.asked.get(key, (0.0, 0))[1]

    def ask(self, keys: list[Any], now: float) -> None:
        """``keys`` were asked for at ``now`` (s)."""
        for key in keys:
            self.asked[key] = (now, self.tries(key) + 1)
