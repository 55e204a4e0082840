"""Device sessions: who owns the device, HELLO (with its challenge-response), take-over.

docs/protocol.md sections 4 and 5 are the contract. The connections to one device (the TCP
server gives each its own :class:`~cdma_lidar.protocol.endpoint.DeviceEndpoint`) share one
:class:`DeviceCore`: whose :class:`DeviceSession` owns the device, and the boot configuration
a new session starts from. Each connection's loop changes only its own session: a HELLO that
takes the device marks the old owner :attr:`DeviceSession.lost`, whose loop ends its session
at its next poll, and the HELLO is answered once it has. A handler is ``(request, fields) ->
Reply``; it refuses by returning a NAK or raising ``ConfigError`` / ``DeviceError``.
"""

from __future__ import annotations

import dataclasses
import logging
import secrets
import time
from collections.abc import Callable
from typing import Any

import numpy as np
from numpy.typing import NDArray

from cdma_lidar.errors import DeviceError, FieldError, FrameError, out_of_range
from cdma_lidar.protocol import auth
from cdma_lidar.protocol.config_keys import config_key, decode_config, encode_config
from cdma_lidar.protocol.framing import PROTOCOL_VERSION, Frame, frame_size
from cdma_lidar.protocol.messages import (
    SCHEMA_CRC,
    Auth,
    CaptureKind,
    ErrorCode,
    HelloFlags,
    MsgType,
    ScanEndReason,
    SessionLostReason,
    decode_payload,
    encode_payload,
    head_size,
)
from cdma_lidar.protocol.streams import Engine, Streams
from cdma_lidar.protocol.transmit import CONTROL, REPAIR, Reply, Transmitter, clip

__all__ = ["DeviceCore", "DeviceSession", "EndpointStats", "new_session_id"]

log = logging.getLogger(__name__)


@dataclasses.dataclass
class EndpointStats:
    """Counters of one connection (or, as ``DeviceCore.totals``, of all since boot)."""

    rx_requests: int = 0
    replays: int = 0
    stale: int = 0
    ignored: int = 0
    naks: int = 0
    tx_frames: int = 0
    columns_sent: int = 0
    auth_rejected: int = 0  #: frames dropped for a wrong MAC or a replayed counter
    auth_throttled: int = 0  #: HELLO MACs not checked: the connection's back-off was running
    sessions: int = 0  #: sessions opened on this connection


class DeviceCore:
    """What every connection to one device shares: the application, its ``engine``
    (default: one on its own thread), the session, the counters since boot.

    ``key``: the shared secret (32 bytes, :mod:`cdma_lidar.protocol.auth`); None: no access
    control (serial ports, ptys, loopback with ``--insecure``). ``session_idle_s``: the
    idle expiry (s, docs/protocol.md section 4). ``clock``: monotonic (s).
    """

    def __init__(self, app: Any, *, key: bytes | None = None, session_idle_s: float = 10.0,
                 clock: Callable[[], float] = time.monotonic,
                 engine: Engine | None = None) -> None:
        if not 0.001 <= session_idle_s <= 4_294_967.295:
            raise out_of_range("session_idle_s", "0.001 to 4294967 s (INFO.session_idle_ms)",
                               session_idle_s)
        if key is not None and len(key) != auth.KEY_BYTES:
            raise out_of_range("key", f"{auth.KEY_BYTES} bytes", len(key))
        self.app, self.key, self.clock = app, key, clock
        self.session_idle_s, self.engine = float(session_idle_s), engine or Engine()
        self.owner: DeviceSession | None = None
        self.owner_nonce = b""  # the owner's HELLO host nonce
        self.opened = self.last_active = 0.0
        try:
            power: NDArray | None = np.array(app.get_power(), dtype=np.uint16)
        except DeviceError:
            power = None
        self._boot = (app.get_config(), power)  # what a new session starts from
        self.backoff = auth.Backoff(clock)  # failed authentication: the global budget
        #: Since boot (the core's creation), over every connection: what STATUS reports.
        self.booted, self.totals, self.rx_frames, self.rx_errors = clock(), EndpointStats(), 0, 0

    def touch(self, session: DeviceSession) -> None:
        """The owner was heard from (or its stream ended)."""
        if self.owner is session:
            self.last_active = self.clock()

    def restore_defaults(self) -> None:
        """Put the boot configuration and power back (the engine is idle)."""
        cfg, power = self._boot
        try:
            if self.app.get_config() != cfg:
                self.app.set_config(dict(cfg))
            if power is not None and not np.array_equal(self.app.get_power(), power):
                self.app.set_power(0, 0, power)
        except Exception:  # the device must stay on the line; the host reads the config
            log.exception("cannot restore the boot configuration for a new session")


