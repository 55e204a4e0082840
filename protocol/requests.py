"""Host requests: the session, each request waited for and sent again, one receive path.

:class:`Requests` owns the port, the receive buffer (a ``FrameDecoder``), the request
counter ``seq`` and the session (docs/protocol.md sections 4 and 5: HELLO, with a key its
challenge-response and signed frames). It blocks only in ``port.read`` (at most
``port.timeout``) and measures every wait on ``clock``, so tests drive it with a fake port
whose reads move a fake clock. Retransmission: section 6.1; a LinkTimeout after the last
try carries a ``DIAG_*`` diagnosis (section 6.7) and its hint. Every frame read goes
through :meth:`Requests.pump`.
"""

from __future__ import annotations

import contextlib
import logging
import secrets
import time
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
    FRAME_LIMIT,
    MIN_MAX_FRAME,
    PROTOCOL_VERSION,
    Frame,
    FrameDecoder,
    encode_frame,
    frame_size,
    rejects,
)
from cdma_lidar.protocol.messages import (
    REPLY_TO,
    SCHEMA_CRC,
    Auth,
    ErrorCode,
    HelloFlags,
    Info,
    MsgKind,
    MsgType,
    SessionLostReason,
    Status,
    decode_payload,
    encode_payload,
    kind_of,
    piece_room,
    split_message,
)
from cdma_lidar.protocol.ports import byte_time_s, default_fec, port_name
from cdma_lidar.protocol.reassembly import Joiner
from cdma_lidar.protocol.trust import DeviceLied, check_info, escape

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


def diagnose(before: tuple[int, ...], now: tuple[int, ...]) -> tuple[str, str]:
    """(DIAG_*, what to say: the diagnosis, its counts where they help, its hint) of what
    the line showed between two readings of :meth:`Requests._counters`."""
    nbytes, frames, wrong, version, damaged, reported = (b - a for a, b in zip(before, now,
                                                                                strict=True))
    if not nbytes:
        diag = DIAG_SILENT
    elif not frames and not reported:
        diag = DIAG_VERSION if version else DIAG_GARBAGE
    elif wrong and frames == wrong and not reported:
        diag = DIAG_WRONG_SESSION
    else:
        diag = DIAG_NOISY if reported or damaged else DIAG_NO_ANSWER
    counts = (f" ({damaged} damaged frames of {damaged + frames} received, {reported} "
              "reported by the device)") if diag in (DIAG_NOISY, DIAG_GARBAGE) else ""
    return diag, f"{diag}{counts}; {DIAG_HINTS[diag]}"


