"""Host requests: send one, wait for its reply on an injected clock, send it again; route
every frame the device sends.

:class:`Requests` owns the port, the receive buffer (a
:class:`~cdma_lidar.protocol.framing.FrameDecoder`) and the request counter ``seq``. It
only ever blocks in ``port.read`` (at most ``port.timeout``) and measures every wait on
``clock``, so a test drives it with a fake port whose reads move a fake clock.
Retransmission follows docs/protocol.md section 6.1; a :class:`LinkTimeout` after the
last try carries a ``DIAG_*`` diagnosis (section 6.7) and ends with its
:data:`DIAG_HINTS`. Frames of a running stream go, undecoded, to the ``stream`` queue
for :class:`~cdma_lidar.protocol.reassembly.ColumnReassembler`.
"""

from __future__ import annotations

import logging
from collections import OrderedDict, deque
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from cdma_lidar.checks import check_int
from cdma_lidar.errors import (
    DeviceError,
    FieldError,
    FrameError,
    LinkError,
    LinkTimeout,
    out_of_range,
)
from cdma_lidar.protocol import auth
from cdma_lidar.protocol.framing import (
    MIN_MAX_FRAME,
    PROTOCOL_VERSION,
    Frame,
    FrameDecoder,
    encode_frame,
    frame_size,
)
from cdma_lidar.protocol.messages import (
    FRAGMENT_HEADER,
    REPLY_TO,
    ErrorCode,
    MsgKind,
    MsgType,
    Pieces,
    SessionLostReason,
    decode_payload,
    encode_payload,
    kind_of,
    split_message,
)
from cdma_lidar.protocol.ports import byte_time_s, default_fec, port_name
from cdma_lidar.protocol.trust import escape
from cdma_lidar.protocol.views import Status

__all__ = ["DIAG_GARBAGE", "DIAG_HINTS", "DIAG_NOISY", "DIAG_NO_ANSWER", "DIAG_SILENT",
           "DIAG_VERSION", "DIAG_WRONG_SESSION", "LinkStats", "Requests", "SessionLost"]

log = logging.getLogger(__name__)

DIAG_SILENT = "no bytes at all"
DIAG_GARBAGE = "bytes but no valid frame"
DIAG_WRONG_SESSION = "frames but wrong session"
DIAG_NO_ANSWER = "frames but no answer"
DIAG_VERSION = "frames of another protocol version"
DIAG_NOISY = "damaged frames"

#: What to do about each diagnosis (one line, for error messages).
DIAG_HINTS = {
    DIAG_SILENT: "check that the device is powered and connected and that the port is right",
    DIAG_GARBAGE: "check the baud rate and that the port is a cdma-lidar device",
    DIAG_WRONG_SESSION: "the device restarted: call hello() again",
    DIAG_NO_ANSWER: "the device is alive but does not answer this request",
    DIAG_VERSION: "host and firmware speak different protocol versions: update one of them",
    DIAG_NOISY: "the line damages more than its error correction repairs: check the cable, "
                "the baud rate and that FEC is on (a serial line)",
}
#: Shortest wait for one reply (s), however fast the line answered so far.
MIN_TIMEOUT_S = 0.02
#: Messages in pieces kept at once (a lost piece leaves its message behind).
_MAX_PIECES = 8
#: RESENDs remembered while their NAK may still come.
_MAX_UNAWAITED = 256


class SessionLost(LinkError):
    """The device ended this host's session (another host took over, or it expired)."""

    def __init__(self, message: str, reason: int = 0) -> None:
        super().__init__(message)
        self.reason = reason


@dataclass
class LinkStats:
    """Counters of the host end (decoder errors are in ``decoder.stats``)."""

    requests: int = 0
    retries: int = 0
    wrong_session: int = 0
    stale_replies: int = 0
    malformed: int = 0
    ignored: int = 0
    columns: int = 0
    duplicates: int = 0
    resend_requests: int = 0
    resent_columns: int = 0
    unauthenticated: int = 0  #: frames of our signed session dropped: bad MAC, replay, unsigned


