"""Host end of the link: requests with retries, streamed columns with gap repair, diagnostics.

:class:`HostLink` talks to a :class:`cdma_lidar.protocol.endpoint.DeviceEndpoint` over any
port-like object (:mod:`cdma_lidar.protocol.ports`): whatever
:func:`~cdma_lidar.protocol.ports.open_port` returns for a pyserial URL (``/dev/ttyACM0``,
``socket://host:port``, a pty path, ``virtual://...``), a
:class:`~cdma_lidar.protocol.ports.FdPort` around a file descriptor, or one end of an
in-process :func:`~cdma_lidar.protocol.pipes.pipe_pair`. It owns its receive buffer (a
:class:`cdma_lidar.protocol.framing.FrameDecoder`) and only ever blocks in ``port.read`` with a
short timeout, so it never spins a core.

Requests: each carries a new ``seq``; the reply (ACK, NAK or data) echoes it. No
reply within ``timeout_s`` -> the identical frame is sent again, up to ``retries``
times; the device answers a retransmission from its replay cache instead of acting
twice. Then :class:`LinkTimeout` says what the line showed (``diagnosis``):

* ``no bytes at all``           -- nothing came back: power, cable, port name;
* ``bytes but no valid frame``  -- wrong baud rate, or not a cdma-lidar device;
* ``frames but wrong session``  -- the device rebooted: call :meth:`HostLink.hello`;
* ``frames of another protocol version`` -- CRC-valid frames this version must not
  read (another ``version`` or unknown incompat flags): update host or firmware;
* ``frames but no answer``      -- the device is alive but ignores this request.

A reply to the pending request that carries another protocol version (a device
answers a request of a version it does not speak with NAK VERSION in its own
version) fails the request at once with :class:`LinkError` naming both versions.

Scans: columns arrive as COLUMN_RESULT frames; :meth:`HostLink.scan` yields them in
column order exactly once, asks for missing ones again (RESEND) as soon as a later
column, a HEARTBEAT or SCAN_END shows they were sent. After ``timeout_s`` of
silence it asks STATUS to learn how far the device got. It fails with LinkTimeout
after ``column_retries`` fruitless RESENDs of one column.
"""

from __future__ import annotations

import contextlib
import logging
import secrets
import time
from collections import OrderedDict, deque
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from cdma_lidar.checks import check_int, is_int
from cdma_lidar.errors import (
    DeviceError,
    FieldError,
    LinkError,
    LinkTimeout,
    out_of_range,
)
from cdma_lidar.protocol import auth
from cdma_lidar.protocol.columns import ColumnResult
from cdma_lidar.protocol.config_keys import config_key, decode_config, encode_config
from cdma_lidar.protocol.framing import (
    COMPAT_RETRANSMIT,
    FRAME_LIMIT,
    MIN_MAX_FRAME,
    OVERHEAD,
    PROTOCOL_VERSION,
    SIGNATURE_SIZE,
    Frame,
    FrameDecoder,
    encode_frame,
)
from cdma_lidar.protocol.messages import (
    REPLY_TO,
    SCHEMA_CRC,
    Auth,
    CaptureKind,
    ErrorCode,
    HelloFlags,
    MsgKind,
    MsgType,
    SessionLostReason,
    State,
    decode_payload,
    encode_payload,
    kind_of,
)
from cdma_lidar.protocol.ports import default_fec
from cdma_lidar.protocol.reassembly import ColumnReassembler, StreamEnded
from cdma_lidar.protocol.trust import ColumnChecker, DeviceLied, check_config, check_info, escape
from cdma_lidar.protocol.views import Info, Status

__all__ = [
    "DIAG_GARBAGE",
    "DIAG_HINTS",
    "DIAG_NOISY",
    "DIAG_NO_ANSWER",
    "DIAG_SILENT",
    "DIAG_VERSION",
    "DIAG_WRONG_SESSION",
    "HostLink",
    "LinkStats",
    "ScanStalled",
    "SessionLost",
    "StreamEnded",
]

log = logging.getLogger(__name__)

#: Smallest frame the device may be asked to send (HELLO host_max_frame).
MIN_HOST_FRAME = 64

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


class ScanStalled(StreamEnded, LinkTimeout):
    """The device kept the stream alive (heartbeats, STATUS "scanning") but no column
    and no ``next_column`` moved for ``HostLink.progress_timeout_s``."""

    def __init__(self, message: str, *, frame: int, next_column: int) -> None:
        StreamEnded.__init__(self, message, frame=frame, next_column=next_column, reason=None)
        self.diagnosis = DIAG_NO_ANSWER


class SessionLost(LinkError):
    """The device ended this host's session (another host took over, or it expired)."""

    def __init__(self, message: str, reason: int = 0) -> None:
        super().__init__(message)
        self.reason = reason


@dataclass
class LinkStats:
    """Counters of a :class:`HostLink` (decoder errors are in ``HostLink.decoder.stats``)."""

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


@dataclass
class _Pieces:
    """FRAGMENTs of one message received so far."""

    count: int
    data: dict[int, bytes] = field(default_factory=dict)
    frames: list[Frame] = field(default_factory=list)
    size: int = 0  # length of a piece other than the last (bytes): the cut; 0 until seen


@dataclass
class _Window:
    """Counters at the start of a wait, for the silent-link diagnosis."""

    bytes: int
    frames: int
    wrong_session: int
    other_version: int
    damaged: int
    line_errors: int