class Requests:
    """The session and its requests over a port; the arguments are ``HostLink``'s."""

    def __init__(self, port: Any, timeout_s: float = 0.5, retries: int = 3, *,
                 column_retries: int | None = None, max_frame: int = FRAME_LIMIT,
                 key: bytes | None = None, take_over: bool = False, keep_config: bool = False,
                 fec: bool | None = None, progress_timeout_s: float = 10.0,
                 clock: Callable[[], float] = time.monotonic) -> None:
        for name, value in (("timeout_s", timeout_s), ("progress_timeout_s", progress_timeout_s)):
            if not value > 0:
                raise out_of_range(name, "a positive number of seconds", value)
        if key is not None and len(key) != auth.KEY_BYTES:
            raise out_of_range("key", f"{auth.KEY_BYTES} bytes", len(key))
        self.port, self.clock, self.port_name = port, clock, port_name(port)
        self.timeout_s = float(timeout_s)
        self.retries = check_int("retries", retries, 0, 100)
        self.column_retries = 10 * (self.retries + 1) if column_retries is None \
            else check_int("column_retries", column_retries, 0, 1000)
        self.progress_timeout_s = float(progress_timeout_s)
        self._next_frame_id = secrets.randbits(31)  # of the next stream
        self.key, self.take_over, self.keep_config = key, bool(take_over), bool(keep_config)
        self.decoder = FrameDecoder(max(max_frame, MIN_MAX_FRAME))
        self.fec = self.decoder.fec = default_fec(port) if fec is None else bool(fec)
        self.coded = False  # this session's frames are coded (the device agreed in HELLO)
        self.stats = LinkStats()
        self.session: int | None = None
        self.info: Info | None = None
        self.config: dict[str, Any] | None = None  # last full CONFIG, checked against INFO
        self._host_max = max_frame
        self.max_frame = 4096  # until INFO says more; every request fits
        self.last_status: Status | None = None
        self.line_errors = 0  # LINE_ERRORs heard so far
        self._nonce = secrets.token_bytes(auth.NONCE_BYTES)
        self.seq = int.from_bytes(self._nonce[:2], "little")  # the last request seq used
        self.signer: auth.FrameMac | None = None  # signs our requests (keyed session)
        self.verifier: auth.FrameMac | None = None  # checks the device's frames
        self._pending: int | None = None  # seq of the request waiting for its reply
        self._pending_type = 0
        self.reply: Frame | None = None  # to the pending seq (of another version: refused)
        self.reply_parts: list[Frame] = []  # the FRAGMENTs the last reply came in
        self.joiner = Joiner(limit=8)  # replies and notices in pieces (section 6.3)
        self._inbox: deque[Frame] = deque()  # frames read behind the reply, for the next pump
        #: (frame, decoded) of the running stream, for its reassembler; None: no stream.
        self.stream: deque[tuple[Frame, Any]] | None = None
        self._unawaited: OrderedDict[int, MsgType] = OrderedDict()  # seq -> RESEND sent
        port.timeout = min(0.05, self.timeout_s / 4)  # longest blocking read (s)
        #: Smoothed round trip and its mean deviation (s), of first tries; None until one.
        self.rtt: float | None = None
        self.rtt_var = 0.0
        #: Shortest wait for a reply (s): below it a busy host's scheduling is the noise.
        self.min_timeout_s = min(MIN_TIMEOUT_S, self.timeout_s)
        self.byte_s = byte_time_s(port)  # s per byte on the line (0: unknown or none)

    # ---- the session ------------------------------------------------------------------
    def hello(self) -> Info:
        """Open a session: the device's identity, limits, geometry and session id.

        With a key, answers the CHALLENGE and checks that INFO is signed with the session
        key. DeviceError (code BUSY, field ``session``) when another host owns the device
        and ``take_over`` is off; DeviceLied when INFO contradicts itself.
        """
        self._forget()
        flags = int((HelloFlags.TAKE_OVER if self.take_over else 0) |
                    (HelloFlags.KEEP_CONFIG if self.keep_config else 0) |
                    (HelloFlags.FEC if self.fec else 0))
        fields_ = {"host_max_frame": self._host_max, "flags": flags, "host_nonce": self._nonce,
                   "device_nonce": bytes(auth.NONCE_BYTES), "mac": bytes(auth.MAC_BYTES)}
        for _ in range(2):
            reply = self.transact(MsgType.HELLO, fields_, self.new_seq())
            if self.reply is not None and self.reply.msg_type == MsgType.INFO:
                return self._open(reply, bytes(fields_["device_nonce"]))
            if self.key is None:
                raise LinkError(f"device on {self.port_name} requires a key: pass --key-file "
                                "FILE or set CDMA_LIDAR_KEY_FILE to the device's key file")
            fields_["device_nonce"] = bytes(reply["device_nonce"])
            fields_["mac"] = auth.hello_mac(self.key, fields_["device_nonce"], self._nonce,
                                            flags, self._host_max)
        raise LinkError("device answered the authenticated HELLO with another CHALLENGE: "
                        "it does not accept this host's key")

    def _open(self, reply: dict[str, Any], device_nonce: bytes) -> Info:
        """Check INFO (with a key: the device's proof, INFO's signature) and make its
        session ours (requests within both ends' max frame, coded when the device coded
        its INFO)."""
        info = Info.from_fields(reply)  # the strict decoder gave every field, in range
        assert self.reply is not None
        if info.protocol_version != PROTOCOL_VERSION:
            raise LinkError(f"device speaks protocol version {info.protocol_version}, host "
                            f"{PROTOCOL_VERSION}; update the host or the firmware")
        if self.key is not None:
            if info.auth != Auth.HMAC_SHA256 or not auth.equal(
                    info.device_mac, auth.device_mac(self.key, self._nonce, device_nonce,
                                                     info.session_id)):
                raise LinkError(f"device on {self.port_name} did not prove it holds the key "
                                f"(INFO.auth = {info.auth}): it is not the device the key "
                                "file belongs to, or it holds no key (then drop --key-file)")
            tx, rx = auth.session_macs(self.key, self._nonce, device_nonce, info.session_id)
            parts = self.reply_parts or [self.reply]  # an INFO in FRAGMENTs: each is signed
            if any(p.session != info.session_id for p in parts) or \
                    not all(map(rx.check, parts)):
                raise LinkError(f"device on {self.port_name} sent an INFO not signed with "
                                "the session key")
            self.signer, self.verifier = tx, rx
        elif info.auth != Auth.NONE:
            raise DeviceLied("device announced signed frames (INFO.auth = "
                             f"{info.auth}) without asking this host for a key", "auth")
        self.info = check_info(info)
        if info.schema_crc != SCHEMA_CRC:
            log.warning("device schema 0x%08x differs from host schema 0x%08x: host and "
                        "firmware come from different revisions", info.schema_crc, SCHEMA_CRC)
        self.session = info.session_id
        self.max_frame = min(info.max_frame, self.decoder.max_frame)
        self.coded = self.fec and self.reply.fec
        log.info("session 0x%08x with %s (firmware %s, %d channels, max frame %d%s)",
                 info.session_id, self.info.serial, self.info.firmware_version, info.channels,
                 info.max_frame, ", signed" if self.signer else "")
        return self.info

    def _forget(self) -> None:
        """No session any more: its keys, coding, INFO and configuration go with it."""
        self.session = self.info = self.config = None
        self.signer, self.verifier, self.coded = None, None, False

    def close(self) -> None:
        """End the session (SESSION_END, one short try, so another host may HELLO without
        take-over) and close the port."""
        if self.session is not None:
            try:
                self.transact(MsgType.SESSION_END, {}, self.new_seq(), retries=0,
                              timeout_s=min(self.timeout_s, 0.2))
            except Exception:  # LinkError, SessionLost: the device forgets us when idle
                log.debug("SESSION_END got no answer; the session expires when idle")
            self.session = None
        with contextlib.suppress(Exception):
            self.port.close()

    # ---- sending ------------------------------------------------------------------------
    def new_seq(self) -> int:
        self.seq = (self.seq + 1) & 0xFFFF
        return self.seq

    def request(self, msg_type: MsgType, fields_: dict[str, Any]) -> dict[str, Any]:
        """A request of the session (HELLO first when there is none)."""
        if self.session is None:
            self.hello()
        return self.transact(msg_type, fields_, self.new_seq())

    def transact(self, msg_type: MsgType, fields_: dict[str, Any], seq: int, *,
                 retries: int | None = None, timeout_s: float | None = None) -> dict[str, Any]:
        """Send a request and wait for its reply (decoded), retrying on the clock."""
        payload = encode_payload(msg_type, fields_)
        retries = self.retries if retries is None else retries
        timeout_s = self.timeout_s if timeout_s is None else timeout_s
        before = self._counters()
        self.stats.requests += 1
        self._pending, self._pending_type = seq, int(msg_type)
        self.reply = None
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
                while self.reply is None and self.clock() < sent + wait:
                    self.pump()
                tries += 1
                waited += wait
                if self.reply is not None:
                    if tries == 1:  # Karn: only a first try's reply measures the line
                        self._measured(self.clock() - sent - nbytes * self.byte_s)
                    return self.accept_reply(msg_type, self.reply)
        finally:
            self._pending = None
            self.port.timeout = min(0.05, self.timeout_s / 4)
        diag, what = diagnose(before, self._counters())
        raise LinkTimeout(f"{msg_type.name} got no answer from {self.port_name} after "
                          f"{tries} tries in {waited:.3g} s: {what}", diag)

    def reply_wait(self, nbytes: int, attempt: int, timeout_s: float) -> float:
        """How long try ``attempt`` (0 first) of a request of ``nbytes`` wire bytes waits
        (s), at least ``min_timeout_s``, at most ``timeout_s`` (docs/protocol.md 6.1)."""
        if self.rtt is None:
            return timeout_s
        base = max(self.min_timeout_s, self.rtt + 4 * self.rtt_var + nbytes * self.byte_s)
        return min(timeout_s, base * 2 ** attempt)

    def _measured(self, rtt: float) -> None:
        """One round trip (s): smoothed as TCP does (RFC 6298: gains 1/8 and 1/4)."""
        rtt = max(0.0, rtt)
        if self.rtt is None:
            self.rtt, self.rtt_var = rtt, rtt / 2
        else:
            self.rtt_var += (abs(self.rtt - rtt) - self.rtt_var) / 4
            self.rtt += (rtt - self.rtt) / 8

    def _send(self, msg_type: MsgType, payload: bytes, seq: int) -> int:
        """Write one try of a request (bytes written), signed afresh (same seq), whole or
        in FRAGMENTs of at most ``max_frame`` bytes (docs/protocol.md section 2.4)."""
        signed = self.signer is not None
        pieces = [(msg_type, payload)]
        if frame_size(len(payload), signed) > self.max_frame:
            try:
                pieces = [(MsgType.FRAGMENT, p) for p in split_message(
                    msg_type, payload, piece_room(self.max_frame, signed), seq)]
            except DeviceError as exc:
                raise FieldError(str(exc), "payload") from None
        wire = b"".join(encode_frame(t, p, seq, self.session or 0, signer=self.signer,
                                     coded=self.coded) for t, p in pieces)
        if msg_type == MsgType.HELLO and self.fec:
            # Coded (gets through a noisy line), then plain (for a device that cannot
            # decode it): the device acts once, its replay cache answers the copy.
            wire = encode_frame(msg_type, payload, seq, 0, coded=True) + wire
        try:
            self.port.write(wire)
        except Exception as exc:  # pyserial raises SerialException (an OSError) or others
            raise LinkError(f"cannot write to {self.port_name}: {exc}; is the device "
                            "still connected?") from None
        return len(wire)

    def send_unawaited(self, msg_type: MsgType, fields_: dict[str, Any]) -> int:
        """Send a request of the stream whose reply is not waited for (bytes written); a
        NAK to it still fails the scan (raised by the :meth:`pump` that reads it)."""
        seq = self.new_seq()
        self.stats.requests += 1
        self._unawaited[seq] = msg_type
        while len(self._unawaited) > _MAX_UNAWAITED:
            self._unawaited.popitem(last=False)
        return self._send(msg_type, encode_payload(msg_type, fields_), seq)

    def _counters(self) -> tuple[int, ...]:
        """What :func:`diagnose` compares: bytes, frames, wrong session, other version
        or incompat flags, damaged, LINE_ERRORs so far."""
        st = self.decoder.stats
        return (st.bytes, st.frames, self.stats.wrong_session, st.version + st.incompat,
                st.damaged, self.line_errors)

    def accept_reply(self, msg_type: MsgType, frame: Frame) -> dict[str, Any]:
        """The decoded reply; DeviceError for a NAK, LinkError for anything else amiss."""
        if rejects(frame):  # of another version or with incompat flags (see pump)
            raise LinkError(
                f"device answered {msg_type.name} in protocol version {frame.version} with "
                f"incompat flags 0x{frame.incompat:02x}; this host speaks version "
                f"{PROTOCOL_VERSION} and knows no incompat flags: {DIAG_HINTS[DIAG_VERSION]}")
        try:
            body = decode_payload(frame.msg_type, frame.payload)
        except Exception as exc:  # FrameError; the decoder raises nothing else
            self.stats.malformed += 1
            raise LinkError(f"malformed {frame.msg_type:#04x} reply to {msg_type.name}: "
                            f"{exc}") from None
        assert isinstance(body, dict)
        if frame.msg_type == MsgType.NAK:  # code, field and detail, escaped
            code, fld = body["code"], escape(body["field"])
            cname = ErrorCode(code).name if code in iter(ErrorCode) else f"error {code}"
            where = f" (field {fld})" if fld else ""
            detail = f": {escape(body['detail'])}" if body["detail"] else ""
            if code == ErrorCode.WRONG_SESSION:
                detail += " (the device restarted, or another host took it over)"
            raise DeviceError(f"device refused {msg_type.name}: {cname}{where}{detail}",
                              code=code, field=fld or None)
        if msg_type == MsgType.HELLO and frame.msg_type == MsgType.CHALLENGE:
            return body
        expected = REPLY_TO[msg_type]
        if frame.msg_type != expected or (expected == MsgType.ACK and
                                          body["request_type"] != msg_type):
            raise LinkError(f"device answered {msg_type.name} with {frame.msg_type:#04x}")
        return body

    # ---- receiving ----------------------------------------------------------------------
    def pump(self) -> None:
        """Handle the frames read behind the last reply, else one read (at most
        ``port.timeout`` s) and its frames, up to the pending reply."""
        if not self._inbox:
            try:
                data = self.port.read(self.port.in_waiting or 1)
            except Exception as exc:
                raise LinkError(f"cannot read from {self.port_name}: {exc}; is the device "
                                "still connected?") from None
            self._inbox.extend(self.decoder.feed(data) if data else ())
        # Stop at the reply: what follows it may need the session it opens (INFO).
        while self._inbox and (self.reply is None or self._pending is None):
            self._receive(self._inbox.popleft())
        while self.decoder.rejected:  # frames of another version or incompat flags
            frame = self.decoder.rejected.pop(0)
            if kind_of(frame.msg_type) is MsgKind.REPLY and frame.seq == self._pending:
                self.reply = self.reply or frame  # accept_reply refuses it (a valid one wins)

    def _receive(self, frame: Frame) -> None:
        """Check one frame (session, signature), join its pieces, handle it whole. Replies
        to our HELLO (or their FRAGMENTs) are of a session not known yet (see :meth:`_open`)."""
        mtype = frame.msg_type
        if kind_of(mtype) is MsgKind.REQUEST:
            self.stats.ignored += 1
            return
        body = None  # a FRAGMENT's fields (the whole message's type and seq first)
        if mtype == MsgType.FRAGMENT and (body := self._decoded(frame)) is None:
            return
        seq, what = (body["seq"], body["msg_type"]) if body else (frame.seq, mtype)
        if seq == self._pending and self._pending_type == MsgType.HELLO and \
                what in (MsgType.INFO, MsgType.NAK, MsgType.CHALLENGE):
            pass
        elif mtype == MsgType.LINE_ERROR and self.verifier is None:
            pass  # unsigned: a hint only (diagnosis), from any session
        elif frame.session != self.session:
            self.stats.wrong_session += 1
            if (mtype == MsgType.NAK and frame.seq == self._pending and self.reply is None
                    and self.verifier is None and
                    frame.payload[1:3] == ErrorCode.WRONG_SESSION.to_bytes(2, "little")):
                self.reply = frame  # the device says it restarted: fail fast
            return
        elif self.verifier is not None and not self.verifier.check(frame):
            self.stats.unauthenticated += 1  # forged, replayed or unsigned: not from the device
            log.debug("dropped an unauthenticated %#04x frame", mtype)
            return
        parts: list[Frame] = []
        # A column's pieces go to the stream one by one: its reassembler joins them.
        if body is not None and body["msg_type"] != MsgType.COLUMN_RESULT:
            if (whole := self.joiner.add(frame, body)) is None:
                return
            (frame, parts), body = whole, None
        self._dispatch(frame, parts, body)

    def _dispatch(self, frame: Frame, parts: list[Frame], body: Any) -> None:
        """A whole message (or a column's FRAGMENT), checked; ``parts``: the FRAGMENTs it
        came in; ``body``: its decoded payload if known."""
        mtype = frame.msg_type
        if mtype == MsgType.LINE_ERROR:
            self.line_errors += 1  # the device saw damage (signed session: ours, checked)
        elif mtype == MsgType.SESSION_LOST:  # the device ended our session
            self._forget()  # malformed: still lost, said without the device's words
            body = self._decoded(frame) or {"reason": 0, "detail": "no reason given"}
            what = {SessionLostReason.TAKEN_OVER: "another host took over the device",
                    SessionLostReason.EXPIRED: "the session expired"}.get(body["reason"])
            raise SessionLost(f"session lost on {self.port_name}: "
                              f"{escape(body['detail']) or what or 'session ended'}",
                              body["reason"])
        elif kind_of(mtype) is MsgKind.REPLY:  # the pending one, a RESEND's, or stale
            # ACK and NAK echo the request type: a reply to another request that happens
            # to carry the same seq (a previous link, a wrapped counter) is not ours.
            echoed = frame.payload[:1] if mtype in (MsgType.ACK, MsgType.NAK) else b""
            unawaited = self._unawaited.get(frame.seq)
            if unawaited is not None and echoed == bytes([unawaited]):
                del self._unawaited[frame.seq]
                if mtype == MsgType.NAK:  # the device refused a RESEND: say why
                    self.accept_reply(unawaited, frame)
            elif frame.seq == self._pending and self.reply is None and \
                    echoed in (b"", bytes([self._pending_type])):
                self.reply, self.reply_parts = frame, parts
            else:
                self.stats.stale_replies += 1
        elif self.stream is not None or mtype == MsgType.HEARTBEAT:
            if body is None and (body := self._decoded(frame)) is None:
                return
            if mtype == MsgType.HEARTBEAT:
                self.last_status = Status(**body)
            if self.stream is not None:
                self.stream.append((frame, body))

    def _decoded(self, frame: Frame) -> Any:
        """The decoded payload of a stream frame or FRAGMENT; None (counted) if malformed."""
        try:
            return decode_payload(frame.msg_type, frame.payload)
        except FrameError:  # dropped
            self.stats.malformed += 1
            return None

    def end_stream(self) -> None:
        """No stream: its frames and RESENDs go (a NAK to an earlier stream's RESEND is
        stale; its column pieces went with its reassembler)."""
        self.stream = None
        self._unawaited.clear()
