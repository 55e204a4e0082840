"""Device end of the link: sessions, signing, ACK/NAK, replay cache, fragments, column ring.

The device application (:class:`DeviceApp`, e.g. ``cdma_lidar.virtual.board`` for the
virtual device) only answers decoded requests and produces columns.
:class:`DeviceEndpoint` does everything that touches the wire::

    port bytes -> FrameDecoder -> damaged chunk? --> LINE_ERROR at once
                                     | a request
                 session ok? --no--> NAK WRONG_SESSION (HELLO always passes)
                                     | yes
          signed session: MAC and counter ok? --no--> dropped (unsigned: NAK AUTH_REQUIRED)
                                     | yes
         same seq + same bytes as a  --yes--> replay the stored reply (re-signed; act once)
         cached request?             | no
         older seq than the last?    --yes--> dropped as stale duplicate
                                     | no
        needs the application? --yes--> request worker (in arrival order)
                                     | no (STATUS_GET, RESEND, SCAN_ABORT, FRAME_SIZE, ...)
                 act -> reply (ACK / NAK / data; FRAGMENTs if long) with the request's seq

HELLO opens a session owned by one host (:class:`DeviceCore` knows the owner across
the connections of one device): another host gets NAK BUSY unless it takes over or
the session expired, and the old owner then gets SESSION_LOST. With a key, HELLO is a
challenge-response and every later frame is signed (:mod:`cdma_lidar.protocol.auth`).

While a scan or calibration runs, a worker thread pulls columns from the app's
generator, keeps each in a ring of recent columns for RESEND and sends it; the
polling thread meanwhile answers requests and sends a HEARTBEAT every
``heartbeat_s`` seconds, so the host hears from the device even while a column takes
long to compute. The application is only ever called by one thread at a time.

Frames leave through one transmit queue in three classes, each first-in first-out:
replies and notices (ACK, NAK, INFO, STATUS, HEARTBEAT, LINE_ERROR, SESSION_LOST)
first, then retransmitted columns, then new columns and SCAN_END. On a slow line
(a UART at 921600 baud sends a 1.6 kB column in 18 ms) a reply or a repair therefore
waits for at most the frame on the wire, not for the columns queued behind it.
Frames are encoded and signed when they go out, so the signature counters rise in
wire order whatever the class. The polling thread sends replies, notices and (a
bounded share of) repairs; the column worker sends everything, new columns last.

Run it in a thread behind any port-like object (``read(n)``, ``write(b)``,
``in_waiting``, ``timeout``): a pty or an accepted TCP socket
(:class:`cdma_lidar.protocol.ports.FdPort`), a pyserial port or an in-process pipe
(:class:`cdma_lidar.protocol.pipes.PipePort`)::

    stop = threading.Event()
    ep = DeviceEndpoint(port, app)
    threading.Thread(target=ep.serve_forever, args=(stop,), daemon=True).start()
"""

from __future__ import annotations

import abc
import dataclasses
import logging
import queue
import secrets
import threading
import time
import zlib
from collections import OrderedDict, deque
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

from cdma_lidar.checks import check_int
from cdma_lidar.errors import ConfigError, DeviceError, FieldError, FrameError, out_of_range
from cdma_lidar.protocol import auth
from cdma_lidar.protocol.columns import ColumnResult, column_payload_size, encode_column
from cdma_lidar.protocol.config_keys import CONFIG_KEYS, config_key, decode_config, encode_config
from cdma_lidar.protocol.framing import (
    COMPAT_RETRANSMIT,
    FRAME_LIMIT,
    MIN_MAX_FRAME,
    OVERHEAD,
    PROTOCOL_VERSION,
    Frame,
    FrameDecoder,
    encode_frame,
    frame_size,
)
from cdma_lidar.protocol.messages import (
    SCHEMA_CRC,
    Auth,
    CaptureKind,
    ErrorCode,
    HelloFlags,
    MsgKind,
    MsgType,
    ScanEndReason,
    SessionLostReason,
    State,
    decode_payload,
    encode_payload,
    kind_of,
)
from cdma_lidar.protocol.views import TEMPERATURE_UNKNOWN, Info, Status

__all__ = ["FAULT_HEALTH", "DeviceApp", "DeviceCore", "DeviceEndpoint", "EndpointStats"]

log = logging.getLogger(__name__)

_READ_ONLY = {k.name for k in CONFIG_KEYS if k.read_only}
_CAPTURE_HEADER = 18  # CAPTURE_DATA bytes before the data
#: FRAGMENT payload bytes before the data.
FRAGMENT_HEADER = 11
#: Most FRAGMENTs one message may take (FRAGMENT.count is 2..254).
MAX_PIECES = 254
# Requests answered without calling the application (never wait for a column to compute).
_WITHOUT_APP = frozenset({MsgType.STATUS_GET, MsgType.RESEND, MsgType.SCAN_ABORT,
                          MsgType.FRAME_SIZE})
#: STATUS.faults bit set by the endpoint when the application's health() fails.
FAULT_HEALTH = 0x8000_0000
#: Transmit classes, sent in this order: replies and notices, repairs, new columns.
_CONTROL, _REPAIR, _FRESH = 0, 1, 2
#: Repair bytes the polling thread sends per poll while a column worker runs (it then
#: reads again; the worker sends the rest between its columns' frames).
_POLL_REPAIR_BYTES = 2048


@dataclass(frozen=True)
class _Job:
    """One frame waiting to be sent; encoded (and signed) when it goes out."""

    msg_type: MsgType
    payload: bytes
    seq: int | None  # None: the next stream seq, taken when sent
    session: int
    compat: int
    max_frame: int
    signer: auth.FrameSigner | None
    repair: tuple[int, int, int] | None = None  # (frame, column, fragment or -1) of a repair
    coded: bool = False  # Reed-Solomon coded (the session's FEC, or a coded request's reply)
    version: int = PROTOCOL_VERSION  # another only for NAK VERSION to an older host


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


@dataclass
class EndpointStats:
    """Counters of a :class:`DeviceEndpoint`."""

    rx_requests: int = 0
    replays: int = 0
    stale: int = 0
    ignored: int = 0
    naks: int = 0
    tx_frames: int = 0
    columns_sent: int = 0
    resent: int = 0
    auth_rejected: int = 0  #: frames dropped for a wrong MAC or a replayed counter
    auth_throttled: int = 0  #: HELLO MACs not checked: the peer's back-off was running
    sessions: int = 0  #: sessions opened on this connection


@dataclass
class _Stream:
    gen: Iterator[ColumnResult]
    frame: int
    first: int
    count: int
    calibration: bool
    produced: int = 0
    stopped: bool = False  # set (under the endpoint lock) when the stream ends for any reason
    finished: bool = False  # generator closed and app.abort() called if due (under _app_lock)

    @property
    def next_column(self) -> int:
        return self.first + self.produced


#: A reply as cached for replay: (type, payload, signed). Encoded (and signed with a
#: fresh counter) each time it is sent.
_Reply = tuple[MsgType, bytes, bool]


@dataclass
class _Cached:
    key: int
    replies: list[_Reply] = field(default_factory=list)


