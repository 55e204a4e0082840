"""Device transmit queue: three priority classes, FRAGMENTs, signing at send time.

Frames of one connection wait first-in first-out in three classes, sent in this order
(docs/protocol.md section 6.2, transmit order): replies and notices (:data:`CONTROL`),
retransmitted columns (:data:`REPAIR`), new columns and SCAN_END (:data:`FRESH`). Frames
are encoded and signed as they leave, so signature counters rise in wire order. The
connection's loop is the only writer.
"""

from __future__ import annotations

import logging
from collections import OrderedDict
from collections.abc import Callable, Iterable
from functools import partial
from typing import Any

from cdma_lidar.errors import FieldError
from cdma_lidar.protocol.auth import FrameMac
from cdma_lidar.protocol.framing import (
    COMPAT_RETRANSMIT,
    PROTOCOL_VERSION,
    Frame,
    encode_frame,
    frame_size,
)
from cdma_lidar.protocol.messages import (
    MAX_PIECES,
    ErrorCode,
    MsgType,
    encode_payload,
    piece_room,
    split_message,
    type_name,
)

__all__ = ["CONTROL", "FRESH", "MAX_PIECES", "REPAIR", "Reply", "Transmitter",
           "clip"]

log = logging.getLogger(__name__)

#: Transmit classes, sent in this order.
CONTROL, REPAIR, FRESH = 0, 1, 2
_SESSION = object()  # "the session's signer", resolved when queued
#: A reply as cached for replay: (type, payload, signed); signed afresh each time sent.
Reply = tuple[MsgType, bytes, bool]


def clip(s: str, limit: int = 255) -> str:
    """``s`` cut to at most ``limit`` UTF-8 bytes, on a character boundary."""
    return s.encode("utf-8")[:limit].decode("utf-8", errors="ignore")


