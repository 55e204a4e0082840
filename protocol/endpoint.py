"""Device end of the link: one :class:`DeviceEndpoint` per connection, in front of a
:class:`DeviceApp` (e.g. ``cdma_lidar.virtual.board``), which only answers decoded
requests and produces columns.

A request passes, in this order, the frame checks (docs/protocol.md section 2.3, a damaged
chunk: LINE_ERROR at once), its session (4; HELLO always passes), its signature (5), the
replay cache and the stale-seq rule (6.1); one that needs the application while the engine
computes is held, in order (6.6); a handler's reply goes through
:mod:`~cdma_lidar.protocol.transmit` with the request's seq. One loop per connection
(:meth:`DeviceEndpoint.poll`) does all of it and never waits for the application: the
device's :class:`~cdma_lidar.protocol.streams.Engine` computes the columns one step at a
time while the loop answers from its state.
"""

from __future__ import annotations

import abc
import logging
import math
import threading
import time
import zlib
from collections import OrderedDict
from collections.abc import Callable, Iterator
from concurrent.futures import wait
from typing import Any

import numpy as np
from numpy.typing import NDArray

from cdma_lidar.checks import check_int
from cdma_lidar.errors import ConfigError, DeviceError, FrameError, out_of_range
from cdma_lidar.protocol.columns import ColumnResult
from cdma_lidar.protocol.device_sessions import DeviceCore, DeviceSession, EndpointStats
from cdma_lidar.protocol.framing import PROTOCOL_VERSION, Frame, FrameDecoder
from cdma_lidar.protocol.messages import (
    TEMPERATURE_UNKNOWN,
    CaptureKind,
    ErrorCode,
    Info,
    MsgKind,
    MsgType,
    State,
    Status,
    decode_payload,
    encode_payload,
    kind_of,
    type_name,
)
from cdma_lidar.protocol.ports import port_name
from cdma_lidar.protocol.reassembly import Joiner
from cdma_lidar.protocol.streams import Engine, Streams
from cdma_lidar.protocol.transmit import CONTROL, Reply, Transmitter

__all__ = ["FAULT_HEALTH", "DeviceApp", "DeviceCore", "DeviceEndpoint", "EndpointStats",
           "Engine"]

log = logging.getLogger(__name__)

#: Requests that call the application, held while the engine computes. CONFIG_GET,
#: CONFIG_SET, SCAN_START and CALIBRATE do only when no stream runs: during one they are
#: answered at once from its state (STATUS_GET, RESEND, SCAN_ABORT always are).
_APP = frozenset({MsgType.HELLO, MsgType.POWER_SET, MsgType.POWER_GET, MsgType.CAPTURE})
_APP_IDLE = frozenset({MsgType.CONFIG_GET, MsgType.CONFIG_SET, MsgType.SCAN_START,
                       MsgType.CALIBRATE})
#: A HEARTBEAT goes this share of heartbeat_s after the last, so that the gap between
#: stream frames stays within INFO.heartbeat_ms with the loop up to half of it late.
_HEARTBEAT_EARLY = 0.5
#: Requests remembered for retransmission replay.
_REPLAY_DEPTH = 32
#: STATUS.faults bit set by the endpoint when the application's health() fails.
FAULT_HEALTH = 0x8000_0000
#: Bytes of columns the loop sends per poll while a stream runs before it reads again.
_POLL_BYTES = 4096
#: An engine step this young (s) is waited for (``poll_s`` at a time) rather than the
#: port: most steps are quicker.
_QUICK_STEP_S = 0.05


