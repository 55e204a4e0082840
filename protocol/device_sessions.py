"""Device sessions: who owns the device, HELLO (with its challenge-response), take-over.

One device may be reached over several connections at once (the TCP server gives each
its own :class:`~cdma_lidar.protocol.endpoint.DeviceEndpoint`). :class:`DeviceCore`,
shared by them, knows which connection's host owns the session, since when and how
long it has been idle, and the boot configuration a new session starts from. HELLO
opens a session (docs/protocol.md, Sessions and Access control): another host gets
NAK BUSY unless it takes over or the session expired, and the old owner then gets
SESSION_LOST.
"""

from __future__ import annotations

import contextlib
import dataclasses
import logging
import secrets
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import NDArray

from cdma_lidar.errors import DeviceError, out_of_range
from cdma_lidar.protocol import auth
from cdma_lidar.protocol.framing import PROTOCOL_VERSION, Frame
from cdma_lidar.protocol.handlers import Reply, ack, clip, nak
from cdma_lidar.protocol.messages import (
    SCHEMA_CRC,
    Auth,
    ErrorCode,
    HelloFlags,
    MsgType,
    ScanEndReason,
    SessionLostReason,
    encode_payload,
)
from cdma_lidar.protocol.streams import finish, stop_stream
from cdma_lidar.protocol.transmit import CONTROL, REPAIR

if TYPE_CHECKING:
    from cdma_lidar.protocol.endpoint import DeviceApp, DeviceEndpoint

__all__ = ["HANDLERS", "DeviceCore", "EndpointStats", "hello_gate", "new_session_id"]

log = logging.getLogger(__name__)


@dataclass
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
    """What every connection to one device shares: the application, its lock, the session.

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
        self.app, self.key, self.clock = app, key, clock
        self.session_idle_s = float(session_idle_s)
        #: Serialises every call into the application. Lock order: app_lock before any
        #: endpoint's lock, never the reverse.
        self.app_lock = threading.RLock()
        self.owner: DeviceEndpoint | None = None
        self.owner_nonce = b""
        self.opened = self.last_active = 0.0
        self._boot: tuple[dict[str, Any], NDArray | None] | None = None
        self.backoff = auth.Backoff(clock)  # failed authentication: the global budget
        #: Since boot (the core's creation), over every connection: what STATUS reports.
        self.booted = clock()
        self.totals = EndpointStats()
        self.rx_frames = self.rx_errors = 0

    def idle_s(self, now: float) -> float:
        """Seconds the owner's session has been idle (0 while it streams)."""
        if self.owner is None or self.owner.stream is not None:
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

    def restore_defaults(self, keep: bool) -> None:
        """Remember the boot configuration and power once; unless ``keep``, put them back
        (caller holds app_lock)."""
        if self._boot is None:
            try:
                power: NDArray | None = np.array(self.app.get_power(), dtype=np.uint16)
            except DeviceError:
                power = None
            self._boot = (self.app.get_config(), power)
        if keep:
            return
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


def hello_gate(ep: DeviceEndpoint, req: Frame, f: dict) -> Reply | None:
    """What HELLO gets without the application: a CHALLENGE, AUTH_FAILED (a wrong MAC,
    or one sent during this connection's back-off) or BUSY; None: open a session.

    Runs in the polling thread, so a HELLO is refused at once whatever the application
    is computing, and again in the request worker.
    """
    core = ep.core
    if core.key is not None:
        if not any(f["mac"]) or ep.challenge is None or \
                not auth.equal(f["device_nonce"], ep.challenge):
            ep.challenge = secrets.token_bytes(auth.NONCE_BYTES)
            return (MsgType.CHALLENGE, encode_payload(
                MsgType.CHALLENGE, {"device_nonce": ep.challenge}), False)
        wait = core.backoff.wait_s(*ep.auth_failures)
        if wait > 0:
            ep.challenge = None
            ep.stats.auth_throttled += 1
            return nak(ep, req, ErrorCode.AUTH_FAILED, "mac", "too many failed "
                       f"authentications on this connection: retry in {wait:.1f} s", False)
        want = auth.hello_mac(core.key, ep.challenge, bytes(f["host_nonce"]), f["flags"],
                              f["host_max_frame"])
        if not auth.equal(want, f["mac"]):
            ep.challenge = None
            ep.stats.auth_rejected += 1
            ep.auth_failures = (ep.auth_failures[0] + 1, core.clock())
            core.backoff.failed(ep.peer, "HELLO with a wrong MAC (the host holds another key)")
            return nak(ep, req, ErrorCode.AUTH_FAILED, "mac",
                       "the MAC does not match this device's key", False)
    owner = core.owner
    if owner is None or (owner is ep and core.owner_nonce == bytes(f["host_nonce"])):
        return None
    now = core.clock()
    idle = core.idle_s(now)
    if idle >= core.session_idle_s or f["flags"] & HelloFlags.TAKE_OVER:
        return None
    return nak(ep, req, ErrorCode.BUSY, "session",
               f"another host owns the device: its session opened {now - core.opened:.1f} s "
               f"ago and has been idle {idle:.1f} s (expires after {core.session_idle_s:g} s "
               "idle); say HELLO with take-over to end it", False)