class DeviceCore:
    """What every connection to one device shares: the application, its lock, the session.

    One device may be reached over several connections at once (the TCP server gives
    each its own :class:`DeviceEndpoint`) or by several hosts on one line. The core
    knows which host owns the session, since when and how long it has been idle, and
    holds the boot configuration (and power matrix, when the application can read it
    back) that a new session starts from.

    Args:
        app: the device application.
        key: shared secret (32 bytes, :mod:`cdma_lidar.protocol.auth`); None: no access
            control (serial ports, ptys, loopback with ``--insecure``).
        session_idle_s: a session idle this long (no request from its host, no stream
            running) may be taken by another host's HELLO without take-over (s).
        clock: monotonic clock (s).
    """

    def __init__(self, app: DeviceApp, *, key: bytes | None = None, session_idle_s: float = 10.0,
                 clock: Callable[[], float] = time.monotonic) -> None:
        if not 0.001 <= session_idle_s <= 4_294_967.295:
            raise out_of_range("session_idle_s", "0.001 to 4294967 s (INFO.session_idle_ms)",
                               session_idle_s)
        if key is not None and len(key) != auth.KEY_BYTES:
            raise out_of_range("key", f"{auth.KEY_BYTES} bytes", len(key))
        self.app = app
        self.key = key
        self.session_idle_s = float(session_idle_s)
        self.clock = clock
        #: Serialises every call into the application. Lock order: app_lock before any
        #: endpoint's _lock, never the reverse.
        self.app_lock = threading.RLock()
        self.owner: DeviceEndpoint | None = None
        self.owner_nonce = b""
        self.opened = 0.0
        self.last_active = 0.0
        self._boot: tuple[dict[str, Any], NDArray | None] | None = None
        self.backoff = auth.Backoff(clock)  # failed authentication, per peer
        #: Since boot (the core's creation), over every connection: what STATUS reports.
        self.booted = clock()
        self.totals = EndpointStats()
        self.rx_frames = self.rx_errors = 0

    def idle_s(self, now: float) -> float:
        """Seconds the owner's session has been idle (0 while it streams)."""
        if self.owner is None or self.owner.streaming:
            return 0.0
        return max(0.0, now - self.last_active)

    def touch(self, endpoint: DeviceEndpoint) -> None:
        """The owner was heard from (or its stream ended)."""
        if self.owner is endpoint:
            self.last_active = self.clock()

    def release(self, endpoint: DeviceEndpoint) -> None:
        """``endpoint``'s connection closed: its session ends at once."""
        if self.owner is endpoint:
            self.owner = None

    def snapshot(self) -> None:
        """Remember the boot configuration and power (caller holds app_lock), once."""
        if self._boot is None:
            power: NDArray | None
            try:
                power = np.array(self.app.get_power(), dtype=np.uint16)
            except DeviceError:
                power = None
            self._boot = (self.app.get_config(), power)

    def restore_defaults(self) -> None:
        """Put the boot configuration and power back (caller holds app_lock)."""
        assert self._boot is not None
        cfg, power = self._boot
        try:
            if self.app.get_config() != cfg:
                self.app.set_config(dict(cfg))
            if power is not None and not np.array_equal(self.app.get_power(), power):
                self.app.set_power(0, 0, power)
        except Exception:  # the device must stay on the line; the host reads the config
            log.exception("cannot restore the boot configuration for a new session")


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
        max_frame: largest frame this end sends or accepts (bytes, 512..65535).
        ring_columns: recent columns kept for RESEND.
        heartbeat_s: HEARTBEAT interval while scanning (s).
        poll_s: longest blocking read when idle (s).
        replay_depth: requests remembered for retransmission replay.
        fec: accept Reed-Solomon coded frames and code a session whose HELLO asks for it
            (a serial line); False on TCP, where a damaged frame is not worth the CPU.
        peer: who is on the other end (an IP address), for the per-peer back-off after
            failed authentication; default the port's name.
        clock: monotonic clock (s), replaceable in tests.
    """

    def __init__(self, port: Any, app: DeviceApp | None = None, *,
                 core: DeviceCore | None = None, key: bytes | None = None,
                 session_id: int | None = None, session_idle_s: float = 10.0,
                 max_frame: int = 16384, ring_columns: int = 1024, heartbeat_s: float = 0.2,
                 poll_s: float = 0.01, replay_depth: int = 32, peer: str | None = None,
                 fec: bool = True,
                 clock: Callable[[], float] = time.monotonic) -> None:
        check_int("max_frame", max_frame, MIN_MAX_FRAME, FRAME_LIMIT)
        check_int("ring_columns", ring_columns, 0, 65535)
        if not 0.001 <= heartbeat_s <= 65.535:
            raise out_of_range("heartbeat_s", "0.001 to 65.535 s (INFO.heartbeat_ms)",
                               heartbeat_s)
        if not 0 < poll_s <= 1:
            raise out_of_range("poll_s", "above 0 and at most 1 s (0 would spin)", poll_s)
        check_int("replay_depth", replay_depth, 1, 32768)
        if session_id is not None:  # 0 or None: random
            check_int("session_id", session_id, 0, 0xFFFFFFFF)
        if core is None:
            if app is None:
                raise out_of_range("app", "a DeviceApp (or a DeviceCore)", app)
            core = DeviceCore(app, key=key, session_idle_s=session_idle_s, clock=clock)
        self.core = core
        self.app = core.app
        self.port = port
        #: Who is on the other end (an IP address over TCP), for the auth back-off and logs.
        self.peer = peer or str(getattr(port, "name", None) or type(port).__name__)
        self.session = session_id if session_id else _new_session()
        self.session_open = False
        #: Since when this connection has had no session (core clock, s).
        self.sessionless_since = core.clock()
        self.max_frame = max_frame
        self.tx_max_frame = max_frame
        self.ring_columns = ring_columns
        self.heartbeat_s = heartbeat_s
        self.replay_depth = replay_depth
        self.clock = clock
        self.fec = fec
        self.coded = False  # this session's frames are Reed-Solomon coded (HELLO flag FEC)
        self.decoder = FrameDecoder(max_frame, fec=fec)
        self.stats = EndpointStats()
        self._replay: OrderedDict[int, _Cached] = OrderedDict()
        self._last_seq: int | None = None
        self._stream: _Stream | None = None
        self._latest: _Stream | None = None  # the last stream started, running or not
        self._last_frame = 0
        self._last_next = 0
        self._last_end = ScanEndReason.COMPLETE
        self._ring: OrderedDict[tuple[int, int], bytes] = OrderedDict()
        # Piece length (bytes) each ring column was last cut at; 0: sent whole.
        self._cuts: dict[tuple[int, int], int] = {}
        self._stream_seq = 0
        self._notice_id = 0  # FRAGMENT.seq of notices sent in pieces
        self._rx_counted = (0, 0)  # decoder (frames, errors) already in the core's totals
        self._last_heartbeat = 0.0
        self._capture: tuple[tuple[int, int, int], NDArray] | None = None
        self._info: Info | None = None  # as sent in the last INFO
        self._config: dict[str, Any] | None = None  # the app's config, for CONFIG_GET mid-scan
        self._host_nonce = b""
        self._challenge: bytes | None = None  # nonce of the last CHALLENGE sent
        self._tx: auth.FrameSigner | None = None  # signs this session's frames
        self._rx: auth.FrameVerifier | None = None  # checks the host's frames
        # _lock guards the endpoint's state and the port's write side; the core's app_lock
        # serialises calls into the application and is always taken first.
        self._lock = threading.Lock()
        self._app_lock = core.app_lock
        self._health = (TEMPERATURE_UNKNOWN, 0)
        self._queue: queue.SimpleQueue[tuple[Frame, bool] | None] = queue.SimpleQueue()
        # Transmit queue: one deque per class, guarded by _txcv; one writer at a time.
        self._txq: tuple[deque[_Job], deque[_Job], deque[_Job]] = (deque(), deque(), deque())
        self._txcv = threading.Condition()
        self._writing = False
        self._repairs: set[tuple[int, int, int]] = set()  # repairs queued, not yet sent
        self._queued = 0  # requests queued for the request worker and not yet handled
        self._worker: threading.Thread | None = None
        #: Request handler of each request type, ``(request, fields, after) -> reply``.
        self._handlers: dict[MsgType, Callable[[Frame, dict, list], _Reply]] = {
            MsgType.HELLO: self._on_hello,
            MsgType.CONFIG_GET: self._on_config_get,
            MsgType.CONFIG_SET: self._on_config_set,
            MsgType.POWER_SET: self._on_power_set,
            MsgType.POWER_GET: self._on_power_get,
            MsgType.SCAN_START: self._on_scan_start,
            MsgType.SCAN_ABORT: self._on_scan_abort,
            MsgType.RESEND: self._on_resend,
            MsgType.CALIBRATE: self._on_calibrate,
            MsgType.CAPTURE: self._on_capture,
            MsgType.STATUS_GET: self._on_status_get,
            MsgType.SESSION_END: self._on_session_end,
            MsgType.FRAME_SIZE: self._on_frame_size,
        }
        port.timeout = poll_s

    @property
    def streaming(self) -> bool:
        """True while a scan or calibration stream runs."""
        return self._stream is not None

    # ---- main loop ------------------------------------------------------------------
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
        """Stop a running stream (no SCAN_END), end this connection's session, stop the worker.

        The port is left open.
        """
        with self._lock:
            self._stop_stream(ScanEndReason.ABORTED, send_end=False)
            self.core.release(self)
            self.session_open = False
        if self._worker is not None:
            self._queue.put(None)
            if self._worker is not threading.current_thread():
                self._worker.join(timeout=5.0)
            self._worker = None

    def poll(self) -> None:
        """Read what arrived (blocking at most ``poll_s``), answer requests, send heartbeats.

        Never waits for the application: columns are produced by a stream worker and
        requests that need the application by a request worker, so STATUS_GET, RESEND,
        SCAN_ABORT, CONFIG_GET during a scan and heartbeats go out while it computes.
        """
        n = self.port.in_waiting
        if n:
            data = self.port.read(n)
        else:
            data = self.port.read(1)
            if data:
                more = self.port.in_waiting
                if more:
                    data += self.port.read(more)
        with self._lock:
            if data:
                damaged = self.decoder.stats.damaged
                for frame in self.decoder.feed(data):
                    self._on_frame(frame)
                while self.decoder.rejected:
                    self._on_rejected(self.decoder.rejected.pop(0))
                self._count_rx()
                if self.decoder.stats.damaged > damaged:
                    # Say so at once: a host waiting for a reply sends its request again
                    # now rather than after its timeout.
                    self._send_stream(MsgType.LINE_ERROR, encode_payload(
                        MsgType.LINE_ERROR, {"rx_errors": self.decoder.stats.errors
                                             & 0xFFFFFFFF}))
            now = self.clock()
            if self._stream is not None and now - self._last_heartbeat >= self.heartbeat_s:
                self._last_heartbeat = now
                self._send_stream(MsgType.HEARTBEAT,
                                  encode_payload(MsgType.HEARTBEAT, self.status().to_fields()))
            worker = self._stream is not None
        # Replies and notices now; repairs in a bounded share while a column worker runs
        # (it sends the rest); everything when no stream runs.
        self._flush(_FRESH if not worker else _REPAIR,
                    None if not worker else _POLL_REPAIR_BYTES)


    def _count_rx(self) -> None:
        """Add what the decoder counted since the last call to the core's totals."""
        ds, (frames, errors) = self.decoder.stats, self._rx_counted
        self.core.rx_frames += ds.frames - frames
        self.core.rx_errors += ds.errors - errors
        self._rx_counted = (ds.frames, ds.errors)

    def status(self) -> Status:
        """Current status (as sent in STATUS and HEARTBEAT); counters since boot."""
        self._count_rx()
        st = self._stream
        if self._app_lock.acquire(blocking=False):  # else: the last reading
            try:
                self._health = self.app.health()
            except Exception:  # a health sensor must not take the link down
                log.exception("application health() failed")
                self._health = (TEMPERATURE_UNKNOWN, FAULT_HEALTH)
            finally:
                self._app_lock.release()
        temp, faults = self._health
        core = self.core
        mask = 0xFFFFFFFF
        return Status(
            state=(State.IDLE if st is None else
                   State.CALIBRATING if st.calibration else State.SCANNING),
            frame=(st.frame if st else self._last_frame) & mask,
            next_column=(st.next_column - self._column_queued() if st else self._last_next)
            & 0xFFFF,
            last_end=int(self._last_end),
            columns_sent=core.totals.columns_sent & mask,
            uptime_ms=int((self.clock() - core.booted) * 1000) & mask,
            rx_frames=core.rx_frames & mask, rx_errors=core.rx_errors & mask,
            tx_frames=core.totals.tx_frames & mask, replays=core.totals.replays & mask,
            temperature_mc=temp, faults=faults & mask)

    # ---- sending --------------------------------------------------------------------
    def _enqueue_tx(self, cls: int, msg_type: MsgType, payload: bytes, seq: int | None,
                    compat: int = 0, signer: auth.FrameSigner | None = None,
                    repair: tuple[int, int, int] | None = None, max_frame: int = 0,
                    coded: bool | None = None, version: int = PROTOCOL_VERSION) -> None:
        """Queue one frame of class ``cls`` (encoded and signed when it is sent) of at
        most ``max_frame`` bytes (0: the session's current max frame).

        A ``repair`` already queued is not queued twice: a host that asks again before
        the first answer reached it costs the line nothing.
        """
        job = _Job(msg_type, payload, seq, self.session, compat,
                   max_frame or self.tx_max_frame, signer, repair,
                   self.coded if coded is None else coded, version)
        with self._txcv:
            if repair is not None:
                if repair in self._repairs:
                    return
                self._repairs.add(repair)
            self._txq[cls].append(job)

    def _flush(self, upto: int, budget: int | None = None, wait: bool = False) -> None:
        """Send queued frames of classes 0..``upto``, highest priority first.

        One thread writes at a time: if another is writing, return at once unless
        ``wait`` (that writer sends replies and notices before it gives up its role;
        the column worker waits, so new columns always go). ``budget``: stop after
        about this many bytes of classes above _CONTROL (replies and notices all go).
        """
        with self._txcv:
            if self._writing and not wait:
                return
            while self._writing:
                self._txcv.wait()
            self._writing = True
        sent = 0
        try:
            while True:
                with self._txcv:
                    cls = next((c for c in range(upto + 1) if self._txq[c]), None)
                    if cls is None or (cls > _CONTROL and budget is not None and
                                       sent >= budget):
                        # Give up the writer's role in the same breath as the last look
                        # at the queue: a frame queued after it finds no writer and
                        # its thread sends it; one queued before it was seen here.
                        self._writing = False
                        self._txcv.notify_all()
                        return
                    job = self._txq[cls].popleft()
                    if job.repair is not None:
                        self._repairs.discard(job.repair)
                seq = job.seq
                if seq is None:
                    self._stream_seq = seq = (self._stream_seq + 1) & 0xFFFF
                try:
                    wire = encode_frame(job.msg_type, job.payload, seq, job.session,
                                        compat=job.compat, max_frame=job.max_frame,
                                        signer=job.signer, coded=job.coded,
                                        version=job.version)
                except FieldError:  # a bug must not take the device off the line
                    log.exception("cannot send a %s frame", _type_name(job.msg_type))
                    continue
                self.port.write(wire)
                self.stats.tx_frames += 1
                self.core.totals.tx_frames += 1
                if cls > _CONTROL:
                    sent += len(wire)
        except BaseException:  # the port failed: let the next writer try
            with self._txcv:
                self._writing = False
                self._txcv.notify_all()
            raise

    def _column_queued(self) -> int:
        """1 while frames of a new column wait in the queue (that column is not sent yet)."""
        with self._txcv:
            return int(any(j.msg_type != MsgType.SCAN_END for j in self._txq[_FRESH]))

    def _drop_tx(self, cls: int) -> None:
        """Forget the queued frames of one class (an ended stream's new columns)."""
        with self._txcv:
            self._txq[cls].clear()
            if cls == _REPAIR:
                self._repairs.clear()

    def _send_stream(self, msg_type: MsgType, payload: bytes, compat: int = 0,
                     cls: int = _CONTROL, repair: tuple[int, int, int] | None = None) -> None:
        if self._pieces(payload, self._tx is not None) > 1:  # a notice longer than a frame
            self._notice_id = (self._notice_id + 1) & 0xFFFF
            self._send_pieces(msg_type, payload, self._notice_id, 0, 0, self._tx, None, compat,
                              cls)
            return
        self._enqueue_tx(cls, msg_type, payload, None, compat, self._tx, repair)

    def _piece_room(self, signed: bool) -> int:
        """Payload bytes one FRAGMENT carries in this session."""
        return self.tx_max_frame - frame_size(FRAGMENT_HEADER, signed)

    def _pieces(self, payload: bytes, signed: bool) -> int:
        """Frames a payload takes: 1 if it fits the max frame, else its FRAGMENT count."""
        if frame_size(len(payload), signed) <= self.tx_max_frame:
            return 1
        return -(-len(payload) // self._piece_room(signed))

    def _send_reply(self, req: Frame, reply: _Reply) -> None:
        msg_type, payload, signed = reply
        signer = self._tx if signed else None
        coded = self.coded or req.fec  # a coded request gets a coded reply
        if self._pieces(payload, signed) == 1:
            self._enqueue_tx(_CONTROL, msg_type, payload, req.seq, 0, signer, coded=coded)
            return
        self._send_pieces(msg_type, payload, req.seq, 0, 0, signer, None, coded=coded)

    def _send_pieces(self, msg_type: MsgType, payload: bytes, seq: int, frame: int,
                     column: int, signer: auth.FrameSigner | None, only: Iterable[int] | None,
                     compat: int = 0, cls: int = _CONTROL, room: int = 0,
                     coded: bool | None = None) -> int:
        """Send ``payload`` as FRAGMENTs (all of them, or the indexes in ``only``) of
        ``room`` bytes each (0: as many as the current max frame carries); returns the
        piece length used."""
        signed = signer is not None
        cut = room
        room = room or self._piece_room(signed)
        count = -(-len(payload) // room)
        if count > MAX_PIECES:
            raise DeviceError(f"{msg_type.name} of {len(payload)} bytes needs {count} "
                              f"fragments at max frame {self.tx_max_frame} (at most "
                              f"{MAX_PIECES})", code=ErrorCode.TOO_LARGE)
        for k in range(count) if only is None else only:
            body = encode_payload(MsgType.FRAGMENT, {
                "msg_type": int(msg_type), "seq": seq, "frame": frame, "column": column,
                "index": k, "count": count, "data": payload[k * room:(k + 1) * room]})
            self._enqueue_tx(cls, MsgType.FRAGMENT, body, None, compat, signer,
                             (frame, column, k) if cls == _REPAIR else None,
                             frame_size(FRAGMENT_HEADER + cut, signed) if cut else 0, coded)
        return room

    def _send_column(self, key: tuple[int, int], payload: bytes, compat: int = 0,
                     only: Iterable[int] | None = None) -> None:
        """One COLUMN_RESULT, or its FRAGMENTs when it does not fit the max frame.

        Queued as a repair when ``compat`` marks a retransmission, else as a new column.
        Pieces asked for by index (``only``) are cut as the column last was, whatever
        the frame size now, so the pieces the host holds stay good; a whole column is
        cut at the current size.
        """
        cls = _REPAIR if compat & COMPAT_RETRANSMIT else _FRESH
        cut = self._cuts.get(key, 0)
        if only is not None and cut:
            count = -(-len(payload) // cut)
            if all(0 <= k < count for k in only):
                self._send_pieces(MsgType.COLUMN_RESULT, payload, 0, key[0], key[1], self._tx,
                                  only, compat, cls, cut)
                return
        # A whole column (or pieces of a column never cut, or of no cut: all of it).
        if self._pieces(payload, self._tx is not None) == 1:
            self._cuts[key] = 0
            self._send_stream(MsgType.COLUMN_RESULT, payload, compat, cls,
                              (*key, -1) if cls == _REPAIR else None)
        else:
            self._cuts[key] = self._send_pieces(MsgType.COLUMN_RESULT, payload, 0, key[0],
                                                key[1], self._tx, None, compat, cls)

    def _reply(self, req: Frame, msg_type: MsgType, payload: bytes) -> _Reply:
        return (msg_type, payload, self._tx is not None and bool(req.sig))

    def _nak(self, req: Frame, code: ErrorCode, fld: str = "", detail: str = "",
             signed: bool | None = None) -> _Reply:
        self.stats.naks += 1
        log.debug("NAK %s seq %d: %s %s %s", req.msg_type, req.seq, code.name, fld, detail)
        payload = encode_payload(MsgType.NAK, {
            "request_type": req.msg_type, "code": int(code),
            "field": _clip(fld), "detail": _clip(detail)})
        if signed is None:
            signed = self._tx is not None and bool(req.sig)
        return (MsgType.NAK, payload, signed)

    # ---- receiving ------------------------------------------------------------------
    def _on_rejected(self, frame: Frame) -> None:
        if kind_of(frame.msg_type) is not MsgKind.REQUEST:
            return
        if frame.version != PROTOCOL_VERSION:
            # In the requester's version, so that an older host reads it: the header and
            # the NAK payload are laid out alike in every version.
            reply = self._nak(frame, ErrorCode.VERSION, "version",
                              f"device speaks protocol version {PROTOCOL_VERSION}", False)
            self._enqueue_tx(_CONTROL, MsgType.NAK, reply[1], frame.seq, coded=frame.fec,
                             version=frame.version)
            return
        self._send_reply(frame, self._nak(frame, ErrorCode.UNSUPPORTED_FLAGS, "incompat_flags",
                                          f"unknown incompat flags 0x{frame.incompat:02x}",
                                          False))

    def _on_frame(self, frame: Frame) -> None:
        """One decoded frame (caller holds _lock): check, then answer, replay or queue it.

        While the request worker has work, every request queues behind it, so requests
        are always handled in the order they arrived.
        """
        if kind_of(frame.msg_type) is not MsgKind.REQUEST:
            self.stats.ignored += 1
            return
        if self._queued:
            self._enqueue(frame, False)
        else:
            self._process(frame, False)

    def _enqueue(self, frame: Frame, checked: bool) -> None:
        self._queued += 1
        if self._worker is None:
            self._worker = threading.Thread(target=self._serve_requests, daemon=True,
                                            name="cdma-lidar-requests")
            self._worker.start()
        self._queue.put((frame, checked))

    def _process(self, frame: Frame, in_worker: bool) -> None:
        """Check one request and answer, replay, drop or (poll thread) queue it."""
        self.stats.rx_requests += 1
        is_hello = frame.msg_type == MsgType.HELLO
        if not is_hello:
            if not self.session_open or frame.session != self.session:
                detail = (f"this connection's session is 0x{self.session:08x}; send HELLO"
                          if self.session_open else "no session is open here: send HELLO")
                self._send_reply(frame, self._nak(frame, ErrorCode.WRONG_SESSION, "session",
                                                  detail, False))
                return
            if self._rx is not None:
                if not frame.sig:
                    self._send_reply(frame, self._nak(
                        frame, ErrorCode.AUTH_REQUIRED, "incompat_flags",
                        "this device accepts only signed frames: HELLO with its key", False))
                    return
                if not self._rx.check(frame):  # forged or replayed: no answer at all
                    self.stats.auth_rejected += 1
                    self.core.backoff.failed(f"{self.peer} (session frames)",
                                             "a frame failed authentication")
                    return
            self.core.touch(self)
        key = zlib.crc32(bytes([frame.msg_type]) + frame.payload)
        cached = self._replay.get(frame.seq)
        if cached is not None and cached.key == key:
            self.stats.replays += 1
            self.core.totals.replays += 1
            for reply in cached.replies:
                self._send_reply(frame, reply)
            return
        if not is_hello and self._last_seq is not None:
            age = (self._last_seq - frame.seq) & 0xFFFF
            if 0 < age < 0x8000:
                self.stats.stale += 1
                log.debug("dropped stale request seq %d (last %d)", frame.seq, self._last_seq)
                return
        if is_hello and not in_worker:
            refusal = self._hello_refusal(frame)
            if refusal is not None:
                self._respond(frame, key, refusal)
                return
        if in_worker or frame.msg_type in _WITHOUT_APP or \
                (frame.msg_type == MsgType.CONFIG_GET and self._stream is not None and
                 self._config is not None):
            self._respond(frame, key)
        else:
            self._enqueue(frame, True)

    def _serve_requests(self) -> None:
        """Request worker: handles, in order, the requests that need the application."""
        while True:
            item = self._queue.get()
            if item is None:
                return
            frame, checked = item
            try:
                with self._app_lock, self._lock:
                    self._queued -= 1
                    if checked:
                        self._respond(frame, zlib.crc32(bytes([frame.msg_type]) + frame.payload))
                    else:
                        self._process(frame, True)
                    idle = self._stream is None
                self._flush(_FRESH if idle else _CONTROL)
            except OSError as exc:  # the port went away
                log.warning("request worker stops: %s", exc)
                return
            except Exception:  # a bug must not take the device off the line
                log.exception("request worker failed on %s", _type_name(frame.msg_type))

    def _hello_refusal(self, frame: Frame) -> _Reply | None:
        """The gate's answer to a HELLO, from the polling thread (None: for the worker)."""
        try:
            f = decode_payload(MsgType.HELLO, frame.payload)
        except FrameError:
            return None  # the worker NAKs it MALFORMED
        assert isinstance(f, dict)
        return self._hello_gate(frame, f)

    def _respond(self, frame: Frame, key: int, reply: _Reply | None = None) -> None:
        """Act on one request (or send ``reply``, decided already), cache and send its
        reply (caller holds _lock, maybe app_lock)."""
        is_hello = frame.msg_type == MsgType.HELLO
        after: list[Callable[[], None]] = []
        try:
            if reply is None:
                reply = self._handle(frame, after)
        except FrameError as exc:
            reply = self._nak(frame, ErrorCode.MALFORMED, exc.field or "", str(exc))
        except DeviceError as exc:
            reply = self._nak(frame, _code(exc.code), exc.field or "", str(exc))
            after.clear()
        except ConfigError as exc:
            reply = self._nak(frame, ErrorCode.OUT_OF_RANGE, exc.field or "", str(exc))
            after.clear()
        except Exception as exc:  # the device must never die on a request
            log.exception("device application failed on %s", _type_name(frame.msg_type))
            reply = self._nak(frame, ErrorCode.INTERNAL, "", f"{type(exc).__name__}: {exc}")
            after.clear()
        if is_hello and reply[0] == MsgType.INFO:
            self._replay.clear()
        self._replay[frame.seq] = _Cached(key, [reply])
        self._replay.move_to_end(frame.seq)
        while len(self._replay) > self.replay_depth:
            self._replay.popitem(last=False)
        if not is_hello:
            self._last_seq = frame.seq
        self._send_reply(frame, reply)
        for action in after:
            try:
                action()
            except OSError:
                raise  # the port failed
            except Exception:  # a bug must not take the device off the line
                log.exception("action after %s failed", _type_name(frame.msg_type))

    # ---- request handlers -------------------------------------------------------------
    def _handle(self, req: Frame, after: list[Callable[[], None]]) -> _Reply:
        try:
            t = MsgType(req.msg_type)
        except ValueError:
            return self._nak(req, ErrorCode.UNKNOWN_TYPE, "msg_type",
                             f"unknown request type 0x{req.msg_type:02x}")
        handler = self._handlers.get(t)
        if handler is None:
            return self._nak(req, ErrorCode.UNKNOWN_TYPE, "msg_type", f"{t.name} is not a request")
        fields_ = decode_payload(t, req.payload)
        assert isinstance(fields_, dict)
        return handler(req, fields_, after)

    def _ack(self, req: Frame) -> _Reply:
        return self._reply(req, MsgType.ACK,
                           encode_payload(MsgType.ACK, {"request_type": req.msg_type}))

    def _hello_gate(self, req: Frame, f: dict) -> _Reply | None:
        """What HELLO gets without the application: a CHALLENGE, AUTH_FAILED (a wrong MAC,
        or one sent during the peer's back-off) or BUSY; None: open a session.

        Runs in the polling thread (holding _lock), so a HELLO is refused at once
        whatever the application is computing, and again in the request worker.
        """
        core = self.core
        if core.key is not None:
            if not any(f["mac"]) or self._challenge is None or \
                    not auth.equal(f["device_nonce"], self._challenge):
                self._challenge = secrets.token_bytes(auth.NONCE_BYTES)
                return (MsgType.CHALLENGE, encode_payload(
                    MsgType.CHALLENGE, {"device_nonce": self._challenge}), False)
            wait = core.backoff.wait_s(self.peer)
            if wait > 0:
                self._challenge = None
                self.stats.auth_throttled += 1
                return self._nak(req, ErrorCode.AUTH_FAILED, "mac", "too many failed "
                                 f"authentications from this peer: retry in {wait:.1f} s",
                                 False)
            want = auth.hello_mac(core.key, self._challenge, bytes(f["host_nonce"]),
                                  f["flags"], f["host_max_frame"])
            if not auth.equal(want, f["mac"]):
                self._challenge = None
                self.stats.auth_rejected += 1
                core.backoff.failed(self.peer, "HELLO with a wrong MAC (the host holds "
                                               "another key)")
                return self._nak(req, ErrorCode.AUTH_FAILED, "mac",
                                 "the MAC does not match this device's key", False)
        owner = core.owner
        if owner is None or (owner is self and core.owner_nonce == bytes(f["host_nonce"])):
            return None
        now = core.clock()
        idle = core.idle_s(now)
        if idle >= core.session_idle_s or f["flags"] & HelloFlags.TAKE_OVER:
            return None
        return self._nak(
            req, ErrorCode.BUSY, "session",
            f"another host owns the device: its session opened {now - core.opened:.1f} "
            f"s ago and has been idle {idle:.1f} s (expires after "
            f"{core.session_idle_s:g} s idle); say HELLO with take-over to end it", False)

    def _on_hello(self, req: Frame, f: dict, after: list) -> _Reply:
        """Challenge (with a key), check ownership, then open a fresh session.

        Runs in the request worker, holding app_lock and _lock.
        """
        refusal = self._hello_gate(req, f)
        if refusal is not None:
            return refusal
        core = self.core
        if core.key is not None:
            core.backoff.passed(self.peer)
        nonce = bytes(f["host_nonce"])
        now = core.clock()
        owner = core.owner
        flags = HelloFlags(f["flags"])
        mine = owner is self and core.owner_nonce == nonce
        if owner is not None and not mine:
            idle = core.idle_s(now)
            if idle >= core.session_idle_s:
                lost = (SessionLostReason.EXPIRED, f"idle {idle:.1f} s, longer than "
                        f"{core.session_idle_s:g} s: another host opened a session")
            else:
                lost = (SessionLostReason.TAKEN_OVER, "another host took over the device "
                        f"after {now - core.opened:.1f} s")
            if owner is self:
                self._lose(*lost)
            else:
                with owner._lock:  # lock order: app_lock, then one endpoint's _lock
                    owner._lose(*lost)
        # Open a fresh session on this connection.
        self._end_session()
        device_nonce = self._challenge or bytes(auth.NONCE_BYTES)
        self._challenge = None
        if self._latest is not None:  # we hold app_lock: end it for the app right now
            self._finish(self._latest)
        core.snapshot()
        if not flags & HelloFlags.KEEP_CONFIG:
            core.restore_defaults()
        self._config = self.app.get_config()
        if self.stats.sessions or self.session_open:
            self.session = _new_session(self.session)
        self.stats.sessions += 1
        self.session_open = True
        self._host_nonce = nonce
        self._last_seq = None
        core.owner, core.owner_nonce = self, nonce
        core.opened = core.last_active = now
        self.tx_max_frame = min(self.max_frame, f["host_max_frame"])
        self.coded = self.fec and bool(flags & HelloFlags.FEC)
        mac = bytes(auth.MAC_BYTES)
        if core.key is not None:
            to_dev, to_host = auth.session_keys(core.key, nonce, device_nonce, self.session)
            self._tx, self._rx = auth.FrameSigner(to_host), auth.FrameVerifier(to_dev)
            mac = auth.device_mac(core.key, nonce, device_nonce, self.session)
        self._info = info = dataclasses.replace(
            self.app.info(), protocol_version=PROTOCOL_VERSION, session_id=self.session,
            schema_crc=SCHEMA_CRC, max_frame=self.max_frame,
            ring_columns=min(self.ring_columns, 65535),
            heartbeat_ms=max(1, min(65535, round(self.heartbeat_s * 1000))),
            session_idle_ms=max(1, min(2**32 - 1, round(core.session_idle_s * 1000))),
            auth=int(Auth.HMAC_SHA256 if core.key is not None else Auth.NONE), device_mac=mac)
        log.info("HELLO from host %s: session 0x%08x, max frame %d%s", nonce[:4].hex(),
                 self.session, self.tx_max_frame, ", signed" if self._tx else "")
        return (MsgType.INFO, encode_payload(MsgType.INFO, info.to_fields()),
                self._tx is not None)

    def _end_session(self) -> None:
        """Forget the current session's stream, ring, capture, keys (caller holds _lock)."""
        self._stop_stream(ScanEndReason.ABORTED, send_end=False)
        self._drop_tx(_REPAIR)
        self._ring.clear()
        self._cuts.clear()
        self._capture = None
        self._tx = self._rx = None
        self.coded = False
        if self.session_open:
            self.sessionless_since = self.core.clock()
        self.session_open = False

    def _lose(self, reason: SessionLostReason, detail: str) -> None:
        """Another connection's HELLO ends this connection's session: tell its host.

        Caller holds the core's app_lock (it runs in a HELLO handler) and this
        endpoint's _lock.
        """
        if self.session_open:
            log.info("session 0x%08x lost: %s", self.session, detail)
            try:
                self._send_stream(MsgType.SESSION_LOST, encode_payload(
                    MsgType.SESSION_LOST, {"reason": int(reason), "detail": _clip(detail)}))
            except OSError:
                pass  # that host is gone anyway
        self._end_session()
        if self._latest is not None:
            self._finish(self._latest)
        if self.core.owner is self:
            self.core.owner = None

    def _on_session_end(self, req: Frame, f: dict, after: list) -> _Reply:
        """The host closes its link: ACK (signed), then forget the session."""
        def end() -> None:
            self._end_session()
            if self._latest is not None:
                self._finish(self._latest)
            self.core.release(self)
            log.info("session 0x%08x ended by its host", self.session)

        after.append(end)
        return self._ack(req)

    def _on_frame_size(self, req: Frame, f: dict, after: list) -> _Reply:
        """New largest frame this device sends; the ACK still goes out at the old size."""
        new = min(self.max_frame, f["host_max_frame"])
        st = self._stream
        if st is not None and self._info is not None and self._config is not None:
            size = column_payload_size(self._info.channels, int(self._config.get("peaks", 1)))
            room = new - frame_size(FRAGMENT_HEADER, self._tx is not None)
            if size + OVERHEAD > new and -(-size // room) > MAX_PIECES:
                return self._nak(req, ErrorCode.TOO_LARGE, "host_max_frame",
                                 f"a column of {size} bytes would need more than "
                                 f"{MAX_PIECES} fragments at {new} bytes")

        def apply() -> None:
            self.tx_max_frame = new
            log.debug("frames of session 0x%08x now at most %d bytes", self.session, new)

        after.append(apply)
        return self._ack(req)

    def _on_config_get(self, req: Frame, f: dict, after: list) -> _Reply:
        if self._stream is not None and self._config is not None:
            values = dict(self._config)  # no CONFIG_SET while streaming: still current
        else:
            values = self.app.get_config()
            self._config = dict(values)
        if f["keys"]:
            want = []
            for kid in f["keys"]:
                try:
                    want.append(config_key(kid).name)
                except FieldError:
                    return self._nak(req, ErrorCode.UNKNOWN_KEY, f"key {kid}")
            values = {n: values[n] for n in want if n in values}
        payload = encode_payload(MsgType.CONFIG, {"items": encode_config(values)})
        if self._pieces(payload, self._tx is not None) > MAX_PIECES:
            return self._nak(req, ErrorCode.TOO_LARGE, "keys",
                             "ask for fewer keys per CONFIG_GET")
        return self._reply(req, MsgType.CONFIG, payload)

    def _on_config_set(self, req: Frame, f: dict, after: list) -> _Reply:
        if self._stream is not None:
            return self._nak(req, ErrorCode.BUSY, "", "abort the running scan first")
        cfg = decode_config(f["items"])
        if cfg.unknown:
            return self._nak(req, ErrorCode.UNKNOWN_KEY, f"key {cfg.unknown[0]}",
                             "key not known to this device")
        for name in cfg.values:
            if name in _READ_ONLY:
                return self._nak(req, ErrorCode.READ_ONLY, name, f"{name} is read-only")
        self.app.set_config(cfg.values)
        self._config = self.app.get_config()
        return self._ack(req)

    def _on_power_set(self, req: Frame, f: dict, after: list) -> _Reply:
        power = np.asarray(f["power"], dtype=np.uint16).reshape(f["channels"], f["columns"])
        self.app.set_power(f["channel_start"], f["column_start"], power)
        return self._ack(req)

    def _on_power_get(self, req: Frame, f: dict, after: list) -> _Reply:
        m = np.asarray(self.app.get_power(), dtype=np.uint16)
        r0, c0, nr, nc = f["channel_start"], f["column_start"], f["channels"], f["columns"]
        if r0 + nr > m.shape[0]:
            return self._nak(req, ErrorCode.OUT_OF_RANGE, "channels",
                             f"channel_start + channels must be at most {m.shape[0]}")
        if c0 + nc > m.shape[1]:
            return self._nak(req, ErrorCode.OUT_OF_RANGE, "columns",
                             f"column_start + columns must be at most {m.shape[1]}")
        payload = encode_payload(MsgType.POWER, {
            "channel_start": r0, "column_start": c0, "channels": nr, "columns": nc,
            "power": m[r0:r0 + nr, c0:c0 + nc]})
        if self._pieces(payload, self._tx is not None) > MAX_PIECES:
            return self._nak(req, ErrorCode.TOO_LARGE, "columns",
                             "ask for a smaller rectangle per POWER_GET")
        return self._reply(req, MsgType.POWER, payload)

    def _start_stream(self, req: Frame, gen_factory: Callable[[], Iterator[ColumnResult]],
                      frame: int, first: int, count: int, calibration: bool,
                      after: list[Callable[[], None]]) -> _Reply:
        if self._stream is not None:
            return self._nak(req, ErrorCode.BUSY, "", "a scan is running; abort it first")
        prev = self._latest
        if prev is not None:  # we hold app_lock: its generator is not running
            self._finish(prev)  # close it (and abort) before the app starts another stream
        info = self._info or self.app.info()
        self._config = self.app.get_config()
        peaks = int(self._config.get("peaks", 1))
        size = column_payload_size(info.channels, peaks)
        if self._pieces(bytes(size), self._tx is not None) > MAX_PIECES:
            return self._nak(req, ErrorCode.TOO_LARGE, "peaks",
                             f"a column of {info.channels} channels x {peaks} peaks ({size} "
                             f"bytes) needs more than {MAX_PIECES} fragments at max frame "
                             f"{self.tx_max_frame}")
        gen = iter(gen_factory())
        st = _Stream(gen, frame, first, count, calibration)
        self._stream = self._latest = st
        self._last_frame = frame
        self._last_heartbeat = self.clock()
        worker = threading.Thread(target=self._produce, args=(st,), daemon=True,
                                  name=f"cdma-lidar-frame-{frame}")
        after.append(worker.start)  # after the ACK is on the wire
        return self._ack(req)

    def _on_scan_start(self, req: Frame, f: dict, after: list) -> _Reply:
        return self._start_stream(
            req, lambda: self.app.scan(f["frame"], f["first_column"], f["columns"]),
            f["frame"], f["first_column"], f["columns"], False, after)

    def _on_calibrate(self, req: Frame, f: dict, after: list) -> _Reply:
        return self._start_stream(req, lambda: self.app.calibrate(f["frame"], f["shots"]),
                                  f["frame"], 0, f["shots"], True, after)

    def _on_scan_abort(self, req: Frame, f: dict, after: list) -> _Reply:
        if self._stream is not None:
            after.append(lambda: self._stop_stream(ScanEndReason.ABORTED))
        return self._ack(req)

    def _on_resend(self, req: Frame, f: dict, after: list) -> _Reply:
        frame = f["frame"]
        st = self._stream
        todo: list[tuple[tuple[int, int], bytes, list[int] | None]] = []
        if not f["columns"] and not f["fragments"]:
            return self._nak(req, ErrorCode.MALFORMED, "columns",
                             "name at least one column or fragment")
        wanted = [(f"columns[{k}]", col, None) for k, col in enumerate(f["columns"])] + \
            [(f"fragments[{k}]", p["column"], p["index"]) for k, p in enumerate(f["fragments"])]
        for name, col, piece in wanted:
            payload = self._ring.get((frame, col))
            if payload is not None:
                todo.append(((frame, col), payload, None if piece is None else [piece]))
            elif not (st is not None and st.frame == frame and
                      st.next_column <= col < st.first + st.count):
                return self._nak(req, ErrorCode.NOT_AVAILABLE, name,
                                 f"column {col} of frame {frame} is no longer kept")

        def resend() -> None:
            for key, payload, only in todo:
                self.stats.resent += 1
                self.stats.columns_sent += 1
                self.core.totals.columns_sent += 1
                self._send_column(key, payload, COMPAT_RETRANSMIT, only)

        after.append(resend)
        return self._ack(req)

    def _on_capture(self, req: Frame, f: dict, after: list) -> _Reply:
        key = (f["kind"], f["column"], f["channel"])
        if f["offset"] == 0 or self._capture is None or self._capture[0] != key:
            if f["offset"] != 0:
                return self._nak(req, ErrorCode.NOT_AVAILABLE, "offset",
                                 "read offset 0 first to take a capture")
            data = np.asarray(self.app.capture(CaptureKind(f["kind"]), f["column"],
                                               f["channel"])).ravel()
            if data.dtype.kind not in "iu":
                raise DeviceError("capture is not integer data", code=ErrorCode.INTERNAL)
            lo, hi = (int(data.min()), int(data.max())) if data.size else (0, 0)
            for dt in (np.int16, np.int32, np.int64):
                if np.iinfo(dt).min <= lo and hi <= np.iinfo(dt).max:
                    break
            self._capture = (key, data.astype(np.dtype(dt).newbyteorder("<")))
        arr = self._capture[1]
        total, off = arr.size, f["offset"]
        if off > total:
            return self._nak(req, ErrorCode.OUT_OF_RANGE, "offset",
                             f"offset must be 0..{total}, not {off}")
        room = (self.tx_max_frame - frame_size(_CAPTURE_HEADER, self._tx is not None)) \
            // arr.itemsize
        n = max(0, min(f["max_count"], room, total - off))
        payload = encode_payload(MsgType.CAPTURE_DATA, {
            "kind": f["kind"], "column": f["column"], "channel": f["channel"],
            "elem_bytes": arr.itemsize, "total": total, "offset": off,
            "data": arr[off:off + n].tobytes()})
        return self._reply(req, MsgType.CAPTURE_DATA, payload)

    def _on_status_get(self, req: Frame, f: dict, after: list) -> _Reply:
        return self._reply(req, MsgType.STATUS,
                           encode_payload(MsgType.STATUS, self.status().to_fields()))

    # ---- streaming -------------------------------------------------------------------
    def _produce(self, st: _Stream) -> None:
        """Worker thread of one stream: pull columns from the app and send them in order."""
        reason = ScanEndReason.COMPLETE
        try:
            while not st.stopped and st.produced < st.count:
                try:
                    with self._app_lock:
                        if st.stopped:
                            break
                        col = next(st.gen)
                    if col.frame != st.frame or col.calibration != st.calibration:
                        col = dataclasses.replace(col, frame=st.frame,
                                                  calibration=st.calibration)
                    payload = encode_column(col)
                    if self._pieces(payload, self._tx is not None) > MAX_PIECES:
                        log.error("frame %d column %d: %d bytes need more than %d fragments "
                                  "at max frame %d", st.frame, col.column, len(payload),
                                  MAX_PIECES, self.tx_max_frame)
                        reason = ScanEndReason.ERROR
                        break
                except StopIteration:
                    log.warning("application ended frame %d after %d of %d columns", st.frame,
                                st.produced, st.count)
                    reason = ScanEndReason.ERROR
                    break
                except Exception:
                    log.exception("application failed during frame %d", st.frame)
                    reason = ScanEndReason.ERROR
                    break
                with self._lock:
                    if st.stopped:
                        break
                    key = (st.frame, col.column)
                    self._ring[key] = payload
                    self._ring.move_to_end(key)
                    while len(self._ring) > self.ring_columns:
                        self._cuts.pop(self._ring.popitem(last=False)[0], None)
                    st.produced += 1
                    self.stats.columns_sent += 1
                    self.core.totals.columns_sent += 1
                    self._send_column(key, payload)
                    if st.produced >= st.count:
                        # End the stream under the same lock that queued its last column:
                        # a SCAN_START arriving right after must not find it still busy.
                        self._stop_stream(reason)
                # On the line before the next column is computed: replies and repairs
                # first, then this column (the worker never runs ahead of the line).
                self._flush(_FRESH, wait=True)
            with self._lock:
                if not st.stopped:
                    self._stop_stream(reason)
            self._flush(_FRESH, wait=True)
        except OSError as exc:  # the port went away under us
            log.warning("column stream of frame %d stops: %s", st.frame, exc)
            with self._lock:
                if self._stream is st:
                    self._stream = None
                st.stopped = True
        except Exception:  # e.g. a column the frame size cannot carry: end it, stay alive
            log.exception("column stream of frame %d failed", st.frame)
            with self._lock:
                if not st.stopped:
                    try:  # marks it stopped before it sends SCAN_END
                        self._stop_stream(ScanEndReason.ERROR)
                    except Exception:
                        log.exception("cannot send SCAN_END of frame %d", st.frame)
        finally:
            with self._app_lock:
                self._finish(st)

    def _finish(self, st: _Stream) -> None:
        """Close the generator of an ended stream; call ``app.abort()`` if it ended early.

        Caller holds app_lock (so the generator is not running). Runs once per
        stream: in its worker when it exits, or earlier in the next SCAN_START /
        CALIBRATE / HELLO, so the application never sees the clean-up of an old stream
        after it was asked for a new one.
        """
        if st.finished or not st.stopped:
            return
        st.finished = True
        try:
            close = getattr(st.gen, "close", None)
            if close is not None:
                close()
            if st.produced < st.count:
                self.app.abort()
        except Exception:  # the device must not die on an application's clean-up
            log.exception("application failed while ending frame %d", st.frame)

    def _stop_stream(self, reason: ScanEndReason, send_end: bool = True) -> None:
        """End the current stream (caller holds ``_lock``); its worker notices and exits."""
        st = self._stream
        if st is None:
            return
        st.stopped = True
        self._stream = None
        self._last_next = st.next_column
        self._last_end = reason
        self.core.touch(self)  # idle time counts from the end of the stream
        if reason != ScanEndReason.COMPLETE:
            self._drop_tx(_FRESH)  # aborted: its queued columns need not go out (kept in ring)
        if send_end:  # after the columns queued before it
            self._send_stream(MsgType.SCAN_END, encode_payload(MsgType.SCAN_END, {
                "frame": st.frame, "first_column": st.first, "columns": st.produced,
                "calibration": int(st.calibration), "reason": int(reason)}), cls=_FRESH)


def _new_session(old: int = 0) -> int:
    """A random non-zero session id different from ``old``."""
    while True:
        s = secrets.randbits(32)
        if s and s != old:
            return s


def _clip(s: str, limit: int = 255) -> str:
    b = s.encode("utf-8")[:limit]
    return b.decode("utf-8", errors="ignore")


def _code(code: int) -> ErrorCode:
    try:
        return ErrorCode(code)
    except ValueError:
        return ErrorCode.INTERNAL


def _type_name(t: int) -> str:
    try:
        return MsgType(t).name
    except ValueError:
        return f"0x{t:02x}"