class DeviceApp(abc.ABC):
    """What a device application implements behind a :class:`DeviceEndpoint`.

    Methods are called one at a time: the scan generator and :meth:`abort` in the
    device's :class:`~cdma_lidar.protocol.streams.Engine`, the others in a connection's
    loop while the engine is idle, so a generator may take long per column. Refuse a
    request by raising ``ConfigError(message, field=name)`` (answered NAK OUT_OF_RANGE
    naming the field) or ``DeviceError(message, code=ErrorCode..., field=...)``.
    """

    @abc.abstractmethod
    def info(self) -> Info:
        """Identity, limits and nominal geometry (link fields are filled by the endpoint)."""

    @abc.abstractmethod
    def get_config(self) -> dict[str, Any]:
        """Current configuration ``{key name: python value}`` (see CONFIG_KEYS)."""

    @abc.abstractmethod
    def set_config(self, values: dict[str, Any]) -> None:
        """Apply all of ``values`` or none of them (validate first)."""

    @abc.abstractmethod
    def scan(self, frame: int, first_column: int, columns: int) -> Iterator[ColumnResult]:
        """Start a scan: validate now (raise to NAK), then yield columns in order."""

    def calibrate(self, frame: int, shots: int) -> Iterator[ColumnResult]:
        """Start a zeroth-order calibration: yield ``shots`` columns (column = shot)."""
        raise DeviceError("calibration not supported", code=ErrorCode.UNKNOWN_TYPE)

    def set_power(self, channel_start: int, column_start: int,
                  power: NDArray[np.uint16]) -> None:
        """Store a (channels, columns) rectangle of the power matrix (1/65535 of max)."""
        raise DeviceError("power control not supported", code=ErrorCode.UNKNOWN_TYPE)

    def get_power(self) -> NDArray[np.uint16]:
        """The whole (K, C) power matrix (1/65535 of max), for POWER_GET and session resets."""
        raise DeviceError("power read-back not supported", code=ErrorCode.NOT_AVAILABLE)

    def capture(self, kind: CaptureKind, column: int, channel: int) -> NDArray[np.integer]:
        """Debug data of one column: raw ADC codes (RAW) or a correlation trace (CORR)."""
        raise DeviceError("capture not supported", code=ErrorCode.NOT_AVAILABLE)

    def abort(self) -> None:  # noqa: B027 - optional hook, default does nothing
        """Called when a running scan or calibration is stopped early."""

    def health(self) -> tuple[int, int]:
        """(temperature in m°C or TEMPERATURE_UNKNOWN, fault bits). Called while a scan
        runs: read state only, never block."""
        return TEMPERATURE_UNKNOWN, 0

    def column_time_s(self) -> float:
        """Longest the next column may take with the current configuration (s), batching
        included; 0.0: not stated. STATUS and every HEARTBEAT carry it, and the host's
        no-progress limit follows it. Called while a scan runs: read state only, never
        block."""
        return 0.0