class HostLink:
    """Host end of the protocol over a port-like object.

    Args:
        port: from :func:`~cdma_lidar.protocol.ports.open_port`, a
            :class:`~cdma_lidar.protocol.ports.FdPort`, or anything with ``read``,
            ``write``, ``in_waiting`` and ``timeout``.
        timeout_s: wait for one reply, and longest silence in a scan (s).
        retries: retransmissions of a request before LinkTimeout.
        column_retries: RESENDs of one missing column before LinkTimeout; default
            ``10 * (retries + 1)``. Columns are long frames: on a noisy line most of
            them may need several tries although the device answers every request
            (at a bit error rate of 1e-4 a 1.6 KB frame gets through 27 % of the time).
        poll_s: longest blocking read (s), greater than 0 so that waiting never spins;
            default ``min(0.05, timeout_s / 4)``.
        max_frame: largest frame the device may send (bytes, 64..65535), announced in
            HELLO: longer replies and columns come in FRAGMENTs, so a noisy line can be
            given short frames. Requests stay within min(INFO.max_frame, max(max_frame,
            256)).
        key: shared secret of a device that requires one (32 bytes,
            :func:`cdma_lidar.protocol.auth.load_key`); then HELLO answers the device's
            challenge, the device must prove it holds the key too, and every frame of the
            session is signed. None: the device must not ask for a key.
        take_over: HELLO ends another host's live session instead of failing BUSY.
        keep_config: the new session keeps the previous session's configuration and
            power instead of starting from the device's defaults.
        fec: Reed-Solomon coded frames both ways (:mod:`cdma_lidar.protocol.fec`), asked
            for in HELLO; None: on for a serial line, off for ``socket://`` and USB
            (``/dev/ttyACM*``), whose transports already deliver intact bytes
            (:func:`cdma_lidar.protocol.ports.default_fec`).
        progress_timeout_s: a stream whose device stays alive (heartbeats, STATUS
            "scanning") but sends no new column or fragment and does not move
            ``next_column`` for this long fails with :class:`ScanStalled` (s).
        clock: monotonic clock (s), replaceable in tests.

    One HostLink per port, used from one thread at a time.
    """

    def __init__(self, port: Any, timeout_s: float = 0.5, retries: int = 3, *,
                 column_retries: int | None = None, poll_s: float | None = None,
                 max_frame: int = FRAME_LIMIT, key: bytes | None = None,
                 take_over: bool = False, keep_config: bool = False, fec: bool | None = None,
                 progress_timeout_s: float = 30.0,
                 clock: Callable[[], float] = time.monotonic) -> None:
        if not timeout_s > 0:
            raise out_of_range("timeout_s", "a positive number of seconds", timeout_s)
        self.port = port
        self.timeout_s = float(timeout_s)
        self.retries = check_int("retries", retries, 0, 100)
        self.column_retries = 10 * (self.retries + 1) if column_retries is None \
            else check_int("column_retries", column_retries, 0, 1000)
        if poll_s is not None and not 0 < poll_s <= 10:
            raise out_of_range("poll_s", "a number of seconds above 0 and at most 10 (0 "
                               "would make every wait spin)", poll_s)
        if not progress_timeout_s > 0:
            raise out_of_range("progress_timeout_s", "a positive number of seconds",
                               progress_timeout_s)
        self.progress_timeout_s = float(progress_timeout_s)
        #: A column or fragment asked for again is asked once more after this long (s):
        #: its answer comes ahead of new columns, so a quarter of the reply timeout.
        self.resend_s = self.timeout_s / 4
        self.clock = clock
        self.decoder = FrameDecoder(max(max_frame, MIN_MAX_FRAME))
        self.stats = LinkStats()
        self.info: Info | None = None
        self.session: int | None = None
        self.last_status: Status | None = None
        self.max_frame = 4096  # until INFO says more; every request fits
        self._host_max = max_frame
        if key is not None and len(key) != auth.KEY_BYTES:
            raise out_of_range("key", f"{auth.KEY_BYTES} bytes", len(key))
        self.key = key
        self.take_over = bool(take_over)
        self.fec = default_fec(port) if fec is None else bool(fec)
        self.decoder.fec = self.fec
        self.coded = False  # this session's frames are coded (the device agreed in HELLO)
        self.keep_config = bool(keep_config)
        self.config: dict[str, Any] | None = None  # last full CONFIG, checked against INFO
        self._nonce = secrets.token_bytes(auth.NONCE_BYTES)
        self._seq = int.from_bytes(self._nonce[:2], "little")
        self._tx: auth.FrameSigner | None = None  # signs our requests (keyed session)
        self._rx: auth.FrameVerifier | None = None  # checks the device's frames
        self._reply_frame: Frame | None = None
        self._reply_parts: list[Frame] = []  # the FRAGMENTs the pending reply came in
        self._partial: dict[tuple[int, int], _Pieces] = {}  # replies arriving in fragments
        self._notices: dict[tuple[int, int], _Pieces] = {}  # notices arriving in fragments
        self.line_errors = 0  # LINE_ERRORs of our session heard so far
        self._early: list[Frame] = []  # frames that came with INFO, before hello() returned
        self._next_frame_id = secrets.randbits(31)
        self._pending: int | None = None  # seq of the request waiting for its reply
        self._pending_type = 0
        self._hello_seq: int | None = None
        self._reply: Frame | None = None
        self._reply_version: Frame | None = None  # reply to the pending seq we must not read
        self._streaming = False
        # Stream items: (type, decoded body, retransmitted).
        self._stream: deque[tuple[int, Any, bool]] = deque()
        # Requests sent without waiting for their reply (RESEND in a scan): seq -> type.
        self._unawaited: OrderedDict[int, MsgType] = OrderedDict()
        self._refusal: tuple[MsgType, Frame] | None = None  # a NAK to one of them
        self._port_name = str(getattr(port, "portstr", None) or getattr(port, "name", None)
                              or type(port).__name__)
        port.timeout = min(0.05, self.timeout_s / 4) if poll_s is None else poll_s

    # ---- context manager ----------------------------------------------------------------
    def __enter__(self) -> HostLink:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def close(self) -> None:
        """End the session (SESSION_END, one short try: another host may then say HELLO
        without take-over) and close the port."""
        if self.session is not None:
            timeout, retries = self.timeout_s, self.retries
            self.timeout_s, self.retries = min(timeout, 0.2), 0
            try:
                self._transact(MsgType.SESSION_END, {}, self._new_seq())
            except Exception:  # LinkError, SessionLost: the device forgets us when idle
                log.debug("SESSION_END got no answer; the session expires when idle")
            finally:
                self.timeout_s, self.retries = timeout, retries
                self.session = None
        with contextlib.suppress(Exception):
            self.port.close()

    # ---- public requests --------------------------------------------------------------
    def hello(self) -> Info:
        """Open a session: learn the device's identity, limits, geometry and session id.

        With a key, answers the device's CHALLENGE and checks that INFO is signed with
        the session key (so the device holds the key too). Raises DeviceError (code
        BUSY, field ``session``) when another host owns the device and ``take_over``
        is off; DeviceLied when INFO contradicts itself.
        """
        self.session = None
        self._tx = self._rx = None
        self.info = None
        self.config = None
        self._early = []
        flags = (HelloFlags.TAKE_OVER if self.take_over else 0) | \
            (HelloFlags.KEEP_CONFIG if self.keep_config else 0) | \
            (HelloFlags.FEC if self.fec else 0)
        self.coded = False
        reply, fields_ = self._hello_exchange(self._host_max, int(flags))
        return self._open(reply, fields_)

    def _hello_exchange(self, host_max: int, flags: int) -> tuple[dict[str, Any],
                                                                 dict[str, Any]]:
        """HELLO (and, with a key, its CHALLENGE round): (INFO fields, HELLO fields)."""
        fields_ = {"host_max_frame": host_max, "flags": flags,
                   "host_nonce": self._nonce, "device_nonce": bytes(auth.NONCE_BYTES),
                   "mac": bytes(auth.MAC_BYTES)}
        for _ in range(2):
            reply = self._hello_once(fields_)
            if self._reply_frame is not None and self._reply_frame.msg_type == MsgType.INFO:
                break
            if self.key is None:
                raise LinkError(f"device on {self._port_name} requires a key: pass --key-file "
                                "FILE or set CDMA_LIDAR_KEY_FILE to the device's key file")
            fields_["device_nonce"] = bytes(reply["device_nonce"])
            fields_["mac"] = auth.hello_mac(self.key, fields_["device_nonce"], self._nonce,
                                            flags, host_max)
        else:
            raise LinkError("device answered the authenticated HELLO with another CHALLENGE: "
                            "it does not accept this host's key")
        return reply, fields_

    def _open(self, reply: dict[str, Any], fields_: dict[str, Any]) -> Info:
        """Check INFO and make its session ours."""
        try:
            info = Info.from_fields(reply)
        except (TypeError, ValueError) as exc:
            raise DeviceLied(f"device sent an invalid INFO: {exc}") from None
        if info.protocol_version != PROTOCOL_VERSION:
            raise LinkError(f"device speaks protocol version {info.protocol_version}, host "
                            f"{PROTOCOL_VERSION}; update the host or the firmware")
        if self.key is not None:
            self._authenticate(info, bytes(fields_["device_nonce"]))
        elif info.auth != Auth.NONE:
            raise DeviceLied("device announced signed frames (INFO.auth = "
                             f"{info.auth}) without asking this host for a key", "auth")
        info = check_info(info)
        if info.schema_crc != SCHEMA_CRC:
            log.warning("device schema 0x%08x differs from host schema 0x%08x: host and "
                        "firmware come from different revisions", info.schema_crc, SCHEMA_CRC)
        self.info = info
        self.session = info.session_id
        # Requests: what the device accepts, within what this host asked for the line.
        self.max_frame = min(info.max_frame, max(self._host_max, MIN_MAX_FRAME))
        # The device codes its INFO when it agreed to FEC: then so do we.
        self.coded = self.fec and self._reply_frame is not None and self._reply_frame.fec
        early, self._early = self._early, []
        for frame in early:  # e.g. SESSION_LOST right behind INFO
            self._dispatch(frame)
        log.info("session 0x%08x with %s (firmware %s, %d channels, max frame %d%s)",
                 self.session, info.serial, info.firmware_version, info.channels,
                 info.max_frame, ", signed" if self._tx else "")
        return info

    def _hello_once(self, fields_: dict[str, Any]) -> dict[str, Any]:
        seq = self._new_seq()
        self._hello_seq = seq
        try:
            return self._transact(MsgType.HELLO, fields_, seq)
        finally:
            self._hello_seq = None

    def _authenticate(self, info: Info, device_nonce: bytes) -> None:
        """Check the device's proof and INFO's signature; set up the session's signing."""
        frame = self._reply_frame
        assert frame is not None and self.key is not None
        if info.auth != Auth.HMAC_SHA256 or not auth.equal(
                info.device_mac, auth.device_mac(self.key, self._nonce, device_nonce,
                                                 info.session_id)):
            raise LinkError(f"device on {self._port_name} did not prove it holds the key "
                            f"(INFO.auth = {info.auth}): it is not the device the key file "
                            "belongs to, or it holds no key (then drop --key-file)")
        to_dev, to_host = auth.session_keys(self.key, self._nonce, device_nonce,
                                            info.session_id)
        rx = auth.FrameVerifier(to_host)
        parts = self._reply_parts or [frame]  # an INFO in FRAGMENTs: each one is signed
        if any(p.session != info.session_id for p in parts) or not all(map(rx.check, parts)):
            raise LinkError(f"device on {self._port_name} sent an INFO not signed with the "
                            "session key")
        self._tx, self._rx = auth.FrameSigner(to_dev), rx

    def get_config(self, *names: str) -> dict[str, Any]:
        """Configuration values by key name (all keys when no names are given)."""
        keys = [config_key(n).id for n in names]
        reply = self._request(MsgType.CONFIG_GET, {"keys": keys})
        try:
            values = decode_config(reply["items"]).values
        except Exception as exc:  # FrameError from the strict decoder
            raise DeviceLied(f"device sent an invalid CONFIG: {exc}") from None
        if not names:
            assert self.info is not None
            check_config(values, self.info)
            self.config = dict(values)
        elif self.config is not None:
            merged = {**self.config, **values}
            check_config(merged, self.info)  # type: ignore[arg-type]
            self.config = merged
        return values

    def set_config(self, **values: Any) -> None:
        """Set configuration keys (python values, see ``CONFIG_KEYS``); all or none.

        Raises FieldError for a key or value the wire cannot carry and DeviceError
        (``code``, ``field``) when the device refuses.
        """
        if not values:
            return
        self.config = None  # read again (checked) before the next stream
        self._request(MsgType.CONFIG_SET, {"items": encode_config(values,
                                                                  allow_read_only=False)})

    def set_power(self, matrix: ArrayLike, channel_start: int = 0, column_start: int = 0) -> None:
        """Send a (channels, columns) laser-power matrix in chunks that fit the frame size.

        Integer matrices are in units of 1/65535 of the per-pixel maximum (0..65535);
        float matrices are fractions 0..1 and are rounded to that grid.
        """
        self._need_info()  # the chunk size depends on the session's max frame
        m = np.asarray(matrix)
        if m.ndim != 2 or m.size == 0:
            raise out_of_range("power", "a non-empty (channels, columns) matrix",
                               f"shape {m.shape}", FieldError)
        if m.dtype.kind == "f":
            if not np.isfinite(m).all() or m.min() < 0 or m.max() > 1:
                raise out_of_range("power", "fractions from 0 to 1", m, FieldError)
            m = np.rint(m * 65535.0).astype(np.int64)
        elif m.dtype.kind not in "iu" or m.min() < 0 or m.max() > 65535:
            raise out_of_range("power", "integers from 0 to 65535", m, FieldError)
        rows, cols = m.shape
        room = (self.max_frame - OVERHEAD - (SIGNATURE_SIZE if self._tx else 0) - 8) // 2
        step_c = min(cols, room)
        step_r = max(1, min(rows, room // step_c))
        for r0 in range(0, rows, step_r):
            for c0 in range(0, cols, step_c):
                block = m[r0:r0 + step_r, c0:c0 + step_c]
                self._request(MsgType.POWER_SET, {
                    "channel_start": channel_start + r0, "column_start": column_start + c0,
                    "channels": block.shape[0], "columns": block.shape[1],
                    "power": block.ravel()})

    def get_power(self) -> NDArray[np.uint16]:
        """The device's (K, C) power matrix (1/65535 of the per-pixel maximum), read back.

        C is INFO.column_count; read in rectangles of whole rows that fit a reply (a
        longer reply would come in FRAGMENTs anyway).
        """
        info = self._need_info()
        k, c = info.channels, info.column_count
        out = np.zeros((k, c), dtype=np.uint16)
        rows = max(1, min(k, 16384 // max(c, 1)))
        for r0 in range(0, k, rows):
            n = min(rows, k - r0)
            d = self._request(MsgType.POWER_GET, {"channel_start": r0, "column_start": 0,
                                                  "channels": n, "columns": c})
            if (d["channel_start"], d["column_start"], d["channels"], d["columns"]) != \
                    (r0, 0, n, c):
                raise DeviceLied(f"device answered POWER_GET of rows {r0}..{r0 + n - 1} with "
                                 f"rows {d['channel_start']}.. x {d['channels']}", "power")
            out[r0:r0 + n] = np.asarray(d["power"], dtype=np.uint16).reshape(n, c)
        return out

    def status(self) -> Status:
        """Device status."""
        return Status(**self._request(MsgType.STATUS_GET, {}))

    def abort(self) -> None:
        """Stop a running scan or calibration (harmless when idle)."""
        self._request(MsgType.SCAN_ABORT, {})

    def capture(self, kind: str | int = "raw", column: int = 0, channel: int = 0) -> NDArray:
        """Debug capture of one column: raw ADC samples or a channel's correlation trace.

        ``kind`` is ``"raw"`` / ``"corr"`` (or a CaptureKind). Read in chunks under the
        frame size; returns an int16/int32/int64 array.
        """
        if isinstance(kind, str):
            names = {k.name.lower(): k for k in CaptureKind}
            if kind not in names:
                raise out_of_range("kind", "'raw' or 'corr'", kind, FieldError)
            kind = names[kind]
        parts: list[NDArray] = []
        offset, total = 0, None
        while total is None or offset < total:
            d = self._request(MsgType.CAPTURE, {"kind": int(kind), "column": column,
                                                "channel": channel, "offset": offset,
                                                "max_count": 65535})
            dt = {2: "<i2", 4: "<i4", 8: "<i8"}.get(d["elem_bytes"])
            if dt is None or d["offset"] != offset or len(d["data"]) % d["elem_bytes"]:
                raise LinkError(f"CAPTURE_DATA out of step: offset {d['offset']} (wanted "
                                f"{offset}), {d['elem_bytes']} bytes per element")
            chunk = np.frombuffer(d["data"], dtype=dt)
            total = d["total"]
            if chunk.size == 0 and offset < total:
                raise LinkError("CAPTURE_DATA chunk is empty before the end of the capture")
            parts.append(chunk)
            offset += chunk.size
        return np.concatenate(parts) if parts else np.zeros(0, dtype=np.int16)

    def scan(self, first_column: int = 0, columns: int | None = None, frames: int = 1,
             frame: int | None = None) -> Iterator[ColumnResult]:
        """Scan ``frames`` frames of ``columns`` columns from ``first_column``.

        Yields ColumnResults in column order, each exactly once, repairing gaps. By
        default a frame is a full scan: ``columns_per_frame`` columns (configuration).
        Leaving the loop early aborts the scan on the device.
        """
        if not is_int(frames) or frames < 1:
            raise out_of_range("frames", "an integer of at least 1", frames)
        info = self._need_info()
        if columns is None:  # a full scan: columns_per_frame (docs/protocol.md, 6.2)
            if self.config is None:
                self.get_config()
            assert self.config is not None
            columns = min(int(self.config["columns_per_frame"]), info.column_count) - \
                first_column
        for k in range(frames):
            fid = self._frame_id(frame if k == 0 else None)
            yield from self._stream_columns(
                MsgType.SCAN_START,
                {"frame": fid, "first_column": first_column, "columns": columns},
                fid, first_column, columns)

    def calibrate(self, shots: int, frame: int | None = None) -> list[ColumnResult]:
        """Zeroth-order calibration: ``shots`` columns flagged ``calibration``."""
        self._need_info()
        fid = self._frame_id(frame)
        return list(self._stream_columns(MsgType.CALIBRATE, {"frame": fid, "shots": shots},
                                         fid, 0, shots))

    # ---- streaming -------------------------------------------------------------------------
    def _frame_id(self, frame: int | None) -> int:
        if frame is None:
            frame = self._next_frame_id
        self._next_frame_id = (frame + 1) & 0xFFFFFFFF
        return frame

    def _stream_columns(self, req: MsgType, fields_: dict[str, Any], fid: int, first: int,
                        count: int) -> Iterator[ColumnResult]:
        """Start a stream with ``req``; yield columns first..first+count-1 in order, once each.

        Columns arrive whole (COLUMN_RESULT) or in FRAGMENTs; a missing fragment is asked
        for alone (RESEND ``fragments``), a column of which nothing arrived as a whole.
        If the device ends the stream early (SCAN_END aborted or error, or idle short of
        the end), every column it did send is still delivered before the error is raised.
        """
        end = first + count
        if self.config is None:
            self.get_config()
        assert self.info is not None and self.config is not None
        checker = ColumnChecker(self.info, self.config, fid, first, end,
                                req == MsgType.CALIBRATE)
        self._stream.clear()
        self._unawaited.clear()  # a late NAK to a RESEND of an earlier stream is not ours
        self._refusal = None
        self._streaming = True
        finished = False
        try:
            try:
                self._request(req, fields_)
            except DeviceError as exc:
                if exc.code != ErrorCode.BUSY:
                    raise
                # In one session only our own previous stream can be running: its last
                # columns reached us before the device had sent them all (repairs of the
                # same frame id, asked for earlier). Let it end, then ask once more.
                self._await_idle(exc)
                self._stream.clear()
                self._request(req, fields_)
            asm = ColumnReassembler(fid, first, end, checker, self.resend_s)
            last_rx = moved = self.clock()
            progress = asm.progress
            while not asm.done:
                got = False  # heard something about this frame (other frames are no sign of life)
                while self._stream:
                    got = asm.feed(*self._stream.popleft()) or got
                self.stats.duplicates += asm.duplicates
                self.stats.malformed += asm.malformed
                asm.duplicates = asm.malformed = 0
                if self._refusal is not None:  # the device refused a RESEND: say why
                    (mtype, frame), self._refusal = self._refusal, None
                    self._accept_reply(mtype, frame)
                for col in asm.ready():
                    self.stats.columns += 1
                    yield col
                if asm.done:
                    break
                now = self.clock()
                if asm.progress != progress:
                    progress, moved = asm.progress, now
                elif now - moved >= self.progress_timeout_s:
                    raise ScanStalled(
                        f"frame {fid} made no progress for {self.progress_timeout_s:g} s on "
                        f"{self._port_name}: the device says it is still working but column "
                        f"{asm.nxt} never came; {asm.nxt - first} columns were delivered",
                        frame=fid, next_column=asm.nxt)
                if got:
                    last_rx = now
                elif now - last_rx >= self.timeout_s:
                    # Silence: ask the device how far it got (raises LinkTimeout with a
                    # diagnosis if it does not answer either).
                    st = self._probe(fid)
                    asm.sent(st.next_column, st.last_end if st.state == State.IDLE else None)
                    last_rx = self.clock()
                    continue
                due = asm.due(now)
                if due:  # one RESEND, then read: its answer is in the stream
                    self._resend(fid, due, asm, now)
                    last_rx = self.clock()
                self._pump()
            if asm.failure is not None:
                raise asm.failure
            finished = True
        finally:
            self._streaming = False
            self._stream.clear()
            if not finished and self.session is not None:
                with contextlib.suppress(LinkError):
                    self.abort()

    def _await_idle(self, busy: DeviceError) -> None:
        """STATUS_GET until the device's running stream has ended (re-raise ``busy`` if it
        has not within the reply timeout times the retries)."""
        deadline = self.clock() + self.timeout_s * (self.retries + 1)
        while self.status().state != State.IDLE:
            if self.clock() >= deadline:
                raise busy
            self._pump()

    def _probe(self, fid: int) -> Status:
        """STATUS_GET after a silent spell: how far the device got with frame ``fid``."""
        st = self.status()
        if st.frame != fid:
            raise LinkError(f"device is {st.state_name} with frame {st.frame}, not frame {fid}: "
                            "it lost the scan (restarted or another host took over)")
        return st

    def _resend(self, fid: int, due: list[Any], asm: ColumnReassembler, now: float) -> None:
        """RESEND the due columns (ints) and fragments ((column, index)), 255 of each at most."""
        room = self.max_frame - OVERHEAD - (SIGNATURE_SIZE if self._tx else 0) - 6
        cols = [k for k in due if isinstance(k, int)][:min(255, room // 2)]
        pieces = [k for k in due if not isinstance(k, int)][:min(255, (room - 2 * len(cols))
                                                                 // 3)]
        for key in cols + pieces:
            tries = asm.tries(key)
            if tries >= self.column_retries:
                damaged = self.decoder.stats.damaged
                what = f"column {key}" if isinstance(key, int) else \
                    f"fragment {key[1]} of column {key[0]}"
                if damaged:
                    raise LinkTimeout(
                        f"{what} of frame {fid} never arrived intact after {tries} resend "
                        f"requests on {self._port_name}: a noisy line, {damaged} damaged "
                        f"frames of {damaged + self.decoder.stats.frames}; "
                        f"{DIAG_HINTS[DIAG_NOISY]}", DIAG_NOISY)
                raise LinkTimeout(
                    f"{what} of frame {fid} never arrived after {tries} resend requests on "
                    f"{self._port_name}: {DIAG_NO_ANSWER}; {DIAG_HINTS[DIAG_NO_ANSWER]}",
                    DIAG_NO_ANSWER)
        asm.ask(cols + pieces, now)
        self.stats.resend_requests += 1
        self.stats.resent_columns += len(cols) + len(pieces)
        log.debug("frame %d: asking again for %d columns and %d fragments", fid, len(cols),
                  len(pieces))
        # Not waited for: the columns are the answer, and the stream goes on meanwhile.
        # A lost RESEND is asked again once the retransmission timeout passes.
        self._send_unawaited(MsgType.RESEND, {"frame": fid, "columns": cols, "fragments": [
            {"column": c, "index": k} for c, k in pieces]})

    def _send_unawaited(self, msg_type: MsgType, fields_: dict[str, Any]) -> None:
        """Send a request whose reply is not waited for (a NAK to it still fails the scan)."""
        if self.session is None:
            self.hello()
        seq = self._new_seq()
        self.stats.requests += 1
        self._unawaited[seq] = msg_type
        while len(self._unawaited) > 256:
            self._unawaited.popitem(last=False)
        self._send_request(msg_type, encode_payload(msg_type, fields_), seq)

    # ---- request machinery -------------------------------------------------------------------
    def _need_info(self) -> Info:
        if self.info is None:
            self.hello()
        assert self.info is not None
        return self.info

    def _new_seq(self) -> int:
        self._seq = (self._seq + 1) & 0xFFFF
        return self._seq

    def _request(self, msg_type: MsgType, fields_: dict[str, Any]) -> dict[str, Any]:
        if self.session is None:
            self.hello()
        return self._transact(msg_type, fields_, self._new_seq())

    def _transact(self, msg_type: MsgType, fields_: dict[str, Any], seq: int) -> dict[str, Any]:
        payload = encode_payload(msg_type, fields_)
        self.stats.requests += 1
        win = _Window(self.decoder.stats.bytes, self.decoder.stats.frames,
                      self.stats.wrong_session, self._other_version(), self.decoder.stats.damaged,
                      self.line_errors)
        self._pending = seq
        self._pending_type = int(msg_type)
        self._reply = None
        self._reply_frame = None
        self._reply_parts = []
        self._partial.clear()
        self._reply_version = None
        try:
            for attempt in range(self.retries + 1):
                if attempt:
                    self.stats.retries += 1
                    log.debug("%s seq %d: no answer, try %d", msg_type.name, seq, attempt + 1)
                self._send_request(msg_type, payload, seq)
                deadline = self.clock() + self.timeout_s
                while self._reply is None and self._reply_version is None and \
                        self.clock() < deadline:
                    self._pump()
                if self._reply is not None:
                    self._reply_frame = self._reply
                    return self._accept_reply(msg_type, self._reply)
                if self._reply_version is not None:
                    f = self._reply_version
                    raise LinkError(
                        f"device answered {msg_type.name} in protocol version {f.version} "
                        f"with incompat flags 0x{f.incompat:02x}; this host speaks version "
                        f"{PROTOCOL_VERSION} and knows no incompat flags: "
                        f"{DIAG_HINTS[DIAG_VERSION]}")
        finally:
            self._pending = None
        diag = self._diagnose(win)
        what = diag
        if diag in (DIAG_NOISY, DIAG_GARBAGE):
            damaged = self.decoder.stats.damaged - win.damaged
            what += (f" ({damaged} damaged frames of "
                     f"{damaged + self.decoder.stats.frames - win.frames} received, "
                     f"{self.line_errors - win.line_errors} reported by the device)")
        raise LinkTimeout(
            f"{msg_type.name} got no answer from {self._port_name} after "
            f"{self.retries + 1} tries of {self.timeout_s:g} s: {what}; {DIAG_HINTS[diag]}", diag)

    def _send_request(self, msg_type: MsgType, payload: bytes, seq: int) -> None:
        """Write one try of a request, signed afresh (new counter, same seq and payload)."""
        wire = encode_frame(msg_type, payload, seq, self.session or 0, max_frame=self.max_frame,
                            signer=self._tx, coded=self.coded)
        if msg_type == MsgType.HELLO and self.fec:
            # Coded (gets through a noisy line), then plain (a device that cannot decode
            # it, or an older one, reads this copy): the device acts once, the replay
            # cache answers the copy.
            wire = encode_frame(msg_type, payload, seq, 0, coded=True) + wire
        self._write(wire)


    def _diagnose(self, win: _Window) -> str:
        """What the line showed since ``win``: one of the DIAG_* strings."""
        st = self.decoder.stats
        if st.bytes == win.bytes:
            return DIAG_SILENT
        reported = self.line_errors - win.line_errors  # the device saw our frames damaged
        if st.frames == win.frames and not reported:
            return DIAG_VERSION if self._other_version() > win.other_version else DIAG_GARBAGE
        wrong = self.stats.wrong_session - win.wrong_session
        if wrong and st.frames - win.frames == wrong and not reported:
            return DIAG_WRONG_SESSION
        if reported or self.decoder.stats.damaged > win.damaged:
            return DIAG_NOISY
        return DIAG_NO_ANSWER

    def _other_version(self) -> int:
        """CRC-valid frames rejected for their version or incompat flags so far."""
        return self.decoder.stats.version + self.decoder.stats.incompat

    def _accept_reply(self, msg_type: MsgType, frame: Frame) -> dict[str, Any]:
        try:
            body = decode_payload(frame.msg_type, frame.payload)
        except Exception as exc:  # FrameError; the decoder raises nothing else
            self.stats.malformed += 1
            raise LinkError(f"malformed {frame.msg_type:#04x} reply to {msg_type.name}: "
                            f"{exc}") from None
        assert isinstance(body, dict)
        if frame.msg_type == MsgType.NAK:
            try:
                code = ErrorCode(body["code"])
                cname = code.name
            except ValueError:
                cname = f"error {body['code']}"
            fld = escape(body["field"])
            where = f" (field {fld})" if fld else ""
            detail = f": {escape(body['detail'])}" if body["detail"] else ""
            if body["code"] == ErrorCode.WRONG_SESSION:
                detail += " (the device restarted, or another host took it over)"
            raise DeviceError(f"device refused {msg_type.name}: {cname}{where}{detail}",
                              code=body["code"], field=fld or None)
        expected = REPLY_TO[msg_type]
        if msg_type == MsgType.HELLO and frame.msg_type == MsgType.CHALLENGE:
            return body
        if frame.msg_type != expected or (expected == MsgType.ACK and
                                          body["request_type"] != msg_type):
            raise LinkError(f"device answered {msg_type.name} with {frame.msg_type:#04x}")
        return body

    def _session_lost(self, frame: Frame) -> None:
        """The device ended our session: forget it and raise SessionLost (one line)."""
        try:
            body = decode_payload(frame.msg_type, frame.payload)
            assert isinstance(body, dict)
            reason, detail = int(body["reason"]), escape(body["detail"])
        except Exception:  # FrameError: still lost, say so without the device's words
            reason, detail = 0, "no reason given"
        self.session = None
        self.info = None
        self._tx = self._rx = None
        what = {SessionLostReason.TAKEN_OVER: "another host took over the device",
                SessionLostReason.EXPIRED: "the session expired"}.get(reason, "session ended")
        raise SessionLost(f"session lost on {self._port_name}: {detail or what}", reason)

    def _fragment_body(self, frame: Frame) -> dict[str, Any] | None:
        try:
            body = decode_payload(frame.msg_type, frame.payload)
        except Exception:  # FrameError: a malformed fragment is dropped
            self.stats.malformed += 1
            return None
        assert isinstance(body, dict)
        if body["index"] >= body["count"] or not body["data"]:
            self.stats.malformed += 1
            return None
        return body

    def _collect(self, frame: Frame, body: dict[str, Any]) -> None:
        """A fragment of a reply: once all are in, handle the whole reply."""
        key = (body["msg_type"], body["seq"])
        if key[1] != self._pending:
            self.stats.stale_replies += 1
            return
        pc = self._partial.get(key)
        if pc is None or pc.count != body["count"]:
            pc = self._partial[key] = _Pieces(body["count"])
        if body["index"] not in pc.data:
            pc.frames.append(frame)
        pc.data[body["index"]] = body["data"]
        if len(pc.data) < pc.count:
            return
        del self._partial[key]
        whole = Frame(key[0], key[1], frame.session,
                      b"".join(pc.data[i] for i in range(pc.count)), 0, 0, frame.version)
        if self._reply is None and key[1] == self._pending:
            self._reply_parts = pc.frames
        self._reply_reply(MsgKind.REPLY, whole)

    def _write(self, wire: bytes) -> None:
        try:
            self.port.write(wire)
        except Exception as exc:  # pyserial raises SerialException (an OSError) or others
            raise LinkError(f"cannot write to {self._port_name}: {exc}; is the device "
                            "still connected?") from None

    def _pump(self) -> None:
        """One blocking read (at most ``port.timeout``) and dispatch of what it completes."""
        try:
            n = self.port.in_waiting
            data = self.port.read(n if n else 1)
        except Exception as exc:
            raise LinkError(f"cannot read from {self._port_name}: {exc}; is the device "
                            "still connected?") from None
        if data:
            for frame in self.decoder.feed(data):
                self._dispatch(frame)
            while self.decoder.rejected:  # frames of another version or incompat flags
                frame = self.decoder.rejected.pop(0)
                if kind_of(frame.msg_type) is MsgKind.REPLY and frame.seq == self._pending:
                    self._reply_version = frame

    def _dispatch(self, frame: Frame, checked: bool = False) -> None:
        """Route one frame; ``checked``: a notice put together from authenticated pieces."""
        kind = kind_of(frame.msg_type)
        if kind is MsgKind.REQUEST:
            self.stats.ignored += 1
            return
        hello_reply = (kind is MsgKind.REPLY and frame.seq == self._hello_seq and
                       frame.msg_type in (MsgType.INFO, MsgType.NAK, MsgType.CHALLENGE))
        if frame.msg_type == MsgType.FRAGMENT and self._hello_seq is not None and \
                self._reply is None:
            body = self._fragment_body(frame)
            if body is not None and body["seq"] == self._hello_seq and \
                    body["msg_type"] in (MsgType.INFO, MsgType.NAK):
                self._collect(frame, body)  # INFO of a session we do not know yet
                return
        if not hello_reply and self._hello_seq is not None and self._reply is not None and \
                frame.session == self._reply.session:
            self._early.append(frame)  # of the session INFO is opening: read once it is ours
            return
        if frame.msg_type == MsgType.LINE_ERROR and self._rx is None:
            self.line_errors += 1  # unsigned: a hint only (diagnosis), from any session
            return
        if not hello_reply and frame.session != self.session:
            self.stats.wrong_session += 1
            if (kind is MsgKind.REPLY and frame.msg_type == MsgType.NAK and
                    frame.seq == self._pending and self._reply is None and self._rx is None and
                    frame.payload[1:3] == ErrorCode.WRONG_SESSION.to_bytes(2, "little")):
                self._reply = frame  # the device says it restarted: fail fast
            return
        if self._rx is not None and not hello_reply and not checked and \
                not self._rx.check(frame):
            self.stats.unauthenticated += 1  # forged, replayed or unsigned: not from the device
            log.debug("dropped an unauthenticated %#04x frame", frame.msg_type)
            return
        if frame.msg_type == MsgType.LINE_ERROR:
            self.line_errors += 1  # our session's, authenticated: the device saw damage
            return
        if frame.msg_type == MsgType.SESSION_LOST and not hello_reply:
            self._session_lost(frame)
        if frame.msg_type == MsgType.FRAGMENT:
            body = self._fragment_body(frame)
            if body is None:
                return
            if body["msg_type"] == MsgType.COLUMN_RESULT:
                if self._streaming:
                    self._stream.append((MsgType.FRAGMENT, body,
                                         bool(frame.compat & COMPAT_RETRANSMIT)))
            elif kind_of(body["msg_type"]) is MsgKind.REPLY:
                self._collect(frame, body)
            else:  # a notice longer than the frame size (HEARTBEAT, SESSION_LOST, ...)
                whole = self._notice_piece(frame, body)
                if whole is not None:
                    self._dispatch(whole, checked=True)
            return
        self._reply_reply(kind, frame)

    def _notice_piece(self, frame: Frame, body: dict[str, Any]) -> Frame | None:
        """One FRAGMENT of a notice (already authenticated); the whole notice once all
        pieces are in, as an unsigned frame of our session."""
        key = (body["msg_type"], body["seq"])
        pc = self._notices.get(key)
        if pc is None or pc.count != body["count"]:
            pc = self._notices[key] = _Pieces(body["count"])
            while len(self._notices) > 8:  # pieces of lost notices are forgotten
                self._notices.pop(next(iter(self._notices)))
        pc.data[body["index"]] = body["data"]
        if len(pc.data) < pc.count:
            return None
        del self._notices[key]
        return Frame(key[0], 0, frame.session, b"".join(pc.data[i] for i in range(pc.count)))

    def _reply_reply(self, kind: MsgKind, frame: Frame) -> None:
        """A reply or stream frame of our session, authenticated."""
        if kind is MsgKind.REPLY:
            # ACK and NAK echo the request type: a reply to another request that happens
            # to carry the same seq (a previous link, a wrapped counter) is not ours.
            echoed = frame.payload[:1] if frame.msg_type in (MsgType.ACK, MsgType.NAK) else b""
            unawaited = self._unawaited.get(frame.seq)
            if unawaited is not None and echoed == bytes([unawaited]):
                del self._unawaited[frame.seq]
                if frame.msg_type == MsgType.NAK and self._refusal is None:
                    self._refusal = (unawaited, frame)
                return
            if frame.seq == self._pending and self._reply is None and \
                    echoed in (b"", bytes([self._pending_type])):
                self._reply = frame
            else:
                self.stats.stale_replies += 1
            return
        try:
            body = decode_payload(frame.msg_type, frame.payload)
        except Exception:  # FrameError (unknown stream type, malformed payload)
            self.stats.malformed += 1
            return
        if frame.msg_type == MsgType.HEARTBEAT:
            assert isinstance(body, dict)
            body = Status(**body)
            self.last_status = body
        if self._streaming:
            self._stream.append((frame.msg_type, body,
                                 bool(frame.compat & COMPAT_RETRANSMIT)))