def _hello(ep: DeviceEndpoint, req: Frame, f: dict, after: list) -> Reply:
    """Challenge (with a key), check ownership, then open a fresh session.

    Runs in the request worker, holding app_lock and the endpoint's lock.
    """
    refusal = hello_gate(ep, req, f)
    if refusal is not None:
        return refusal
    core = ep.core
    ep.auth_failures = (0, 0.0)
    nonce = bytes(f["host_nonce"])
    now = core.clock()
    owner = core.owner
    if owner is not None and not (owner is ep and core.owner_nonce == nonce):
        idle = core.idle_s(now)
        if idle >= core.session_idle_s:
            lost = (SessionLostReason.EXPIRED, f"idle {idle:.1f} s, longer than "
                    f"{core.session_idle_s:g} s: another host opened a session")
        else:
            lost = (SessionLostReason.TAKEN_OVER, "another host took over the device "
                    f"after {now - core.opened:.1f} s")
        if owner is ep:
            _lose(ep, *lost)
        else:
            with owner.lock:  # lock order: app_lock, then one endpoint's lock
                _lose(owner, *lost)
    _end_session(ep)
    device_nonce = ep.challenge or bytes(auth.NONCE_BYTES)
    ep.challenge = None
    core.restore_defaults(keep=bool(f["flags"] & HelloFlags.KEEP_CONFIG))
    ep.config = ep.app.get_config()
    if ep.stats.sessions:
        ep.tx.session = new_session_id(ep.session)
    ep.stats.sessions += 1
    ep.session_open = True
    ep.last_seq = None
    core.owner, core.owner_nonce = ep, nonce
    core.opened = core.last_active = now
    ep.tx.max_frame = min(ep.max_frame, f["host_max_frame"])
    ep.tx.coded = ep.fec and bool(f["flags"] & HelloFlags.FEC)
    mac = bytes(auth.MAC_BYTES)
    if core.key is not None:
        to_dev, to_host = auth.session_keys(core.key, nonce, device_nonce, ep.session)
        ep.tx.signer, ep.verifier = auth.FrameSigner(to_host), auth.FrameVerifier(to_dev)
        mac = auth.device_mac(core.key, nonce, device_nonce, ep.session)
    ep.info = info = dataclasses.replace(
        ep.app.info(), protocol_version=PROTOCOL_VERSION, session_id=ep.session,
        schema_crc=SCHEMA_CRC, max_frame=ep.max_frame, ring_columns=min(ep.ring_columns, 65535),
        heartbeat_ms=max(1, min(65535, round(ep.heartbeat_s * 1000))),
        session_idle_ms=max(1, min(2**32 - 1, round(core.session_idle_s * 1000))),
        auth=int(Auth.HMAC_SHA256 if core.key is not None else Auth.NONE), device_mac=mac)
    log.info("HELLO from host %s: session 0x%08x, max frame %d%s", nonce[:4].hex(),
             ep.session, ep.tx.max_frame, ", signed" if ep.tx.signer else "")
    return (MsgType.INFO, encode_payload(MsgType.INFO, info.to_fields()), ep.tx.signer is not None)


def _end_session(ep: DeviceEndpoint) -> None:
    """Forget the session's stream, ring, capture, keys and ownership; end the last stream
    for the application (caller holds app_lock and the endpoint's lock)."""
    stop_stream(ep, ScanEndReason.ABORTED, send_end=False)
    if ep.latest is not None:
        finish(ep, ep.latest)
    ep.tx.drop(REPAIR)
    ep.ring.clear()
    ep.capture = None
    if ep.session_open and ep.verifier is not None:  # to sign its NAK WRONG_SESSION
        ep.ended = (ep.session, ep.tx.signer, ep.verifier)
    ep.tx.signer = ep.verifier = None
    ep.tx.coded = False
    if ep.session_open:
        ep.sessionless_since = ep.core.clock()
    ep.session_open = False
    ep.core.release(ep)


def _lose(ep: DeviceEndpoint, reason: SessionLostReason, detail: str) -> None:
    """Another connection's HELLO ends ``ep``'s session: tell its host (caller holds the
    core's app_lock and ``ep``'s lock)."""
    if ep.session_open:
        log.info("session 0x%08x lost: %s", ep.session, detail)
        with contextlib.suppress(OSError):  # that host is gone anyway
            ep.tx.send(CONTROL, MsgType.SESSION_LOST, encode_payload(
                MsgType.SESSION_LOST, {"reason": int(reason), "detail": clip(detail)}))
    _end_session(ep)


def _session_end(ep: DeviceEndpoint, req: Frame, f: dict, after: list) -> Reply:
    """The host closes its link: ACK (signed), then forget the session."""
    def end() -> None:
        _end_session(ep)
        log.info("session 0x%08x ended by its host", ep.session)

    after.append(end)
    return ack(ep, req)


HANDLERS = {MsgType.HELLO: _hello, MsgType.SESSION_END: _session_end}
