"""Device end of the link: one :class:`DeviceEndpoint` per connection, in front of a
:class:`DeviceApp` (e.g. ``cdma_lidar.virtual.board``), which only answers decoded
requests and produces columns.

What a request goes through (docs/protocol.md, Device behaviour)::

    port bytes -> FrameDecoder -> damaged chunk? --> LINE_ERROR at once
    request -> session ok? --no--> NAK WRONG_SESSION (HELLO always passes)
            -> signed session: MAC and counter ok? --no--> dropped (unsigned: NAK AUTH_REQUIRED)
            -> same seq + same bytes as a cached request? --yes--> the stored reply again
            -> older seq than the last? --yes--> dropped as stale
            -> needs the application? --yes--> request worker thread (in arrival order)
            -> handler -> reply (:mod:`~cdma_lidar.protocol.transmit`) with the request's seq

The polling thread answers STATUS_GET, RESEND and SCAN_ABORT and sends a HEARTBEAT
every ``heartbeat_s / 2`` while a stream runs, whatever the application computes; the
application is called by one thread at a time. Run :meth:`DeviceEndpoint.serve_forever`
in a thread behind any port-like object (``read(n)``, ``write(b)``, ``in_waiting``,
``timeout``).
"""

from __future__ import annotations

import abc
import logging
import math
import queue
import threading
import time
import zlib
from collections import OrderedDict
from collections.abc import Callable, Iterator
from typing import Any

import numpy as np
from numpy.typing import NDArray

from cdma_lidar.checks import check_int
from cdma_lidar.errors import ConfigError, DeviceError, FrameError, out_of_range
from cdma_lidar.protocol.columns import ColumnResult
from cdma_lidar.protocol.device_sessions import (
    DeviceCore,
    DeviceSession,
    EndpointStats,
    new_session_id,
)
from cdma_lidar.protocol.framing import (
    FRAME_LIMIT,
    MIN_MAX_FRAME,
    PROTOCOL_VERSION,
    Frame,
    FrameDecoder,
)
from cdma_lidar.protocol.handlers import AppRequests
from cdma_lidar.protocol.messages import (
    CaptureKind,
    ErrorCode,
    MsgKind,
    MsgType,
    Pieces,
    ScanEndReason,
    decode_payload,
    encode_payload,
    kind_of,
    type_name,
)
from cdma_lidar.protocol.ports import port_name
from cdma_lidar.protocol.streams import Streams
from cdma_lidar.protocol.transmit import CONTROL, FRESH, REPAIR, Reply, Transmitter
from cdma_lidar.protocol.views import TEMPERATURE_UNKNOWN, Info, State, Status

__all__ = ["FAULT_HEALTH", "DeviceApp", "DeviceCore", "DeviceEndpoint",
           "EndpointStats"]

log = logging.getLogger(__name__)

# Requests answered without calling the application (never wait for a column to compute).
_WITHOUT_APP = frozenset({MsgType.STATUS_GET, MsgType.RESEND, MsgType.SCAN_ABORT})
# Requests answered NAK BUSY from the stream's state while it runs (their handlers check
# it before they call the application).
_BUSY_WHILE_SCANNING = frozenset({MsgType.CONFIG_SET, MsgType.SCAN_START, MsgType.CALIBRATE})
#: A HEARTBEAT goes out this share of heartbeat_s after the last one, so that the gap
#: between stream frames stays within INFO.heartbeat_ms when the polling thread runs late
#: (by up to half of it: a loaded machine).
_HEARTBEAT_EARLY = 0.5
#: Requests remembered for retransmission replay.
_REPLAY_DEPTH = 32
#: STATUS.faults bit set by the endpoint when the application's health() fails.
FAULT_HEALTH = 0x8000_0000
#: Repair bytes the polling thread sends per poll while a column worker runs (it then
#: reads again; the worker sends the rest between its columns' frames).
_POLL_REPAIR_BYTES = 2048


