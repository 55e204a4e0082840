"""Host session: HELLO (with a key, its CHALLENGE round), INFO checked, take-over, end.

:class:`Session` opens a session over a :class:`~cdma_lidar.protocol.requests.Requests`:
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
from typing import Any

from cdma_lidar.errors import LinkError, out_of_range
from cdma_lidar.protocol import auth
from cdma_lidar.protocol.framing import MIN_MAX_FRAME, PROTOCOL_VERSION
from cdma_lidar.protocol.messages import SCHEMA_CRC, Auth, HelloFlags, MsgType
from cdma_lidar.protocol.requests import Requests
from cdma_lidar.protocol.trust import DeviceLied, check_info
from cdma_lidar.protocol.views import Info

__all__ = ["Session"]

log = logging.getLogger(__name__)


class Session:
    """A host's session with one device over a request layer (see the module docstring);
    the arguments are :class:`~cdma_lidar.protocol.link.HostLink`'s.

    Args:
        requests: the request layer it says HELLO over and whose session it opens.
        max_frame: largest frame the device may send (bytes), announced in HELLO.
    """

    def __init__(self, requests: Requests, *, max_frame: int, key: bytes | None,
                 take_over: bool, keep_config: bool) -> None:
        if key is not None and len(key) != auth.KEY_BYTES:
            raise out_of_range("key", f"{auth.KEY_BYTES} bytes", len(key))
        self.requests, self.key = requests, key
        self.take_over, self.keep_config = bool(take_over), bool(keep_config)
        self.info: Info | None = None
        self.config: dict[str, Any] | None = None  # last full CONFIG, checked against INFO
        self._host_max = max_frame
        self._nonce = secrets.token_bytes(auth.NONCE_BYTES)
        requests.seq = int.from_bytes(self._nonce[:2], "little")
        requests.on_forget = self._forgotten

    def close(self) -> None:
        """End the session (SESSION_END, one short try: another host may then say HELLO
        without take-over) and close the port."""
        rq = self.requests
        if rq.session is not None:
            try:
                rq.transact(MsgType.SESSION_END, {}, rq.new_seq(), retries=0,
                            timeout_s=min(rq.timeout_s, 0.2))
            except Exception:  # LinkError, SessionLost: the device forgets us when idle
                log.debug("SESSION_END got no answer; the session expires when idle")
            rq.session = None
        with contextlib.suppress(Exception):
            rq.port.close()

    def hello(self) -> Info:
        """Open a session: learn the device's identity, limits, geometry and session id.

        With a key, answers the device's CHALLENGE and checks that INFO is signed with
        the session key (so the device holds the key too). Raises DeviceError (code
        BUSY, field ``session``) when another host owns the device and ``take_over``
        is off; DeviceLied when INFO contradicts itself.
        """
        rq = self.requests
        rq.before_hello()
        flags = int((HelloFlags.TAKE_OVER if self.take_over else 0) |
                    (HelloFlags.KEEP_CONFIG if self.keep_config else 0) |
                    (HelloFlags.FEC if rq.fec else 0))
        fields_ = {"host_max_frame": self._host_max, "flags": flags, "host_nonce": self._nonce,
                   "device_nonce": bytes(auth.NONCE_BYTES), "mac": bytes(auth.MAC_BYTES)}
        for _ in range(2):
            rq.hello_seq = rq.new_seq()
            try:
                reply = rq.transact(MsgType.HELLO, fields_, rq.hello_seq)
            finally:
                rq.hello_seq = None
            if rq.reply is not None and rq.reply.msg_type == MsgType.INFO:
                return self._open(reply, bytes(fields_["device_nonce"]))
            if self.key is None:
                raise LinkError(f"device on {rq.port_name} requires a key: pass --key-file "
                                "FILE or set CDMA_LIDAR_KEY_FILE to the device's key file")
            fields_["device_nonce"] = bytes(reply["device_nonce"])
            fields_["mac"] = auth.hello_mac(self.key, fields_["device_nonce"], self._nonce,
                                            flags, self._host_max)
        raise LinkError("device answered the authenticated HELLO with another CHALLENGE: "
                        "it does not accept this host's key")

    def _open(self, reply: dict[str, Any], device_nonce: bytes) -> Info:
        """Check INFO and make its session ours."""
        rq = self.requests
        try:
            info = Info.from_fields(reply)
        except (TypeError, ValueError) as exc:
            raise DeviceLied(f"device sent an invalid INFO: {exc}") from None
        if info.protocol_version != PROTOCOL_VERSION:
            raise LinkError(f"device speaks protocol version {info.protocol_version}, host "
                            f"{PROTOCOL_VERSION}; update the host or the firmware")
        keys = None
        if self.key is not None:
            keys = self._authenticate(info, device_nonce)
        elif info.auth != Auth.NONE:
            raise DeviceLied("device announced signed frames (INFO.auth = "
                             f"{info.auth}) without asking this host for a key", "auth")
        info = check_info(info)
        if info.schema_crc != SCHEMA_CRC:
            log.warning("device schema 0x%08x differs from host schema 0x%08x: host and "
                        "firmware come from different revisions", info.schema_crc, SCHEMA_CRC)
        self.info = info
        # Requests: what the device accepts, within what this host asked for the line; the
        # device codes its INFO when it agreed to FEC: then so do we.
        rq.open_session(info.session_id, min(info.max_frame, max(self._host_max, MIN_MAX_FRAME)),
                        rq.fec and rq.reply is not None and rq.reply.fec, keys)
        log.info("session 0x%08x with %s (firmware %s, %d channels, max frame %d%s)",
                 info.session_id, info.serial, info.firmware_version, info.channels,
                 info.max_frame, ", signed" if keys else "")
        return info

    def _authenticate(self, info: Info, device_nonce: bytes
                      ) -> tuple[auth.FrameSigner, auth.FrameVerifier]:
        """Check the device's proof and INFO's signature; the session's signing keys."""
        rq = self.requests
        assert rq.reply is not None and self.key is not None
        if info.auth != Auth.HMAC_SHA256 or not auth.equal(
                info.device_mac, auth.device_mac(self.key, self._nonce, device_nonce,
                                                 info.session_id)):
            raise LinkError(f"device on {rq.port_name} did not prove it holds the key "
                            f"(INFO.auth = {info.auth}): it is not the device the key file "
                            "belongs to, or it holds no key (then drop --key-file)")
        to_dev, to_host = auth.session_keys(self.key, self._nonce, device_nonce,
                                            info.session_id)
        rx = auth.FrameVerifier(to_host)
        parts = rq.reply_parts or [rq.reply]  # an INFO in FRAGMENTs: each one is signed
        if any(p.session != info.session_id for p in parts) or not all(map(rx.check, parts)):
            raise LinkError(f"device on {rq.port_name} sent an INFO not signed with the "
                            "session key")
        return auth.FrameSigner(to_dev), rx

    def _forgotten(self) -> None:
        self.info = None
        self.config = None

    def need_info(self) -> Info:
        """INFO of the session (HELLO first when there is none)."""
        if self.info is None:
            self.hello()
        assert self.info is not None
        return self.info

    def request(self, msg_type: MsgType, fields_: dict[str, Any]) -> dict[str, Any]:
        """A request of the session (HELLO first when there is none)."""
        if self.requests.session is None:
            self.hello()
        return self.requests.transact(msg_type, fields_, self.requests.new_seq())
