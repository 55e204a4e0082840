"""Access control: the shared key, HELLO's challenge-response and per-session frame signing.

docs/protocol.md section 5 is the contract: a 32-byte key in a file of mode 0600
(:func:`load_or_create_key`), HELLO proved with HMAC-SHA256 both ways (:func:`hello_mac`,
:func:`device_mac`), one key per direction (:func:`session_macs`), and every later frame
signed with a u64 counter and a 16-byte truncated MAC (:class:`FrameMac`); :class:`Backoff`
slows a guesser, never the key holder.
"""

from __future__ import annotations

import hashlib
import hmac
import logging
import os
import secrets
import stat
import struct
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

from cdma_lidar.errors import ConfigError
from cdma_lidar.protocol.framing import SIGNATURE_SIZE, Frame

__all__ = ["KEY_BYTES", "MAC_BYTES", "NONCE_BYTES", "Backoff", "FrameMac", "device_mac",
           "hello_mac", "load_key", "load_or_create_key", "session_macs"]

log = logging.getLogger(__name__)

#: Bytes of the shared key, of a nonce in HELLO and CHALLENGE, of the HELLO and INFO MACs
#: (full HMAC-SHA256).
KEY_BYTES, NONCE_BYTES, MAC_BYTES = 32, 16, 32
_COUNTER = struct.Struct("<Q")  # the signature's counter; its truncated MAC follows


# ---- key file --------------------------------------------------------------------------------
def load_key(path: str | Path) -> bytes:
    """Read a key file: 64 hex digits (32 bytes), whitespace ignored.

    Raises ConfigError naming the file when it is missing, unreadable, not a key,
    or readable by group or others (the key would not be secret).
    """
    p = Path(path)

    def bad(what: str) -> ConfigError:
        return ConfigError(f"key file {str(p)!r} {what}", "key_file")

    try:
        mode = p.stat().st_mode
        text = p.read_text(encoding="ascii").strip()
    except (OSError, UnicodeDecodeError) as exc:
        raise bad(f"cannot be read ({exc})") from None
    if mode & (stat.S_IRWXG | stat.S_IRWXO):
        raise bad(f"must be readable by its owner only (mode 0600), not mode "
                  f"{stat.S_IMODE(mode):04o}: chmod 600 it")
    try:
        key = bytes.fromhex(text)
    except ValueError:
        key = b""
    if len(key) != KEY_BYTES:
        raise bad(f"must hold {2 * KEY_BYTES} hex digits ({KEY_BYTES} bytes), not "
                  f"{len(text)} characters")
    return key