class DeviceApp(abc.ABC):
    """What a device application implements behind a :class:`DeviceEndpoint`.

    Methods are called one at a time (the endpoint serialises them), though not always
    from the same thread: the scan generator and :meth:`abort` run in the endpoint's
    column worker. A generator may take long per column: meanwhile the endpoint keeps
    answering STATUS_GET, RESEND and SCAN_ABORT and sending heartbeats; other requests
    wait for the column in progress. Refuse a request by raising
    ``ConfigError(message, field=name)`` (answered NAK OUT_OF_RANGE naming the field) or
    ``DeviceError(message, code=ErrorCode..., field=...)``.
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
        """(temperature in m°C or TEMPERATURE_UNKNOWN, fault bits)."""
        return TEMPERATURE_UNKNOWN, 0

    def column_time_s(self) -> float:
        """Longest the next column may take with the current configuration (s), batching
        included; 0.0: not stated. STATUS and every HEARTBEAT carry it, and the host's
        no-progress limit follows it. Called while a scan runs, without the serialising
        lock: read state only, never block."""
        return 0.0


class DeviceEndpoint:
    """Protocol engine of one connection to the device. See the module docstring.

    Args:
        port: port-like object (``read``, ``write``, ``in_waiting``, ``timeout``).
        app: the device application (ignored when ``core`` is given).
        core: shared device state when several connections serve one device.
        key: shared secret for a new core (see :class:`DeviceCore`).
        session_id: id of the first session (u32, not 0); random when None. Every
            later HELLO gets a fresh random id.
        session_idle_s: idle time after which another host may take the session (s).
        max_frame: largest frame this end sends or accepts (bytes, 256..65535).
        ring_columns: recent columns kept for RESEND.
        heartbeat_s: HEARTBEAT interval while scanning (s).
        poll_s: longest blocking read when idle (s).
        fec: accept Reed-Solomon coded frames and code a session whose HELLO asks for it
            (a serial line); False on TCP, where a damaged frame is not worth the CPU.
        peer: who is on the other end (an IP address), for the log of failed
            authentication; default the port's name.
        clock: monotonic clock (s), replaceable in tests.
        threads: False: no worker threads; each :meth:`poll` also handles the queued
            requests and one column of a running stream (tests step the device with
            an injected clock; ``poll_s`` may then be 0).
    """

    def __init__(self, port: Any, app: DeviceApp | None = None, *,
                 core: DeviceCore | None = None, key: bytes | None = None,
                 session_id: int | None = None, session_idle_s: float = 10.0,
                 max_frame: int = 16384, ring_columns: int = 1024, heartbeat_s: float = 0.2,
                 poll_s: float = 0.01, peer: str | None = None,
                 fec: bool = True, clock: Callable[[], float] = time.monotonic,
                 threads: bool = True) -> None:
        check_int("max_frame", max_frame, MIN_MAX_FRAME, FRAME_LIMIT)
        check_int("ring_columns", ring_columns, 0, 65535)
        if not 0.001 <= heartbeat_s <= 65.535:
            raise out_of_range("heartbeat_s", "0.001 to 65.535 s (INFO.heartbeat_ms)",
                               heartbeat_s)
        if not (0 < poll_s <= 1 or (poll_s == 0 and not threads)):
            raise out_of_range("poll_s", "above 0 and at most 1 s (0 would spin; allowed "
                               "with threads=False)", poll_s)
        if session_id is not None:  # 0 or None: random
            check_int("session_id", session_id, 0, 0xFFFFFFFF)
        if core is None:
            if app is None:
                raise out_of_range("app", "a DeviceApp (or a DeviceCore)", app)
            core = DeviceCore(app, key=key, session_idle_s=session_idle_s, clock=clock)
        self.core, self.app, self.port = core, core.app, port
        self.clock, self.threads = clock, threads
        self.heartbeat_s = heartbeat_s
        self.decoder = FrameDecoder(max_frame, fec=fec)
        self.stats = EndpointStats()
        self.tx = Transmitter(port, session_id or new_session_id(), max_frame,
                              (self.stats, core.totals))
        # lock guards the connection's state (its session, streams, replay cache); the
        # core's app_lock serialises calls into the application and is always taken first.
        self.lock = threading.Lock()
        self.streams = Streams(core.app, self.tx, core.app_lock, self.lock,
                               ring_columns=ring_columns, threads=threads, clock=clock,
                               counted=self._count_column,
                               stopped=lambda: core.touch(self.session))
        self.requests = AppRequests(core.app, self.tx, self.streams, self.status)
        self.session = DeviceSession(core, self.tx, self.streams, self.stats, self.lock,
                                     max_frame=max_frame, fec=fec, ring_columns=ring_columns,
                                     heartbeat_s=heartbeat_s, peer=peer or port_name(port),
                                     on_end=self._forget_capture)
        #: Request handler of each request type, ``(request, fields, after) -> reply``.
        self.handlers: dict[MsgType, Callable[[Frame, dict, list], Reply]] = {
            **self.session.handlers(), **self.streams.handlers(), **self.requests.handlers()}
        #: seq -> (CRC of the request's type and payload, its reply), for replay.
        self._replay: OrderedDict[int, tuple[int, Reply]] = OrderedDict()
        self.last_seq: int | None = None
        self._rx_counted = (0, 0)  # decoder (frames, errors) already in the core's totals
        #: Requests arriving in FRAGMENTs: (type, seq) -> the pieces so far.
        self._pieces: OrderedDict[tuple[int, int], Pieces] = OrderedDict()
        self._health = (TEMPERATURE_UNKNOWN, 0)
        self._queue: queue.SimpleQueue[tuple[Frame, bool] | None] = queue.SimpleQueue()
        self._queued = 0  # requests queued for the request worker and not yet handled
        self._worker: threading.Thread | None = None
        port.timeout = poll_s

    # What the TCP server and the tests read of the connection.
    @property
    def peer(self) -> str:
        """Who is on the other end (an IP address over TCP), for the logs."""
        return self.session.peer

    @property
    def session_open(self) -> bool:
        return self.session.open

    @property
    def sessionless_since(self) -> float:
        """Since when this connection has had no session (core clock, s)."""
        return self.session.sessionless_since

    def _forget_capture(self) -> None:
        self.requests.capture = None

    def serve_forever(self, stop: threading.Event) -> None:
        """Poll until ``stop`` is set or the port fails (logged); then stop any stream."""
        try:
            while not stop.is_set():
                try:
                    self.poll()
                except (OSError, ValueError, TypeError) as exc:
                    # A closed pty or pyserial port: the host side went away.
                    if not stop.is_set():
                        log.warning("device endpoint stops: port failed (%s)", exc)
                    break
        finally:
            self.close()

    def close(self) -> None:
        """Stop a running stream (no SCAN_END), end this connection's session, stop the
        request worker. The port is left open."""
        with self.lock:
            self.streams.stop(ScanEndReason.ABORTED, send_end=False)
            self.core.release(self.session)
            self.session.open = False
        if not self.threads and self.streams.latest is not None:  # no worker to end it
            with self.core.app_lock:
                self.streams.finish(self.streams.latest)
        if self._worker is not None:
            self._queue.put(None)
            if self._worker is not threading.current_thread():
                self._worker.join(timeout=5.0)
            self._worker = None

    def poll(self) -> None:
        """Read what arrived (blocking at most ``poll_s``), answer requests, send heartbeats.

        Never waits for the application: columns come from a stream worker and the
        requests that need the application from the request worker.
        """
        n = self.port.in_waiting
        data = self.port.read(n or 1)
        if data and not n and self.port.in_waiting:
            data += self.port.read(self.port.in_waiting)
        with self.lock:
            if data:
                damaged = self.decoder.stats.damaged
                for piece in self.decoder.feed(data):
                    frame = self._request_piece(piece) if piece.msg_type == MsgType.FRAGMENT \
                        else piece
                    # While the request worker has work, every request queues behind it,
                    # so requests are always handled in the order they arrived.
                    if frame is None:
                        continue
                    if kind_of(frame.msg_type) is not MsgKind.REQUEST:
                        self.stats.ignored += 1
                    elif self._queued:
                        self._enqueue(frame, False)
                    else:
                        self._process(frame, False)
                while self.decoder.rejected:
                    self._on_rejected(self.decoder.rejected.pop(0))
                self._count_rx()
                if self.decoder.stats.damaged > damaged:
                    # Say so at once (information only: it words the host's diagnosis).
                    self.tx.send(CONTROL, MsgType.LINE_ERROR, encode_payload(
                        MsgType.LINE_ERROR, {"rx_errors": self.decoder.stats.errors
                                             & 0xFFFFFFFF}))
            now, streams = self.clock(), self.streams
            if streams.stream is not None and \
                    now - streams.last_heartbeat >= _HEARTBEAT_EARLY * self.heartbeat_s:
                streams.last_heartbeat = now
                self.tx.send(CONTROL, MsgType.HEARTBEAT,
                               encode_payload(MsgType.HEARTBEAT, self.status().to_fields()))
            worker = streams.stream is not None
        # Replies and notices now; repairs in a bounded share while a column worker runs
        # (it sends the rest); everything when no stream runs.
        self.tx.flush(REPAIR if worker else FRESH, _POLL_REPAIR_BYTES if worker else None)
        if not self.threads:  # what the workers would do meanwhile
            while not self._queue.empty():
                item = self._queue.get()
                assert item is not None
                self._serve_one(*item)
            if streams.latest is not None and not streams.latest.finished:
                streams.step(streams.latest)

    def _count_rx(self) -> None:
        """Add what the decoder counted since the last call to the core's totals."""
        ds, (frames, errors) = self.decoder.stats, self._rx_counted
        self.core.rx_frames += ds.frames - frames
        self.core.rx_errors += ds.errors - errors
        self._rx_counted = (ds.frames, ds.errors)

    def _count_column(self) -> None:
        """One more COLUMN_RESULT queued (new or resent)."""
        self.stats.columns_sent += 1
        self.core.totals.columns_sent += 1

    def status(self) -> Status:
        """Current status (as sent in STATUS and HEARTBEAT); counters since boot."""
        self._count_rx()
        st, streams = self.streams.stream, self.streams
        if self.core.app_lock.acquire(blocking=False):  # else: the last reading
            try:
                self._health = self.app.health()
            except Exception:  # a health sensor must not take the link down
                log.exception("application health() failed")
                self._health = (TEMPERATURE_UNKNOWN, FAULT_HEALTH)
            finally:
                self.core.app_lock.release()
        temp, faults = self._health
        core, mask = self.core, 0xFFFFFFFF
        return Status(
            state=(State.IDLE if st is None else
                   State.CALIBRATING if st.calibration else State.SCANNING),
            frame=(st.frame if st else streams.last_frame) & mask,
            next_column=(st.next_column - self.tx.fresh_pending() if st else streams.last_next)
            & 0xFFFF,
            last_end=int(streams.last_end),
            columns_sent=core.totals.columns_sent & mask,
            uptime_ms=int((self.clock() - core.booted) * 1000) & mask,
            rx_frames=core.rx_frames & mask, rx_errors=core.rx_errors & mask,
            tx_frames=core.totals.tx_frames & mask, replays=core.totals.replays & mask,
            temperature_mc=temp, faults=faults & mask,
            column_time_ms=min(math.ceil(self.app.column_time_s() * 1000), mask))

    # ---- receiving ------------------------------------------------------------------
    def _send_reply(self, req: Frame, reply: Reply) -> None:
        # A coded request gets a coded reply.
        self.tx.send(CONTROL, reply[0], reply[1], req.seq, coded=self.tx.coded or req.fec,
                     signer=self.tx.signer if reply[2] else None)

    def _on_rejected(self, frame: Frame) -> None:
        if kind_of(frame.msg_type) is not MsgKind.REQUEST:
            return
        if frame.version != PROTOCOL_VERSION:
            # In the requester's version, so that an older host reads it: the header and
            # the NAK payload are laid out alike in every version.
            reply = self.tx.nak(frame, ErrorCode.VERSION, "version",
                        f"device speaks protocol version {PROTOCOL_VERSION}", False)
            self.tx.put(CONTROL, MsgType.NAK, reply[1], frame.seq, signer=None,
                        coded=frame.fec, version=frame.version)
            return
        self._send_reply(frame, self.tx.nak(frame, ErrorCode.UNSUPPORTED_FLAGS, "incompat_flags",
                                    f"unknown incompat flags 0x{frame.incompat:02x}", False))

    def _request_piece(self, frame: Frame) -> Frame | None:
        """Keep one FRAGMENT of a request (checked as it comes: a piece of this session's
        signed requests with a bad signature is dropped); the whole request once every
        piece is in, keyed by (type, seq). Two requests in pieces are kept at most."""
        sess = self.session
        ours = sess.open and frame.session == sess.id
        if ours and sess.verifier is not None and not sess.verifier.check(frame):
            self.stats.auth_rejected += 1
            return None
        try:
            body = decode_payload(MsgType.FRAGMENT, frame.payload)
        except FrameError:
            self.stats.ignored += 1
            return None
        if kind_of(body["msg_type"]) is not MsgKind.REQUEST:
            self.stats.ignored += 1
            return None
        key = (body["msg_type"], body["seq"])
        pc = self._pieces.get(key)
        if pc is None or pc.count != body["count"]:
            pc = self._pieces[key] = Pieces(body["count"])
            while len(self._pieces) > 2:
                self._pieces.popitem(last=False)
        if (payload := pc.add(frame, body)) is None:
            return None
        del self._pieces[key]
        return Frame(key[0], key[1], frame.session, payload, fec=frame.fec, joined=ours)

    def _enqueue(self, frame: Frame, checked: bool) -> None:
        self._queued += 1
        if self._worker is None and self.threads:
            self._worker = threading.Thread(target=self._serve_requests, daemon=True,
                                            name="cdma-lidar-requests")
            self._worker.start()
        self._queue.put((frame, checked))

    def _process(self, frame: Frame, in_worker: bool) -> None:
        """Check one request and answer, replay, drop or (poll thread) queue it."""
        self.stats.rx_requests += 1
        is_hello, sess = frame.msg_type == MsgType.HELLO, self.session
        if not is_hello:
            if not sess.open or frame.session != sess.id:
                detail = (f"this connection's session is 0x{sess.id:08x}; send HELLO"
                          if sess.open else "no session is open here: send HELLO")
                refusal = self.tx.nak(frame, ErrorCode.WRONG_SESSION, "session", detail, False)
                sid, signer, verifier = sess.ended or (None, None, None)
                if frame.session == sid and verifier is not None and verifier.check(frame):
                    # A request of the signed session that ended here: its host hears it
                    # signed with that session's key (it drops unsigned frames).
                    self.tx.send(CONTROL, MsgType.NAK, refusal[1], frame.seq, signer=signer,
                                 coded=self.tx.coded or frame.fec)
                else:
                    self._send_reply(frame, refusal)
                return
            if sess.verifier is not None and not frame.joined:
                if not frame.sig:
                    self._send_reply(frame, self.tx.nak(
                        frame, ErrorCode.AUTH_REQUIRED, "incompat_flags",
                        "this device accepts only signed frames: HELLO with its key", False))
                    return
                if not sess.verifier.check(frame):  # forged or replayed: no answer at all
                    self.stats.auth_rejected += 1
                    self.core.backoff.failed(f"{sess.peer} (session frames)",
                                             "a frame failed authentication")
                    return
            self.core.touch(sess)
        key = zlib.crc32(bytes([frame.msg_type]) + frame.payload)
        cached = self._replay.get(frame.seq)
        if cached is not None and cached[0] == key:
            self.stats.replays += 1
            self.core.totals.replays += 1
            self._send_reply(frame, cached[1])
            return
        if not is_hello and self.last_seq is not None:
            age = (self.last_seq - frame.seq) & 0xFFFF
            if 0 < age < 0x8000:
                self.stats.stale += 1
                log.debug("dropped stale request seq %d (last %d)", frame.seq, self.last_seq)
                return
        if is_hello and not in_worker:
            try:  # the gate's answer, at once whatever the application is computing
                refusal = sess.hello_gate(frame, decode_payload(MsgType.HELLO, frame.payload))
            except FrameError:
                refusal = None  # the worker NAKs it MALFORMED
            if refusal is not None:
                self._respond(frame, key, refusal)
                return
        if in_worker or frame.msg_type in _WITHOUT_APP or (self.streams.stream is not None and (
                frame.msg_type in _BUSY_WHILE_SCANNING or frame.msg_type == MsgType.CONFIG_GET)):
            self._respond(frame, key)
        else:
            self._enqueue(frame, True)

    def _serve_requests(self) -> None:
        """Request worker: handles, in order, the requests that need the application."""
        while True:
            item = self._queue.get()
            if item is None or not self._serve_one(*item):
                return

    def _serve_one(self, frame: Frame, checked: bool) -> bool:
        """Handle one queued request; False when the port went away."""
        try:
            with self.core.app_lock, self.lock:
                self._queued -= 1
                if checked:
                    self._respond(frame, zlib.crc32(bytes([frame.msg_type]) + frame.payload))
                else:
                    self._process(frame, True)
                idle = self.streams.stream is None
            self.tx.flush(FRESH if idle else CONTROL)
        except OSError as exc:
            log.warning("request worker stops: %s", exc)
            return False
        except Exception:  # a bug must not take the device off the line
            log.exception("request worker failed on %s", type_name(frame.msg_type))
        return True

    def _respond(self, frame: Frame, key: int, reply: Reply | None = None) -> None:
        """Act on one request (or send ``reply``, decided already), cache and send its
        reply, then run what the handler left for after it (caller holds the lock)."""
        after: list[Callable[[], None]] = []
        try:
            if reply is None:
                handler = self.handlers.get(frame.msg_type)  # type: ignore[call-overload]
                if handler is None:
                    raise DeviceError(f"{type_name(frame.msg_type)} is not a request this "
                                      "device knows", ErrorCode.UNKNOWN_TYPE, "msg_type")
                reply = handler(frame, decode_payload(frame.msg_type, frame.payload), after)
        except FrameError as exc:
            reply = self.tx.nak(frame, ErrorCode.MALFORMED, exc.field or "", str(exc))
        except (DeviceError, ConfigError) as exc:
            code = exc.code if isinstance(exc, DeviceError) else ErrorCode.OUT_OF_RANGE
            reply = self.tx.nak(frame, ErrorCode(code) if code in set(ErrorCode) else
                        ErrorCode.INTERNAL, exc.field or "", str(exc))
            after.clear()
        except Exception as exc:  # the device must never die on a request
            log.exception("device application failed on %s", type_name(frame.msg_type))
            reply = self.tx.nak(frame, ErrorCode.INTERNAL, "", f"{type(exc).__name__}: {exc}")
            after.clear()
        if frame.msg_type == MsgType.HELLO:
            if reply[0] == MsgType.INFO:  # a new session: its requests count afresh
                self._replay.clear()
                self.last_seq = None
        else:
            self.last_seq = frame.seq
        self._replay[frame.seq] = (key, reply)
        self._replay.move_to_end(frame.seq)
        while len(self._replay) > _REPLAY_DEPTH:
            self._replay.popitem(last=False)
        self._send_reply(frame, reply)
        for action in after:
            try:
                action()
            except OSError:
                raise  # the port failed
            except Exception:  # a bug must not take the device off the line
                log.exception("action after %s failed", type_name(frame.msg_type))