class DeviceEndpoint:
    """Protocol engine of one connection to the device. See the module docstring.

    Args:
        port: port-like object (``read``, ``write``, ``in_waiting``, ``timeout``).
        app: the device application, unless ``core`` is given: the device state that
            several connections share; else one is made of ``app``, ``key``,
            ``session_idle_s`` and ``engine`` (:class:`DeviceCore`).
        session_id: the first session's id (u32; 0 or None: random; later ones random).
        max_frame: largest frame this end sends or accepts (bytes, 256..65535).
        ring_columns: recent columns kept for RESEND.
        heartbeat_s: HEARTBEAT interval while scanning (s).
        poll_s: longest blocking read when idle (s, 0..1; 0: never block, for a caller
            that steps the device itself).
        fec: accept Reed-Solomon coded frames and code a session whose HELLO asks for it
            (a serial line; False on TCP: a damaged frame is not worth the CPU).
        peer: the other end (an IP address) in the log; default the port's name.
        clock: monotonic clock (s), replaceable in tests.
    """

    def __init__(self, port: Any, app: DeviceApp | None = None, *,
                 core: DeviceCore | None = None, key: bytes | None = None,
                 engine: Engine | None = None, session_id: int | None = None,
                 session_idle_s: float = 10.0, max_frame: int = 16384,
                 ring_columns: int = 1024, heartbeat_s: float = 0.2, poll_s: float = 0.01,
                 peer: str | None = None, fec: bool = True,
                 clock: Callable[[], float] = time.monotonic) -> None:
        self.decoder = FrameDecoder(max_frame, fec=fec)  # checks max_frame
        check_int("ring_columns", ring_columns, 0, 65535)
        if not 0.001 <= heartbeat_s <= 65.535:
            raise out_of_range("heartbeat_s", "0.001 to 65.535 s (INFO.heartbeat_ms)",
                               heartbeat_s)
        if not 0 <= poll_s <= 1:
            raise out_of_range("poll_s", "0 to 1 s", poll_s)
        if session_id is not None:
            check_int("session_id", session_id, 0, 0xFFFFFFFF)
        self._own_core = core is None
        if core is None:
            if app is None:
                raise out_of_range("app", "a DeviceApp (or a DeviceCore)", app)
            core = DeviceCore(app, key=key, session_idle_s=session_idle_s, clock=clock,
                              engine=engine)
        self.core, self.app, self.port = core, core.app, port
        self.clock, self.heartbeat_s, self.poll_s = clock, heartbeat_s, poll_s
        self.stats = EndpointStats()
        self.tx = Transmitter(port, max_frame, (self.stats, core.totals))
        self.streams = Streams(core.app, self.tx, core.engine, ring_columns=ring_columns,
                               clock=clock, stopped=lambda: core.touch(self.session))
        self.session = DeviceSession(core, self.tx, self.streams, self.stats,
                                     session_id=session_id, max_frame=max_frame, fec=fec,
                                     heartbeat_s=heartbeat_s, peer=peer or port_name(port))
        self.handlers: dict[MsgType, Callable[[Frame, dict], Reply]] = {
            **self.session.handlers(), **self.streams.handlers(),
            MsgType.STATUS_GET: lambda req, f: self.tx.reply(
                req, MsgType.STATUS, encode_payload(MsgType.STATUS, self.status().to_fields()))}
        #: seq -> (CRC of the request's type and payload, its reply), for replay.
        self._replay: OrderedDict[int, tuple[int, Reply]] = OrderedDict()
        self.last_seq: int | None = None
        self._pieces = Joiner(limit=2)  # requests in FRAGMENTs, by (type, seq, session)
        port.timeout = poll_s

    def serve_forever(self, stop: threading.Event) -> None:
        """Poll until ``stop`` is set or the port fails (logged); then stop any stream."""
        try:
            while not stop.is_set():
                self.poll()
        except (OSError, ValueError, TypeError) as exc:  # a closed pty or pyserial port
            if not stop.is_set():
                log.warning("device endpoint stops: port failed (%s)", exc)
        finally:
            self.close()

    def close(self) -> None:
        """End this connection's session and its stream (no SCAN_END); let the engine's
        thread go if this endpoint made it. The port is left open."""
        self.session.end()
        if self._own_core:
            self.core.engine.close()

    def poll(self) -> None:
        """One turn of the connection's loop: read what arrived (blocking at most
        ``poll_s`` when there is nothing to do), answer requests, take a computed column,
        serve held requests at a column boundary, hand the engine the next column, send
        a heartbeat when due, send what is queued. Never waits for the application."""
        sess, streams = self.session, self.streams
        if sess.lost is not None:  # another connection's HELLO took the device
            sess.lose(*sess.lost)
        ds = self.decoder.stats
        damaged, frames, errors = ds.damaged, ds.frames, ds.errors
        received = self.decoder.feed(self._read())
        self.core.rx_frames += ds.frames - frames  # before a STATUS reply says them
        self.core.rx_errors += ds.errors - errors
        for frame in received:
            if frame.msg_type == MsgType.FRAGMENT:
                frame = self._request_piece(frame)  # None until the request is whole
            if frame is not None and kind_of(frame.msg_type) is not MsgKind.REQUEST:
                self.stats.ignored += 1
            elif frame is not None:
                self._process(frame)
        while self.decoder.rejected:
            self._on_rejected(self.decoder.rejected.pop(0))
        if ds.damaged > damaged:
            # Say so at once (information only: it words the host's diagnosis).
            self.tx.send(CONTROL, MsgType.LINE_ERROR, encode_payload(
                MsgType.LINE_ERROR, {"rx_errors": self.core.rx_errors & 0xFFFFFFFF}))
        streams.collect()
        while sess.held and sess.ready:
            self._respond(*sess.held.pop(0))
        if not sess.held:  # held requests go before the next column
            streams.advance()
            streams.collect()  # done at once when the engine is quick (or not threaded)
        now = self.clock()
        if streams.stream is not None and \
                now - streams.last_heartbeat >= _HEARTBEAT_EARLY * self.heartbeat_s:
            streams.last_heartbeat = now
            self.tx.send(CONTROL, MsgType.HEARTBEAT,
                         encode_payload(MsgType.HEARTBEAT, self.status().to_fields()))
        self.tx.flush(_POLL_BYTES if streams.stream is not None else None)

    def _read(self) -> bytes:
        """What arrived; when nothing has, blocks (up to ``poll_s``) only when there is
        nothing to send and no column to hand over, or waits for a young engine step
        (``_QUICK_STEP_S``)."""
        n, st = self.port.in_waiting, self.streams.stream
        job = self.streams.latest and self.streams.latest.job
        quick = job is not None and time.monotonic() - job.started < _QUICK_STEP_S
        busy = (st is not None and job is None) or self.tx.pending()  # a column or a frame
        if not n and ((quick and wait([job], self.poll_s).done) or busy):
            return b""
        data = self.port.read(n or 1)
        if data and self.port.in_waiting:
            data += self.port.read(self.port.in_waiting)
        return data

    def status(self) -> Status:
        """Current status (as sent in STATUS and HEARTBEAT); counters since boot."""
        st, last = self.streams.stream, self.streams.latest  # running, last started
        try:
            temp, faults = self.app.health()
        except Exception:  # a health sensor must not take the link down
            log.exception("application health() failed")
            temp, faults = TEMPERATURE_UNKNOWN, FAULT_HEALTH
        core, totals, mask = self.core, self.core.totals, 0xFFFFFFFF
        return Status(
            state=(State.IDLE if st is None else
                   State.CALIBRATING if st.calibration else State.SCANNING),
            frame=(last.frame if last else 0) & mask,
            next_column=(last.next_column - self.tx.fresh_pending() if last else 0) & 0xFFFF,
            last_end=int(self.streams.last_end), columns_sent=totals.columns_sent & mask,
            uptime_ms=int((self.clock() - core.booted) * 1000) & mask,
            rx_frames=core.rx_frames & mask, rx_errors=core.rx_errors & mask,
            tx_frames=totals.tx_frames & mask, replays=totals.replays & mask,
            temperature_mc=temp, faults=faults & mask,
            column_time_ms=min(math.ceil(self.app.column_time_s() * 1000), mask))

    # ---- receiving ------------------------------------------------------------------
    def _on_rejected(self, frame: Frame) -> None:
        """NAK VERSION a request of another version (in its version, so that an older host
        reads it: the header and the NAK payload are laid out alike in every version), NAK
        UNSUPPORTED_FLAGS one with unknown incompat flags."""
        if kind_of(frame.msg_type) is not MsgKind.REQUEST:
            return
        if frame.version != PROTOCOL_VERSION:
            nak = (ErrorCode.VERSION, "version",
                   f"device speaks protocol version {PROTOCOL_VERSION}")
        else:
            nak = (ErrorCode.UNSUPPORTED_FLAGS, "incompat_flags",
                   f"unknown incompat flags 0x{frame.incompat:02x}")
        self.tx.answer(frame, self.tx.nak(frame, *nak, False))

    def _request_piece(self, frame: Frame) -> Frame | None:
        """Keep one FRAGMENT of a request (at most two requests kept); the whole request once
        every piece is in, ``joined`` (checked) if each was :meth:`~DeviceSession.verified`
        (a forged piece is dropped; an unchecked request is answered as an unsigned one)."""
        good = self.session.verified(frame)
        if good is None:
            return None
        try:
            body = decode_payload(MsgType.FRAGMENT, frame.payload)
        except FrameError:
            body = None
        if body is None or kind_of(body["msg_type"]) is not MsgKind.REQUEST:
            self.stats.ignored += 1
            return None
        whole = self._pieces.add(frame, body, (body["msg_type"], body["seq"], frame.session),
                                 good)
        return None if whole is None else whole[0]

    def _process(self, frame: Frame) -> None:
        """Check one request; answer, replay, drop or hold it."""
        self.stats.rx_requests += 1
        is_hello, sess = frame.msg_type == MsgType.HELLO, self.session
        if not is_hello and not sess.admit(frame):
            return
        key = zlib.crc32(bytes([frame.msg_type]) + frame.payload)
        cached = self._replay.get(frame.seq)
        if cached is not None and cached[0] == key:
            self.stats.replays += 1
            self.core.totals.replays += 1
            self.tx.answer(frame, cached[1])
            return
        if any(h.seq == frame.seq and k == key for h, k in sess.held):
            return  # a retransmission of a held request: its reply comes
        if is_hello:
            refusal = sess.hello_gate(frame)  # at once, whatever the engine computes
            if refusal is not None:
                self._respond(frame, key, refusal)
                return
        elif self.last_seq is not None and 0 < (self.last_seq - frame.seq) & 0xFFFF < 0x8000:
            self.stats.stale += 1
            log.debug("dropped stale request seq %d (last %d)", frame.seq, self.last_seq)
            return
        else:
            self.last_seq = frame.seq  # in arrival order, held or answered
        t = frame.msg_type
        if (t in _APP or (t in _APP_IDLE and self.streams.stream is None)) and \
                (sess.held or not sess.ready):
            sess.held.append((frame, key))
        else:
            self._respond(frame, key)

    def _respond(self, frame: Frame, key: int, reply: Reply | None = None) -> None:
        """Act on one request (or send ``reply``, decided already), cache and send its
        reply; end the session after the ACK of SESSION_END."""
        try:
            if reply is None:
                handler = self.handlers.get(frame.msg_type)  # type: ignore[call-overload]
                if handler is None:
                    raise DeviceError(f"{type_name(frame.msg_type)} is not a request this "
                                      "device knows", ErrorCode.UNKNOWN_TYPE, "msg_type")
                reply = handler(frame, decode_payload(frame.msg_type, frame.payload))
        except (FrameError, DeviceError, ConfigError) as exc:
            code = ErrorCode.MALFORMED if isinstance(exc, FrameError) else \
                exc.code if isinstance(exc, DeviceError) else ErrorCode.OUT_OF_RANGE
            reply = self.tx.nak(frame, ErrorCode(code) if code in set(ErrorCode) else
                                ErrorCode.INTERNAL, exc.field or "", str(exc))
        except Exception as exc:  # the device must never die on a request
            log.exception("device application failed on %s", type_name(frame.msg_type))
            reply = self.tx.nak(frame, ErrorCode.INTERNAL, "", f"{type(exc).__name__}: {exc}")
        if reply[0] == MsgType.INFO:  # a new session: its requests count afresh
            self._replay.clear()
            self.last_seq = None
        self._replay[frame.seq] = (key, reply)
        self._replay.move_to_end(frame.seq)
        while len(self._replay) > _REPLAY_DEPTH:
            self._replay.popitem(last=False)
        self.tx.answer(frame, reply)
        if frame.msg_type == MsgType.SESSION_END and reply[0] == MsgType.ACK:
            self.session.end()
            log.info("session 0x%08x ended by its host", self.session.id)