def load_or_create_key(path: str | Path) -> tuple[bytes, bool]:
    """(the key in ``path``, False); if absent, (a fresh random key, True), written there
    exclusively (never overwritten) with mode 0600."""
    p = Path(path)
    try:
        fd = os.open(p, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
    except FileExistsError:
        return load_key(p), False
    except OSError as exc:
        raise ConfigError(f"key file {str(p)!r} cannot be created ({exc.strerror})",
                          "key_file") from None
    key = secrets.token_bytes(KEY_BYTES)
    with os.fdopen(fd, "w", encoding="ascii") as fh:
        fh.write(key.hex() + "\n")
    log.info("created key file %s", p)
    return key, True


# ---- HELLO challenge-response ------------------------------------------------------------------
def _mac(key: bytes, *parts: bytes) -> bytes:
    return hmac.new(key, b"".join(parts), hashlib.sha256).digest()


def hello_mac(key: bytes, device_nonce: bytes, host_nonce: bytes, flags: int,
              host_max_frame: int) -> bytes:
    """The host's proof in HELLO (32 bytes)."""
    return _mac(key, b"cdma-lidar hello", device_nonce, host_nonce,
                struct.pack("<BH", flags, host_max_frame))


def device_mac(key: bytes, host_nonce: bytes, device_nonce: bytes, session: int) -> bytes:
    """The device's proof in INFO (32 bytes): it holds the key too."""
    return _mac(key, b"cdma-lidar device", host_nonce, device_nonce, struct.pack("<I", session))


#: Constant-time comparison of two MACs (or nonces).
equal = hmac.compare_digest


# ---- frame signing ---------------------------------------------------------------------------
@dataclass
class FrameMac:
    """One direction of a session: its key, keyed once (each frame copies the keyed
    HMAC-SHA256 state: the key's two pad blocks are not hashed again per frame), and
    ``counter``, the counter of the last frame signed (the first is 1) or accepted."""

    key: bytes
    counter: int = 0

    def __post_init__(self) -> None:
        self._keyed = hmac.new(self.key, digestmod=hashlib.sha256)

    def _frame_mac(self, data: bytes, counter: bytes) -> bytes:
        """Truncated MAC of ``data`` (header + payload) and the packed counter."""
        h = self._keyed.copy()
        h.update(data)
        h.update(counter)
        return h.digest()[:SIGNATURE_SIZE - _COUNTER.size]

    def sign(self, data: bytes) -> bytes:
        """Signature of ``data`` (header + payload): the next counter + truncated HMAC."""
        self.counter += 1
        c = _COUNTER.pack(self.counter)
        return c + self._frame_mac(data, c)

    def check(self, frame: Frame) -> bool:
        """True if ``frame`` is signed with this key and newer than every frame accepted."""
        c = frame.sig[:_COUNTER.size]
        if len(frame.sig) != SIGNATURE_SIZE or \
                not equal(self._frame_mac(frame.signed_bytes(), c), frame.sig[_COUNTER.size:]):
            return False
        (counter,) = _COUNTER.unpack(c)
        if newer := counter > self.counter:
            self.counter = counter
        return newer


def session_macs(key: bytes, host_nonce: bytes, device_nonce: bytes,
                 session: int) -> tuple[FrameMac, FrameMac]:
    """(host -> device, device -> host) :class:`FrameMac` of one session, counters 0: the
    host signs with the first and checks with the second, the device the other way round."""
    s = struct.pack("<I", session)
    return (FrameMac(_mac(key, b"cdma-lidar to device", host_nonce, device_nonce, s)),
            FrameMac(_mac(key, b"cdma-lidar to host", host_nonce, device_nonce, s)))


class Backoff:
    """Back-off after failed authentication, which slows a guesser, never the key holder
    (docs/protocol.md section 5 gives the rule with these defaults): after ``n`` wrong MACs
    on a connection its next MAC waits ``min(max_s, base_s * 2**(n - 1))`` s after the last
    failure, and for a budget of ``rate`` checks per second (``burst`` at once) that wrong
    MACs of all connections draw on. Failures of one peer (an address) less than
    ``quiet_s`` apart are one burst, whose first logs one WARNING. ``clock``: monotonic s.
    """

    def __init__(self, clock: Callable[[], float], base_s: float = 0.1, max_s: float = 5.0,
                 rate: float = 2.0, burst: float = 10.0, quiet_s: float = 60.0) -> None:
        self.clock, self.base_s, self.max_s = clock, base_s, max_s
        self.rate, self.burst, self.quiet_s = rate, burst, quiet_s
        self._debt, self._at = 0.0, clock()  # wrong MACs not yet paid back, as of _at
        self._peers: dict[str, float] = {}  # peer -> its last failure (for the log)

    def _owed(self, now: float) -> float:
        return max(0.0, self._debt - (now - self._at) * self.rate)

    def wait_s(self, failures: int, last: float) -> float:
        """Seconds a connection with ``failures`` wrong MACs, the last at ``last`` (clock
        s), must still wait before its next MAC is checked (0: check it now)."""
        if not failures:
            return 0.0
        now = self.clock()
        own = last + min(self.max_s, self.base_s * 2 ** (failures - 1)) - now
        return max(0.0, own, (self._owed(now) - self.burst) / self.rate)

    def failed(self, peer: str, what: str) -> None:
        """One wrong MAC (or forged frame) from ``peer``; ``what`` names it for the log."""
        now = self.clock()
        self._debt, self._at = self._owed(now) + 1.0, now
        last = self._peers.pop(peer, None)
        if last is None or now - last >= self.quiet_s:
            log.warning("%s from %s: further failures are delayed (up to %g s apart per "
                        "connection, %g checked per second in all) and not logged until it "
                        "is quiet for %g s", what, peer, self.max_s, self.rate, self.quiet_s)
            while len(self._peers) >= 4096:  # bounded whatever the number of peers
                self._peers.pop(next(iter(self._peers)))
        self._peers[peer] = now