class Requests:
    """Requests and frame routing over a port (see the module docstring); the arguments
    are :class:`~cdma_lidar.protocol.link.HostLink`'s."""

    def __init__(self, port: Any, timeout_s: float, retries: int, *, max_frame: int,
                 fec: bool | None, clock: Callable[[], float]) -> None:
        if not timeout_s > 0:
            raise out_of_range("timeout_s", "a positive number of seconds", timeout_s)
        self.port, self.clock = port, clock
        self.timeout_s = float(timeout_s)
        self.retries = check_int("retries", retries, 0, 100)
        self.decoder = FrameDecoder(max(max_frame, MIN_MAX_FRAME))
        self.fec = default_fec(port) if fec is None else bool(fec)
        self.decoder.fec = self.fec
        self.coded = False  # this session's frames are coded (the device agreed in HELLO)
        self.stats = LinkStats()
        self.session: int | None = None
        self.max_frame = 4096  # until INFO says more; every request fits
        self.last_status: Status | None = None
        self.line_errors = 0  # LINE_ERRORs heard so far
        self.seq = 0  # the last request seq used
        self.signer: auth.FrameSigner | None = None  # signs our requests (keyed session)
        self.verifier: auth.FrameVerifier | None = None  # checks the device's frames
        self._pending: int | None = None  # seq of the request waiting for its reply
        self._pending_type = 0
        self.reply: Frame | None = None
        self._reply_version: Frame | None = None  # reply to the pending seq we must not read
        self.reply_parts: list[Frame] = []  # the FRAGMENTs the last reply came in
        self._parts: list[Frame] = []  # those of the last message put together
        self._pieces: OrderedDict[tuple[int, int], Pieces] = OrderedDict()
        self.hello_seq: int | None = None  # HELLO pending: its replies open a new session
        self._early: list[Frame] = []  # frames that came with INFO, before it was ours
        self.streaming = False
        self.stream: deque[Frame] = deque()  # stream frames for the reassembler
        self._unawaited: OrderedDict[int, MsgType] = OrderedDict()  # seq -> RESEND sent
        self.refusal: tuple[MsgType, Frame] | None = None  # a NAK to one of them
        self.port_name = port_name(port)
        port.timeout = min(0.05, self.timeout_s / 4)  # longest blocking read (s)
        #: Smoothed round trip of a request and its reply and its mean deviation (s),
        #: measured on first tries; None until the first reply.
        self.rtt: float | None = None
        self.rtt_var = 0.0
        #: Shortest wait for a reply (s): below it a busy host's scheduling is the noise.
        self.min_timeout_s = min(MIN_TIMEOUT_S, self.timeout_s)
        #: Seconds one byte takes on the line (0: unknown, or no line to speak of).
        self.byte_s = byte_time_s(port)
        #: Called whenever the session is forgotten (SESSION_LOST, a new HELLO).
        self.on_forget: Callable[[], None] = lambda: None

    # ---- sending --------------------------------------------------------------------------
    def new_seq(self) -> int:
        self.seq = (self.seq + 1) & 0xFFFF
        return self.seq

    def transact(self, msg_type: MsgType, fields_: dict[str, Any], seq: int, *,
                  retries: int | None = None, timeout_s: float | None = None) -> dict[str, Any]:
        """Send a request and wait for its reply (decoded), retrying on the clock."""
        payload = encode_payload(msg_type, fields_)
        retries = self.retries if retries is None else retries
        timeout_s = self.timeout_s if timeout_s is None else timeout_s
        st = self.decoder.stats
        before = (st.bytes, st.frames, self.stats.wrong_session, self._other_version(),
                  st.damaged, self.line_errors)
        self.stats.requests += 1
        self._pending, self._pending_type = seq, int(msg_type)
        self.reply = self._reply_version = None
        self.reply_parts = []
        tries, waited = 0, 0.0
        try:
            # Short tries while the line answers fast, each twice the last, up to timeout_s;
            # as many as it takes to give the device (retries + 1) * timeout_s in all.
            while tries <= retries or waited < (retries + 1) * timeout_s - 1e-9:
                if tries:
                    self.stats.retries += 1
                    log.debug("%s seq %d: no answer, try %d", msg_type.name, seq, tries + 1)
                nbytes = self._send(msg_type, payload, seq)
                wait = self.reply_wait(nbytes, tries, timeout_s)
                sent = self.clock()
                self.port.timeout = min(0.05, wait / 4)  # longest blocking read (s)
                while self.reply is None and self._reply_version is None and \
                        self.clock() < sent + wait:
                    self.pump()
                tries += 1
                waited += wait
                if self.reply is not None:
                    if tries == 1:  # Karn: only a first try's reply measures the line
                        self._measured(self.clock() - sent - nbytes * self.byte_s)
                    return self.accept_reply(msg_type, self.reply)
                if (f := self._reply_version) is not None:
                    raise LinkError(
                        f"device answered {msg_type.name} in protocol version {f.version} "
                        f"with incompat flags 0x{f.incompat:02x}; this host speaks version "
                        f"{PROTOCOL_VERSION} and knows no incompat flags: "
                        f"{DIAG_HINTS[DIAG_VERSION]}")
        finally:
            self._pending = None
            self.port.timeout = min(0.05, self.timeout_s / 4)
        diag, what = self._diagnose(*before)
        raise LinkTimeout(f"{msg_type.name} got no answer from {self.port_name} after "
                          f"{tries} tries in {waited:.3g} s: {what}; "
                          f"{DIAG_HINTS[diag]}", diag)

    def reply_wait(self, nbytes: int, attempt: int, timeout_s: float | None = None) -> float:
        """How long try ``attempt`` (0 first) of a request of ``nbytes`` wire bytes waits
        for its reply (s): the measured round trip plus four of its mean deviations and
        the request's transmit time, at least ``min_timeout_s``, doubled at each retry,
        at most ``timeout_s``; ``timeout_s`` before the line has been measured."""
        top = self.timeout_s if timeout_s is None else timeout_s
        if self.rtt is None:
            return top
        base = max(self.min_timeout_s, self.rtt + 4 * self.rtt_var + nbytes * self.byte_s)
        return min(top, base * 2 ** attempt)

    def _measured(self, rtt: float) -> None:
        """One round trip (s): smoothed as TCP does (RFC 6298: gains 1/8 and 1/4)."""
        rtt = max(0.0, rtt)
        if self.rtt is None:
            self.rtt, self.rtt_var = rtt, rtt / 2
        else:
            self.rtt_var += (abs(self.rtt - rtt) - self.rtt_var) / 4
            self.rtt += (rtt - self.rtt) / 8

    def _send(self, msg_type: MsgType, payload: bytes, seq: int) -> int:
        """Write one try of a request, signed afresh (new counter, same seq and payload);
        returns the bytes written."""
        wire = b"".join(encode_frame(t, p, seq, self.session or 0, signer=self.signer,
                                     coded=self.coded)
                        for t, p in self._pieces_of(msg_type, payload, seq))
        if msg_type == MsgType.HELLO and self.fec:
            # Coded (gets through a noisy line), then plain (a device that cannot decode
            # it, or an older one, reads this copy): the device acts once, the replay
            # cache answers the copy.
            wire = encode_frame(msg_type, payload, seq, 0, coded=True) + wire
        try:
            self.port.write(wire)
        except Exception as exc:  # pyserial raises SerialException (an OSError) or others
            raise LinkError(f"cannot write to {self.port_name}: {exc}; is the device "
                            "still connected?") from None
        return len(wire)

    def _pieces_of(self, msg_type: MsgType, payload: bytes, seq: int) -> list[tuple[int, bytes]]:
        """(type, payload) of each frame of one request: whole, or in FRAGMENTs of at most
        ``max_frame`` bytes (docs/protocol.md section 2.4)."""
        signed = self.signer is not None
        if frame_size(len(payload), signed) <= self.max_frame:
            return [(msg_type, payload)]
        room = self.max_frame - frame_size(FRAGMENT_HEADER, signed)
        try:
            return [(MsgType.FRAGMENT, p) for p in split_message(msg_type, payload, room, seq)]
        except DeviceError as exc:
            raise FieldError(str(exc), "payload") from None

    def send_unawaited(self, msg_type: MsgType, fields_: dict[str, Any]) -> None:
        """Send a request whose reply is not waited for (a NAK to it still fails the scan)."""
        seq = self.new_seq()
        self.stats.requests += 1
        self._unawaited[seq] = msg_type
        while len(self._unawaited) > _MAX_UNAWAITED:
            self._unawaited.popitem(last=False)
        self._send(msg_type, encode_payload(msg_type, fields_), seq)

    def _diagnose(self, nbytes: int, frames: int, wrong: int, version: int, damaged: int,
                  line_errors: int) -> tuple[str, str]:
        """(DIAG_* string, what to say) of what the line showed since those counters."""
        st = self.decoder.stats
        reported = self.line_errors - line_errors  # the device saw our frames damaged
        hurt = st.damaged - damaged
        if st.bytes == nbytes:
            diag = DIAG_SILENT
        elif st.frames == frames and not reported:
            diag = DIAG_VERSION if self._other_version() > version else DIAG_GARBAGE
        elif (n := self.stats.wrong_session - wrong) and st.frames - frames == n and \
                not reported:
            diag = DIAG_WRONG_SESSION
        else:
            diag = DIAG_NOISY if reported or hurt else DIAG_NO_ANSWER
        if diag not in (DIAG_NOISY, DIAG_GARBAGE):
            return diag, diag
        return diag, (f"{diag} ({hurt} damaged frames of {hurt + st.frames - frames} "
                      f"received, {reported} reported by the device)")

    def _other_version(self) -> int:
        """CRC-valid frames rejected for their version or incompat flags so far."""
        return self.decoder.stats.version + self.decoder.stats.incompat

    def accept_reply(self, msg_type: MsgType, frame: Frame) -> dict[str, Any]:
        """The decoded reply; DeviceError for a NAK, LinkError for anything else amiss."""
        try:
            body = decode_payload(frame.msg_type, frame.payload)
        except Exception as exc:  # FrameError; the decoder raises nothing else
            self.stats.malformed += 1
            raise LinkError(f"malformed {frame.msg_type:#04x} reply to {msg_type.name}: "
                            f"{exc}") from None
        assert isinstance(body, dict)
        if frame.msg_type == MsgType.NAK:
            try:
                cname = ErrorCode(body["code"]).name
            except ValueError:
                cname = f"error {body['code']}"
            fld = escape(body["field"])
            where = f" (field {fld})" if fld else ""
            detail = f": {escape(body['detail'])}" if body["detail"] else ""
            if body["code"] == ErrorCode.WRONG_SESSION:
                detail += " (the device restarted, or another host took it over)"
            raise DeviceError(f"device refused {msg_type.name}: {cname}{where}{detail}",
                              code=body["code"], field=fld or None)
        if msg_type == MsgType.HELLO and frame.msg_type == MsgType.CHALLENGE:
            return body
        expected = REPLY_TO[msg_type]
        if frame.msg_type != expected or (expected == MsgType.ACK and
                                          body["request_type"] != msg_type):
            raise LinkError(f"device answered {msg_type.name} with {frame.msg_type:#04x}")
        return body

    # ---- receiving ------------------------------------------------------------------------
    def pump(self) -> None:
        """One blocking read (at most ``port.timeout``) and dispatch of what it completes."""
        try:
            n = self.port.in_waiting
            data = self.port.read(n if n else 1)
        except Exception as exc:
            raise LinkError(f"cannot read from {self.port_name}: {exc}; is the device "
                            "still connected?") from None
        if data:
            for frame in self.decoder.feed(data):
                self.dispatch(frame)
            while self.decoder.rejected:  # frames of another version or incompat flags
                frame = self.decoder.rejected.pop(0)
                if kind_of(frame.msg_type) is MsgKind.REPLY and frame.seq == self._pending:
                    self._reply_version = frame

    def dispatch(self, frame: Frame, checked: bool = False) -> None:
        """Route one frame; ``checked``: a notice put together from authenticated pieces."""
        mtype, kind = frame.msg_type, kind_of(frame.msg_type)
        if kind is MsgKind.REQUEST:
            self.stats.ignored += 1
            return
        hello_reply = kind is MsgKind.REPLY and frame.seq == self.hello_seq and \
            mtype in (MsgType.INFO, MsgType.NAK, MsgType.CHALLENGE)
        if self.hello_seq is not None and not hello_reply:
            if mtype == MsgType.FRAGMENT and self.reply is None:
                body = self._decoded(frame)
                if body is not None and body["seq"] == self.hello_seq and \
                        body["msg_type"] in (MsgType.INFO, MsgType.NAK):
                    self._reply_piece(frame, body)  # INFO of a session we do not know yet
                    return
            elif self.reply is not None and frame.session == self.reply.session:
                self._early.append(frame)  # of the session INFO opens: read once it is ours
                return
        if mtype == MsgType.LINE_ERROR and self.verifier is None:
            self.line_errors += 1  # unsigned: a hint only (diagnosis), from any session
            return
        if not hello_reply and frame.session != self.session:
            self.stats.wrong_session += 1
            if (mtype == MsgType.NAK and frame.seq == self._pending and self.reply is None
                    and self.verifier is None and
                    frame.payload[1:3] == ErrorCode.WRONG_SESSION.to_bytes(2, "little")):
                self.reply = frame  # the device says it restarted: fail fast
            return
        if self.verifier is not None and not hello_reply and not checked and \
                not self.verifier.check(frame):
            self.stats.unauthenticated += 1  # forged, replayed or unsigned: not from the device
            log.debug("dropped an unauthenticated %#04x frame", mtype)
            return
        if mtype == MsgType.LINE_ERROR:
            self.line_errors += 1  # our session's, authenticated: the device saw damage
        elif mtype == MsgType.SESSION_LOST:
            self._session_lost(frame)
        elif mtype == MsgType.FRAGMENT:
            self._fragment(frame)
        elif kind is MsgKind.REPLY:
            self._on_reply(frame)
        else:
            if mtype == MsgType.HEARTBEAT:
                if (body := self._decoded(frame)) is None:
                    return
                self.last_status = Status(**body)
            if self.streaming:
                self.stream.append(frame)

    def _fragment(self, frame: Frame) -> None:
        """An authenticated FRAGMENT of a column (the stream's), a reply or a notice."""
        if frame.payload[:1] == bytes([MsgType.COLUMN_RESULT]):  # field msg_type comes first
            if self.streaming:
                self.stream.append(frame)
            return
        body = self._decoded(frame)
        if body is None:
            return
        if kind_of(body["msg_type"]) is MsgKind.REPLY:
            self._reply_piece(frame, body)
        elif (whole := self._piece(frame, body)) is not None:  # a notice longer than a frame
            self.dispatch(whole._replace(seq=0), checked=True)

    def _decoded(self, frame: Frame) -> dict[str, Any] | None:
        """The decoded payload of a FRAGMENT or HEARTBEAT; None (counted) if malformed."""
        try:
            return decode_payload(frame.msg_type, frame.payload)  # type: ignore[return-value]
        except FrameError:  # dropped
            self.stats.malformed += 1
            return None

    def _piece(self, frame: Frame, body: dict[str, Any]) -> Frame | None:
        """Keep one piece; the whole message (unsigned, of the piece's session) once all
        are in (its pieces then in ``_parts``)."""
        key = (body["msg_type"], body["seq"])
        pc = self._pieces.get(key)
        if pc is None or pc.count != body["count"]:
            pc = self._pieces[key] = Pieces(body["count"])
            while len(self._pieces) > _MAX_PIECES:
                self._pieces.popitem(last=False)
        if (payload := pc.add(frame, body)) is None:
            return None
        del self._pieces[key]
        self._parts = pc.frames
        return Frame(key[0], key[1], frame.session, payload, 0, 0, frame.version)

    def _reply_piece(self, frame: Frame, body: dict[str, Any]) -> None:
        """A piece of a reply: once all are in, handle the whole reply."""
        if body["seq"] != self._pending:
            self.stats.stale_replies += 1
        elif (whole := self._piece(frame, body)) is not None:
            if self.reply is None:
                self.reply_parts = self._parts
            self._on_reply(whole)

    def _on_reply(self, frame: Frame) -> None:
        """A reply of our session, authenticated: the pending one, a RESEND's, or stale."""
        # ACK and NAK echo the request type: a reply to another request that happens
        # to carry the same seq (a previous link, a wrapped counter) is not ours.
        echoed = frame.payload[:1] if frame.msg_type in (MsgType.ACK, MsgType.NAK) else b""
        unawaited = self._unawaited.get(frame.seq)
        if unawaited is not None and echoed == bytes([unawaited]):
            del self._unawaited[frame.seq]
            if frame.msg_type == MsgType.NAK and self.refusal is None:
                self.refusal = (unawaited, frame)
        elif frame.seq == self._pending and self.reply is None and \
                echoed in (b"", bytes([self._pending_type])):
            self.reply = frame
        else:
            self.stats.stale_replies += 1

    def _session_lost(self, frame: Frame) -> None:
        """The device ended our session: forget it and raise SessionLost (one line)."""
        try:
            body = decode_payload(frame.msg_type, frame.payload)
            assert isinstance(body, dict)
            reason, detail = int(body["reason"]), escape(body["detail"])
        except Exception:  # FrameError: still lost, say so without the device's words
            reason, detail = 0, "no reason given"
        self.forget()
        what = {SessionLostReason.TAKEN_OVER: "another host took over the device",
                SessionLostReason.EXPIRED: "the session expired"}.get(reason, "session ended")
        raise SessionLost(f"session lost on {self.port_name}: {detail or what}", reason)

    def forget(self) -> None:
        """No session any more (keys with it); then :attr:`on_forget`."""
        self.session = None
        self.signer = self.verifier = None
        self.on_forget()

    def before_hello(self) -> None:
        """A HELLO is about to go: no session, uncoded, nothing held from the last one."""
        self.forget()
        self._early = []
        self.coded = False

    def open_session(self, session: int, max_frame: int, coded: bool,
                     keys: tuple[auth.FrameSigner, auth.FrameVerifier] | None) -> None:
        """INFO opened ``session``: requests within ``max_frame`` (bytes), ``coded`` or not,
        signed and checked with ``keys``; then the frames that came with INFO are read."""
        self.session, self.max_frame, self.coded = session, max_frame, coded
        if keys is not None:
            self.signer, self.verifier = keys
        early, self._early = self._early, []
        for frame in early:  # e.g. SESSION_LOST right behind INFO
            self.dispatch(frame)

    def start_stream(self) -> None:
        """Stream frames go to :attr:`stream` from now on (a late NAK to a RESEND of an
        earlier stream is not this one's)."""
        self.stream.clear()
        self._unawaited.clear()
        self.refusal = None
        self.streaming = True

    def end_stream(self) -> None:
        self.streaming = False
        self.stream.clear()