def new_session_id(old: int = 0) -> int:
    """A random non-zero session id different from ``old``."""
    while True:
        s = secrets.randbits(32)
        if s and s != old:
            return s


class DeviceSession:
    """The session of one connection: open or not, its keys, the challenge sent, failed
    authentications, the capture being read, the requests it makes of the application and
    those held until it is :attr:`ready`.

    ``tx`` (session id, max frame, signing, coding), ``streams`` (ended with the session)
    and ``stats`` are the connection's; ``session_id`` (of the first session), ``max_frame``,
    ``fec`` and ``heartbeat_s`` as :class:`~cdma_lidar.protocol.endpoint.DeviceEndpoint`
    takes them (INFO says them); ``peer`` names the other end in the log.
    """

    def __init__(self, core: DeviceCore, tx: Transmitter, streams: Streams,
                 stats: EndpointStats, *, session_id: int | None, max_frame: int, fec: bool,
                 heartbeat_s: float, peer: str) -> None:
        self.core, self.app, self.tx, self.streams, self.stats = \
            core, core.app, tx, streams, stats
        self.max_frame, self.fec, self.heartbeat_s = max_frame, fec, heartbeat_s
        self.peer, self.open = peer, False
        tx.session = session_id or new_session_id()  # the first session's (0, None: random)
        self.sessionless_since = core.clock()  # since when it has had no session (s)
        self.verifier: auth.FrameMac | None = None  # checks the host's signed frames
        self.challenge: bytes | None = None  # nonce of the last CHALLENGE sent
        #: The last signed session that ended on this connection: (id, signer, verifier).
        self.ended: tuple[int, auth.FrameMac | None, auth.FrameMac] | None = None
        #: (wrong HELLO MACs on this connection since its last success, the last one's time)
        self.auth_failures: tuple[int, float] = (0, 0.0)
        #: Set by another connection's HELLO that took the device: (reason, detail).
        self.lost: tuple[SessionLostReason, str] | None = None
        self._previous: DeviceSession | None = None  # the owner a passed HELLO waits for
        #: The capture being read out: ((kind, column, channel), its data).
        self.capture: tuple[tuple[int, int, int], NDArray] | None = None
        #: Requests waiting for the application, in arrival order: (request, its CRC).
        self.held: list[tuple[Frame, int]] = []

    @property
    def id(self) -> int:
        """The current (or first) session id."""
        return self.tx.session

    def handlers(self) -> dict[MsgType, Callable[[Frame, dict], Reply]]:
        return {MsgType.HELLO: self._hello, MsgType.SESSION_END: lambda req, f: self.tx.ack(req),
                MsgType.CONFIG_GET: self._config_get, MsgType.CONFIG_SET: self._config_set,
                MsgType.POWER_SET: self._power_set, MsgType.POWER_GET: self._power_get,
                MsgType.CAPTURE: self._capture}

    def admit(self, req: Frame) -> bool:
        """A request other than HELLO may go on: it names this open session and, in a
        signed session, is :meth:`verified`. Otherwise it is refused (NAK WRONG_SESSION, or
        AUTH_REQUIRED unsigned) or dropped (forged or replayed)."""
        good = self.verified(req)
        if not self.open or req.session != self.id:
            detail = (f"this connection's session is 0x{self.id:08x}; send HELLO"
                      if self.open else "no session is open here: send HELLO")
            # A request of the signed session that ended here hears the NAK signed with
            # that session's key (its host drops unsigned frames).
            self.tx.answer(req, self.tx.nak(req, ErrorCode.WRONG_SESSION, "session", detail,
                                            bool(good)), self.ended and self.ended[1])
            return False
        if self.verifier is not None and not good:
            if good is False:
                self.tx.answer(req, self.tx.nak(
                    req, ErrorCode.AUTH_REQUIRED, "incompat_flags",
                    "this device accepts only signed frames: HELLO with its key", False))
            return False
        self.core.touch(self)
        return True

    def verified(self, req: Frame) -> bool | None:
        """True: ``req`` (joined: each piece) passed the MAC and counter check of the open
        signed session or of the signed session that ended here; None: a signed frame of the
        open one failed (forged or replayed: dropped unanswered, counted against the
        back-off); else False."""
        if req.joined:
            return True
        ours = self.open and req.session == self.id
        sid, _, ended = self.ended or (None, None, None)
        verifier = self.verifier if ours else ended if req.session == sid else None
        if verifier is not None and verifier.check(req):
            return True
        if verifier is None or not (ours and req.sig):
            return False
        self.stats.auth_rejected += 1
        self.core.backoff.failed(f"{self.peer} (session frames)", "a frame failed authentication")
        return None

    def hello_gate(self, req: Frame) -> Reply | None:
        """What HELLO gets from the session state alone, at once: MALFORMED, a CHALLENGE,
        AUTH_FAILED (a wrong MAC, or one sent during this connection's back-off) or BUSY. None:
        the HELLO passed and took the device from its owner, which hears SESSION_LOST (at once
        on this connection, at its next poll on another); the session opens when it is handled."""
        core = self.core
        try:
            f = decode_payload(MsgType.HELLO, req.payload)
        except FrameError as exc:
            return self.tx.nak(req, ErrorCode.MALFORMED, exc.field or "", str(exc))
        if core.key is not None:
            if not any(f["mac"]) or self.challenge is None or \
                    not auth.equal(f["device_nonce"], self.challenge):
                self.challenge = secrets.token_bytes(auth.NONCE_BYTES)
                return (MsgType.CHALLENGE, encode_payload(
                    MsgType.CHALLENGE, {"device_nonce": self.challenge}), False)
            wait = core.backoff.wait_s(*self.auth_failures)  # > 0: the MAC is not checked
            if wait > 0 or not auth.equal(f["mac"], auth.hello_mac(
                    core.key, self.challenge, bytes(f["host_nonce"]), f["flags"],
                    f["host_max_frame"])):
                self.challenge = None
                if wait > 0:
                    self.stats.auth_throttled += 1
                    return self.tx.nak(req, ErrorCode.AUTH_FAILED, "mac", "too many failed "
                                       "authentications on this connection: retry in "
                                       f"{wait:.1f} s", False)
                self.stats.auth_rejected += 1
                self.auth_failures = (self.auth_failures[0] + 1, core.clock())
                core.backoff.failed(self.peer,
                                    "HELLO with a wrong MAC (the host holds another key)")
                return self.tx.nak(req, ErrorCode.AUTH_FAILED, "mac",
                                   "the MAC does not match this device's key", False)
        owner, nonce, now = core.owner, bytes(f["host_nonce"]), core.clock()
        if owner is not None and not (owner is self and core.owner_nonce == nonce):
            idle = 0.0 if owner.streams.stream is not None else max(0.0, now - core.last_active)
            if idle >= core.session_idle_s:
                lost = (SessionLostReason.EXPIRED, f"idle {idle:.1f} s, longer than "
                        f"{core.session_idle_s:g} s: another host opened a session")
            elif f["flags"] & HelloFlags.TAKE_OVER:
                lost = (SessionLostReason.TAKEN_OVER, "another host took over the device "
                        f"after {now - core.opened:.1f} s")
            else:
                return self.tx.nak(req, ErrorCode.BUSY, "session",
                                   f"another host owns the device: its session opened "
                                   f"{now - core.opened:.1f} s ago and has been idle "
                                   f"{idle:.1f} s (expires after {core.session_idle_s:g} s "
                                   "idle); say HELLO with take-over to end it", False)
            if owner is self:
                self.lose(*lost)
            else:
                owner.lost, self._previous = lost, owner
        # Its stream ends now: the engine has cleaned it up when the HELLO calls the app.
        self.streams.stop(ScanEndReason.ABORTED, send_end=False)
        core.owner, core.owner_nonce = self, nonce
        return None

    @property
    def ready(self) -> bool:
        """This connection may call the application now: it owns the device, the owner its
        HELLO took the device from has ended its session (its loop clears ``lost``), and
        the engine is idle."""
        prev = self._previous  # its end() clears lost (and open with it)
        return self.core.owner is self and not (prev and prev.lost) and self.core.engine.idle

    def _hello(self, req: Frame, f: dict) -> Reply:
        """Open a fresh session (after :meth:`hello_gate`, the engine idle)."""
        core = self.core
        if core.owner is not self:
            return self.tx.nak(req, ErrorCode.BUSY, "session",
                               "another host took over the device meanwhile", False)
        self.end()
        core.owner, self.auth_failures, self._previous = self, (0, 0.0), None
        nonce, device_nonce = core.owner_nonce, self.challenge or bytes(auth.NONCE_BYTES)
        self.challenge = None
        if not f["flags"] & HelloFlags.KEEP_CONFIG:
            core.restore_defaults()
        if self.stats.sessions:
            self.tx.session = new_session_id(self.id)
        self.stats.sessions += 1
        self.open = True
        core.opened = core.last_active = core.clock()
        self.tx.max_frame = min(self.max_frame, f["host_max_frame"])
        self.tx.coded = self.fec and bool(f["flags"] & HelloFlags.FEC)
        mac = bytes(auth.MAC_BYTES)
        if core.key is not None:
            self.verifier, self.tx.signer = auth.session_macs(core.key, nonce, device_nonce,
                                                              self.id)
            mac = auth.device_mac(core.key, nonce, device_nonce, self.id)
        info = dataclasses.replace(  # the link fields' ranges were checked when given
            self.app.info(), protocol_version=PROTOCOL_VERSION, session_id=self.id,
            schema_crc=SCHEMA_CRC, max_frame=self.max_frame, ring_columns=self.streams.ring_columns,
            heartbeat_ms=round(self.heartbeat_s * 1000),
            session_idle_ms=round(core.session_idle_s * 1000),
            auth=int(Auth.HMAC_SHA256 if core.key is not None else Auth.NONE), device_mac=mac)
        log.info("HELLO from host %s: session 0x%08x, max frame %d%s", nonce[:4].hex(),
                 self.id, self.tx.max_frame, ", signed" if self.tx.signer else "")
        return (MsgType.INFO, encode_payload(MsgType.INFO, info.to_fields()),
                self.tx.signer is not None)

    def end(self) -> None:
        """Forget the session's stream (its clean-up goes to the engine), ring, held requests,
        capture, keys, ownership and a loss not yet acted on: the device is free at once."""
        self.streams.stop(ScanEndReason.ABORTED, send_end=False)
        self.tx.drop(REPAIR)
        self.streams.ring.clear()
        self.held.clear()
        if self.open:
            self.sessionless_since = self.core.clock()
            if self.verifier is not None:  # to sign its NAK WRONG_SESSION
                self.ended = (self.id, self.tx.signer, self.verifier)
        self.open, self.capture, self.verifier, self.lost = False, None, None, None
        self.tx.signer, self.tx.coded = None, False
        if self.core.owner is self:
            self.core.owner = None

    def lose(self, reason: SessionLostReason, detail: str) -> None:
        """Another HELLO ended this session: tell its host, then end it."""
        if self.open:
            log.info("session 0x%08x lost: %s", self.id, detail)
            self.tx.send(CONTROL, MsgType.SESSION_LOST, encode_payload(  # queued: never fails
                MsgType.SESSION_LOST, {"reason": int(reason), "detail": clip(detail)}))
        self.end()

    # ---- what the session asks of the application -------------------------------------
    def _config_get(self, req: Frame, f: dict) -> Reply:
        st = self.streams.stream  # its configuration is still current (no CONFIG_SET)
        values = dict(st.config) if st is not None else self.app.get_config()
        if f["keys"]:
            try:
                want = [config_key(kid).name for kid in f["keys"]]
            except FieldError as exc:  # it names the key's id
                return self.tx.nak(req, ErrorCode.UNKNOWN_KEY, f"key {exc.field}")
            values = {n: values[n] for n in want if n in values}
        # The model checked its configuration: encoded as it is (the host checks it).
        payload = encode_payload(MsgType.CONFIG, {"items": encode_config(values, check=False)})
        return self.tx.reply(req, MsgType.CONFIG, payload, "keys",
                             "ask for fewer keys per CONFIG_GET")

    def _config_set(self, req: Frame, f: dict) -> Reply:
        if self.streams.stream is not None:
            return self.tx.nak(req, ErrorCode.BUSY, "", "abort the running scan first")
        cfg = decode_config(f["items"])
        if cfg.unknown:
            return self.tx.nak(req, ErrorCode.UNKNOWN_KEY, f"key {cfg.unknown[0]}",
                               "key not known to this device")
        for name in cfg.values:
            if config_key(name).read_only:
                return self.tx.nak(req, ErrorCode.READ_ONLY, name, f"{name} is read-only")
        self.app.set_config(cfg.values)
        return self.tx.ack(req)

    def _power_set(self, req: Frame, f: dict) -> Reply:
        power = np.asarray(f["power"], dtype=np.uint16).reshape(f["channels"], f["columns"])
        self.app.set_power(f["channel_start"], f["column_start"], power)
        return self.tx.ack(req)

    def _power_get(self, req: Frame, f: dict) -> Reply:
        m = np.asarray(self.app.get_power(), dtype=np.uint16)
        r0, c0, nr, nc = f["channel_start"], f["column_start"], f["channels"], f["columns"]
        for name, start, n, have in (("channels", r0, nr, m.shape[0]),
                                     ("columns", c0, nc, m.shape[1])):
            if start + n > have:
                return self.tx.nak(req, ErrorCode.OUT_OF_RANGE, name,
                                   f"{name[:-1]}_start + {name} must be at most {have}")
        payload = encode_payload(MsgType.POWER, {**f, "power": m[r0:r0 + nr, c0:c0 + nc]})
        return self.tx.reply(req, MsgType.POWER, payload, "columns",
                             "ask for a smaller rectangle per POWER_GET")

    def _capture(self, req: Frame, f: dict) -> Reply:
        key = (f["kind"], f["column"], f["channel"])
        if f["offset"] == 0 or self.capture is None or self.capture[0] != key:
            if f["offset"] != 0:
                return self.tx.nak(req, ErrorCode.NOT_AVAILABLE, "offset",
                                   "read offset 0 first to take a capture")
            data = np.asarray(self.app.capture(CaptureKind(f["kind"]), f["column"],
                                               f["channel"])).ravel()
            if data.dtype.kind not in "iu":
                raise DeviceError("capture is not integer data", code=ErrorCode.INTERNAL)
            lo, hi = (int(data.min()), int(data.max())) if data.size else (0, 0)
            dt = next(t for t in (np.int16, np.int32, np.int64)
                      if np.iinfo(t).min <= lo and hi <= np.iinfo(t).max)
            self.capture = (key, data.astype(np.dtype(dt).newbyteorder("<")))
        arr = self.capture[1]
        total, off = arr.size, f["offset"]
        if off > total:
            return self.tx.nak(req, ErrorCode.OUT_OF_RANGE, "offset",
                               f"offset must be 0..{total}, not {off}")
        room = (self.tx.max_frame - frame_size(head_size(MsgType.CAPTURE_DATA),
                                               self.tx.signer is not None)) // arr.itemsize
        n = max(0, min(f["max_count"], room, total - off))
        return self.tx.reply(req, MsgType.CAPTURE_DATA, encode_payload(MsgType.CAPTURE_DATA, {
            "kind": f["kind"], "column": f["column"], "channel": f["channel"],
            "elem_bytes": arr.itemsize, "total": total, "offset": off,
            "data": arr[off:off + n].tobytes()}))