class Transmitter:
    """The transmit side of one connection.

    ``session``, ``max_frame`` (largest frame sent, bytes), ``signer`` and ``coded`` are the
    current session's; a frame takes them when queued. ``counters``: objects whose
    ``tx_frames`` count frames written and ``columns_sent`` COLUMN_RESULTs queued (new or
    resent); the first (the connection's) also counts in ``naks`` the NAKs of :meth:`nak`.
    """

    def __init__(self, port: Any, max_frame: int, counters: Iterable[Any]) -> None:
        self.port, self.session, self.max_frame = port, 0, max_frame
        self.signer: FrameMac | None = None
        self.coded = False
        self.counters = tuple(counters)
        #: Per class, first in first out: a REPAIR frame's (frame, column, fragment or -1), any
        #: other's object() -> (type, seq (None: the next stream seq), its encoder given seq).
        self._q: tuple[OrderedDict[Any, tuple[MsgType, int | None, Callable[..., bytes]]], ...] \
            = (OrderedDict(), OrderedDict(), OrderedDict())
        self._stream_seq = 0
        self._notice_id = 0  # FRAGMENT.seq of notices sent in pieces

    def reply(self, req: Frame, msg_type: MsgType, payload: bytes, fld: str = "",
              detail: str = "") -> Reply:
        """A reply, signed when the session and the request are; NAK TOO_LARGE naming
        ``fld`` (``detail``: what to ask instead) when it needs too many FRAGMENTs."""
        if not self.fits(len(payload)):
            return self.nak(req, ErrorCode.TOO_LARGE, fld, detail)
        return (msg_type, payload, self.signer is not None and (bool(req.sig) or req.joined))

    def ack(self, req: Frame) -> Reply:
        return self.reply(req, MsgType.ACK, encode_payload(MsgType.ACK,
                                                           {"request_type": req.msg_type}))

    def nak(self, req: Frame, code: ErrorCode, fld: str = "", detail: str = "",
            signed: bool | None = None) -> Reply:
        """NAK ``code`` naming field ``fld`` (both texts clipped to 255 UTF-8 bytes)."""
        self.counters[0].naks += 1
        log.debug("NAK %s seq %d: %s %s %s", req.msg_type, req.seq, code.name, fld, detail)
        payload = encode_payload(MsgType.NAK, {"request_type": req.msg_type, "code": int(code),
                                               "field": clip(fld), "detail": clip(detail)})
        return self.reply(req, MsgType.NAK, payload) if signed is None else \
            (MsgType.NAK, payload, signed)

    def answer(self, req: Frame, reply: Reply, signer: FrameMac | None = None) -> None:
        """Queue ``reply`` to ``req`` (class CONTROL, its seq and version), coded if the
        session or the request is, signed if the reply is (by ``signer`` or the session's)."""
        self.send(CONTROL, reply[0], reply[1], req.seq, coded=req.fec,
                  signer=(signer or self.signer) if reply[2] else None, version=req.version)

    def flush(self, budget: int | None = None) -> None:
        """Send the queued frames, highest class first; ``budget``: stop after about this
        many bytes above CONTROL (replies and notices all go), so the loop reads between
        a stream's frames."""
        sent = 0
        for cls, queue in enumerate(self._q):  # nothing is queued meanwhile: one loop
            while queue:
                if cls > CONTROL and budget is not None and sent >= budget:
                    return
                msg_type, seq, encode = queue.popitem(last=False)[1]
                if seq is None:
                    self._stream_seq = seq = (self._stream_seq + 1) & 0xFFFF
                try:
                    wire = encode(seq=seq)
                except FieldError:  # a bug must not take the device off the line
                    log.exception("cannot send a %s frame", type_name(msg_type))
                    continue
                self.port.write(wire)
                for c in self.counters:
                    c.tx_frames += 1
                sent += len(wire) if cls > CONTROL else 0

    def pending(self, cls: int | None = None) -> bool:
        """Frames of class ``cls`` (None: of any) wait to be sent."""
        return any(self._q) if cls is None else bool(self._q[cls])

    def fresh_pending(self) -> int:
        """1 while frames of a new column wait (that column is not sent yet), else 0."""
        return int(any(j[0] != MsgType.SCAN_END for j in self._q[FRESH].values()))

    def drop(self, cls: int) -> None:
        """Forget the queued frames of one class (an ended stream's new columns)."""
        self._q[cls].clear()

    def fits(self, payload_len: int) -> bool:
        """A payload (bytes) of this session goes whole or in at most MAX_PIECES FRAGMENTs."""
        return payload_len <= MAX_PIECES * piece_room(self.max_frame, self.signer is not None)

    def send(self, cls: int, msg_type: MsgType, payload: bytes, seq: int | None = None, *,
             key: tuple[int, int] = (0, 0), signer: Any = _SESSION, coded: bool = False,
             only: Iterable[int] | None = None, version: int = PROTOCOL_VERSION) -> None:
        """Queue one message of class ``cls`` (REPAIR frames marked retransmitted), whole or
        in FRAGMENTs of the max frame (the indexes in ``only``; all when it is None or names
        one out of range, as -1); ``signer`` defaults to the session's; coded when the
        session is or ``coded``.

        ``seq``: a reply's (the request's); None: a stream frame's (whole: the next stream
        seq; in pieces: a counter of fragmented notices, 0 for a COLUMN_RESULT, whose
        FRAGMENTs name ``key`` = (frame, column)). A REPAIR frame (frame, column, fragment
        or -1) already queued is not queued again: a host that asks again before the first
        answer reached it costs the line nothing. ``version``: another only for NAK VERSION
        to an older host.
        """
        if msg_type == MsgType.COLUMN_RESULT:
            for c in self.counters:
                c.columns_sent += 1
        signer = self.signer if signer is _SESSION else signer
        frames = [(msg_type, payload, seq, -1)]
        if frame_size(len(payload), signer is not None) > self.max_frame:
            if seq is None and msg_type != MsgType.COLUMN_RESULT:
                self._notice_id = seq = (self._notice_id + 1) & 0xFFFF
            room = piece_room(self.max_frame, signer is not None)
            pieces = split_message(msg_type, payload, room, seq or 0, key)
            if only is None or not all(0 <= k < len(pieces) for k in only):
                only = range(len(pieces))
            frames = [(MsgType.FRAGMENT, pieces[k], None, k) for k in only]
        for mtype, data, fseq, k in frames:
            self._q[cls].setdefault((*key, k) if cls == REPAIR else object(), (mtype, fseq, partial(
                encode_frame, mtype, data, session=self.session, max_frame=self.max_frame,
                compat=COMPAT_RETRANSMIT if cls == REPAIR else 0, version=version,
                signer=signer, coded=self.coded or coded)))
