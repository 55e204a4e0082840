"""Host session: HELLO (with a key, its CHALLENGE round), INFO checked, take-over, end.

:class:`Session` opens a session on top of :class:`~cdma_lidar.protocol.requests.Requests`:
it sends HELLO with this host's nonce, frame limit and flags (TAKE_OVER, KEEP_CONFIG, FEC),
answers a CHALLENGE with the HELLO MAC of the shared key, checks that INFO proves the
device holds the key and is signed with the session key, and from then on signs every
request and checks every frame (:mod:`cdma_lidar.protocol.auth`). Any request made
without a session says HELLO first.
"""

from __future__ import annotations

import contextlib
import logging
import secrets
from typing import Any, Self

from cdma_lidar.errors import LinkError, out_of_range
from cdma_lidar.protocol import auth
from cdma_lidar.protocol.framing import MIN_MAX_FRAME, PROTOCOL_VERSION
from cdma_lidar.protocol.messages import SCHEMA_CRC, Auth, HelloFlags, MsgType
from cdma_lidar.protocol.requests import Requests
from cdma_lidar.protocol.trust import DeviceLied, check_info
from cdma_lidar.protocol.views import Info

__all__ = ["Session"]

log = logging.getLogger(__name__)


class Session(Requests):
    """A host's session with one device (see the module docstring); the arguments are
    :class:`~cdma_lidar.protocol.link.HostLink`'s."""

    def __init__(self, port: Any, timeout_s: float, retries: int, *, key: bytes | None,
                 take_over: bool, keep_config: bool, **kw: Any) -> None:
        super().__init__(port, timeout_s, retries, **kw)
        if key is not None and len(key) != auth.KEY_BYTES:
            raise out_of_range("key", f"{auth.KEY_BYTES} bytes", len(key))
        self.key = key
        self.take_over, self.keep_config = bool(take_over), bool(keep_config)
        self.info: Info | None = None
        self.config: dict[str, Any] | None = None  # last full CONFIG, checked against INFO
        self._host_max = kw["max_frame"]
        self._nonce = secrets.token_bytes(auth.NONCE_BYTES)
        self._seq = int.from_bytes(self._nonce[:2], "little")

    def __enter__(self) -> Self:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def close(self) -> None:
        """End the session (SESSION_END, one short try: another host may then say HELLO
        without take-over) and close the port."""
        if self.session is not None:
            try:
                self._transact(MsgType.SESSION_END, {}, self._new_seq(), retries=0,
                               timeout_s=min(self.timeout_s, 0.2))
            except Exception:  # LinkError, SessionLost: the device forgets us when idle
                log.debug("SESSION_END got no answer; the session expires when idle")
            self.session = None
        with contextlib.suppress(Exception):
            self.port.close()

    def hello(self) -> Info:
        """Open a session: learn the device's identity, limits, geometry and session id.

        With a key, answers the device's CHALLENGE and checks that INFO is signed with
        the session key (so the device holds the key too). Raises DeviceError (code
        BUSY, field ``session``) when another host owns the device and ``take_over``
        is off; DeviceLied when INFO contradicts itself.
        """
        self._forget()
        self.config = None
        self._early = []
        self.coded = False
        flags = int((HelloFlags.TAKE_OVER if self.take_over else 0) |
                    (HelloFlags.KEEP_CONFIG if self.keep_config else 0) |
                    (HelloFlags.FEC if self.fec else 0))
        fields_ = {"host_max_frame": self._host_max, "flags": flags, "host_nonce": self._nonce,
                   "device_nonce": bytes(auth.NONCE_BYTES), "mac": bytes(auth.MAC_BYTES)}
        for _ in range(2):
            self._hello_seq = self._new_seq()
            try:
                reply = self._transact(MsgType.HELLO, fields_, self._hello_seq)
            finally:
                self._hello_seq = None
            if self._reply is not None and self._reply.msg_type == MsgType.INFO:
                return self._open(reply, bytes(fields_["device_nonce"]))
            if self.key is None:
                raise LinkError(f"device on {self._port_name} requires a key: pass --key-file "
                                "FILE or set CDMA_LIDAR_KEY_FILE to the device's key file")
            fields_["device_nonce"] = bytes(reply["device_nonce"])
            fields_["mac"] = auth.hello_mac(self.key, fields_["device_nonce"], self._nonce,
                                            flags, self._host_max)
        raise LinkError("device answered the authenticated HELLO with another CHALLENGE: "
                        "it does not accept this host's key")

    def _open(self, reply: dict[str, Any], device_nonce: bytes) -> Info:
        """Check INFO and make its session ours."""
        try:
            info = Info.from_fields(reply)
        except (TypeError, ValueError) as exc:
            raise DeviceLied(f"device sent an invalid INFO: {exc}") from None
        if info.protocol_version != PROTOCOL_VERSION:
            raise LinkError(f"device speaks protocol version {info.protocol_version}, host "
                            f"{PROTOCOL_VERSION}; update the host or the firmware")
        if self.key is not None:
            self._authenticate(info, device_nonce)
        elif info.auth != Auth.NONE:
            raise DeviceLied("device announced signed frames (INFO.auth = "
                             f"{info.auth}) without asking this host for a key", "auth")
        info = check_info(info)
        if info.schema_crc != SCHEMA_CRC:
            log.warning("device schema 0x%08x differs from host schema 0x%08x: host and "
                        "firmware come from different revisions", info.schema_crc, SCHEMA_CRC)
        self.info, self.session = info, info.session_id
        # Requests: what the device accepts, within what this host asked for the line.
        self.max_frame = min(info.max_frame, max(self._host_max, MIN_MAX_FRAME))
        # The device codes its INFO when it agreed to FEC: then so do we.
        self.coded = self.fec and self._reply is not None and self._reply.fec
        early, self._early = self._early, []
        for frame in early:  # e.g. SESSION_LOST right behind INFO
            self._dispatch(frame)
        log.info("session 0x%08x with %s (firmware %s, %d channels, max frame %d%s)",
                 self.session, info.serial, info.firmware_version, info.channels,
                 info.max_frame, ", signed" if self._tx else "")
        return info

    def _authenticate(self, info: Info, device_nonce: bytes) -> None:
        """Check the device's proof and INFO's signature; set up the session's signing."""
        assert self._reply is not None and self.key is not None
        if info.auth != Auth.HMAC_SHA256 or not auth.equal(
                info.device_mac, auth.device_mac(self.key, self._nonce, device_nonce,
                                                 info.session_id)):
            raise LinkError(f"device on {self._port_name} did not prove it holds the key "
                            f"(INFO.auth = {info.auth}): it is not the device the key file "
                            "belongs to, or it holds no key (then drop --key-file)")
        to_dev, to_host = auth.session_keys(self.key, self._nonce, device_nonce,
                                            info.session_id)
        rx = auth.FrameVerifier(to_host)
        parts = self._reply_parts or [self._reply]  # an INFO in FRAGMENTs: each one is signed
        if any(p.session != info.session_id for p in parts) or not all(map(rx.check, parts)):
            raise LinkError(f"device on {self._port_name} sent an INFO not signed with the "
                            "session key")
        self._tx, self._rx = auth.FrameSigner(to_dev), rx

    def _forget(self) -> None:
        super()._forget()
        self.info = None

    def _need_info(self) -> Info:
        if self.info is None:
            self.hello()
        assert self.info is not None
        return self.info

    def _request(self, msg_type: MsgType, fields_: dict[str, Any]) -> dict[str, Any]:
        """A request of the session (HELLO first when there is none)."""
        if self.session is None:
            self.hello()
        return self._transact(msg_type, fields_, self._new_seq())
