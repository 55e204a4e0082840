"""Frame layer: header, CRC-32 and COBS with 0x00 delimiters; a stream decoder that never raises.

One frame on the wire (docs/protocol.md section 2: COBS, the header :data:`HEADER_FIELDS`,
frozen in every version, the CRC and the acceptance rules)::

    00 | COBS( header(12) | payload(payload_len) | [signature(24)] | crc32(4) ) | 00

crc32 is CRC-32/ISO-HDLC (``zlib.crc32``), little-endian, over header, payload and the
signature (:mod:`cdma_lidar.protocol.auth`) when INCOMPAT_SIGNED is set. A FEC session codes
the body around COBS (:mod:`cdma_lidar.protocol.fec`). :class:`FrameDecoder` turns any byte
stream into :class:`Frame` objects and counts what it rejects in :class:`DecoderStats`.
"""

from __future__ import annotations

import struct
import zlib
from dataclasses import dataclass
from typing import NamedTuple, Protocol

from cobs import cobs as _cobs

from cdma_lidar.checks import check_int
from cdma_lidar.errors import FieldError, FrameError, out_of_range
from cdma_lidar.protocol import fec
from cdma_lidar.protocol.fec import coded_len
from cdma_lidar.protocol.schema import Layout, u

__all__ = ["COMPAT_RETRANSMIT", "CRC_SIZE", "DELIMITER", "FRAME_LIMIT", "HEADER", "HEADER_FIELDS",
           "HEADER_SIZE", "INCOMPAT_KNOWN", "INCOMPAT_SIGNED", "MIN_MAX_FRAME", "OVERHEAD",
           "PROTOCOL_VERSION", "SIGNATURE_SIZE", "DecoderStats", "Frame", "FrameDecoder", "Signer",
           "cobs_decode", "cobs_encode", "cobs_max_len", "crc32", "decode_frame", "encode_frame",
           "frame_size", "rejects"]

#: Version 4: v3 (sessions per HELLO, signed frames, FRAGMENTs, Reed-Solomon FEC negotiated
#: in HELLO) with the code around COBS instead of inside it, and requests in FRAGMENTs too
#: (docs/protocol.md).
PROTOCOL_VERSION = 4
DELIMITER = b"\x00"
#: Header fields in wire order. Frozen in every version.
HEADER_FIELDS = Layout(
    u("version", 8, "protocol version; this document: 4"),
    u("incompat_flags", 8, "bit 0: signed (24-byte signature before the CRC); a receiver "
      "drops (device: NAKs) a frame with an unknown bit set"),
    u("compat_flags", 8, "bit 0: retransmitted (a resent column); unknown bits are ignored"),
    u("msg_type", 8, "message type (table below)"),
    u("seq", 16, "request: host counter; reply: the request's seq; stream: device counter"),
    u("payload_len", 16, "payload bytes that follow the header"),
    u("session_id", 32, "session, random per HELLO the device accepts, never 0; host sends 0 "
      "before HELLO"),
)
HEADER = struct.Struct("<" + "".join(f.fmt for f in HEADER_FIELDS.fields))  # the hot path
HEADER_SIZE = HEADER.size  # 12
CRC_SIZE = 4
OVERHEAD = HEADER_SIZE + CRC_SIZE  # 16 bytes around every payload
#: Largest decoded frame (header + payload + CRC, bytes) any device may announce.
FRAME_LIMIT = 65535
#: Smallest max frame size (bytes): every request fits; longer replies and columns are sent
#: as FRAGMENTs.
MIN_MAX_FRAME = 256
#: compat flag bit 0: this frame is a retransmission (a resent column); informational.
COMPAT_RETRANSMIT = 0x01
#: incompat flag bit 0: the frame carries a signature between payload and CRC.
INCOMPAT_SIGNED = 0x01
#: incompat flag bits this implementation understands.
INCOMPAT_KNOWN = INCOMPAT_SIGNED
#: Bytes of a frame signature: u64 counter (little-endian) + 16 bytes of HMAC-SHA256.
SIGNATURE_SIZE = 24

_CRC = struct.Struct("<I")


#: COBS-encode bytes, no delimiters (the ``cobs`` package's C extension; the tests hold it
#: byte for byte to a pure-Python reference, ``tests/protocol/wire_oracle.py``).
cobs_encode = _cobs.encode


def cobs_decode(enc: bytes) -> bytes:
    """COBS-decode ``enc`` (no delimiters); raises FrameError (only) if malformed."""
    if not enc:
        raise FrameError("COBS: empty input")
    try:
        return _cobs.decode(enc)
    except _cobs.DecodeError as exc:
        raise FrameError(f"COBS: {exc}") from None


def cobs_max_len(n: int) -> int:
    """Upper bound (bytes) of the COBS encoding of ``n`` data bytes, delimiters excluded."""
    return n + 1 + n // 254


#: CRC-32/ISO-HDLC of bytes (check value of b"123456789" is 0xCBF43926).
crc32 = zlib.crc32


class Frame(NamedTuple):
    """One frame that passed the CRC and version checks. ``payload`` is still undecoded."""

    msg_type: int
    seq: int
    session: int
    payload: bytes
    compat: int = 0
    incompat: int = 0
    version: int = PROTOCOL_VERSION
    #: signature (counter + MAC, SIGNATURE_SIZE bytes) of a signed frame, else b"".
    sig: bytes = b""
    #: it came Reed-Solomon coded (cdma_lidar.protocol.fec).
    fec: bool = False
    #: put together from FRAGMENTs, each of them checked (session, signature) on arrival.
    joined: bool = False

    def signed_bytes(self) -> bytes:
        """What a signature covers: the header as sent and the payload."""
        return HEADER.pack(self.version, self.incompat, self.compat, self.msg_type, self.seq,
                           len(self.payload), self.session) + self.payload


class Signer(Protocol):
    """Signs outgoing frames: ``sign(header + payload)`` returns SIGNATURE_SIZE bytes."""

    def sign(self, data: bytes) -> bytes: ...


def frame_size(payload_len: int, signed: bool = False) -> int:
    """Decoded bytes of a frame with ``payload_len`` payload bytes (header, CRC, signature)."""
    return OVERHEAD + payload_len + (SIGNATURE_SIZE if signed else 0)


def encode_frame(msg_type: int, payload: bytes, seq: int, session: int, *,
                 compat: int = 0, incompat: int = 0, version: int = PROTOCOL_VERSION,
                 max_frame: int = FRAME_LIMIT, signer: Signer | None = None,
                 coded: bool = False) -> bytes:
    """Build the wire bytes of one frame, both 0x00 delimiters included.

    With a ``signer`` the frame is signed (incompat bit INCOMPAT_SIGNED, signature
    between payload and CRC). ``coded``: Reed-Solomon parity around the COBS bytes
    (:mod:`cdma_lidar.protocol.fec`; ``max_frame`` bounds the frame before coding).
    Raises FieldError naming the header field that cannot hold its value, or ``payload``
    when the frame would exceed ``max_frame`` bytes (decoded size).
    """
    if signer is not None:
        incompat |= INCOMPAT_SIGNED
    size = frame_size(len(payload), signer is not None)
    if size > max_frame:
        raise out_of_range("payload", f"at most {max_frame - size + len(payload)} bytes (max "
                           f"frame {max_frame})", f"{len(payload)} bytes", FieldError)
    try:
        body = Frame(msg_type, seq, session, payload, compat, incompat, version).signed_bytes()
    except struct.error:  # checked only on failure: every column frame is packed here
        for name, value, hi in (("msg_type", msg_type, 0xFF), ("seq", seq, 0xFFFF),
                                ("session", session, 0xFFFFFFFF), ("compat", compat, 0xFF),
                                ("incompat", incompat, 0xFF), ("version", version, 0xFF)):
            check_int(f"frame.{name}", value, 0, hi, cls=FieldError)
        raise
    if signer is not None:
        body += signer.sign(body)
    body += _CRC.pack(zlib.crc32(body))
    if coded:  # a second delimiter after it: one damaged on the line still ends the frame
        return b"".join((DELIMITER, fec.encode(cobs_encode(fec.whiten(body))), DELIMITER * 2))
    return b"".join((DELIMITER, cobs_encode(body), DELIMITER))


def decode_frame(body: bytes, max_frame: int = FRAME_LIMIT) -> Frame:
    """Check and split one COBS-decoded frame of at most ``max_frame`` bytes; raises
    FrameError (only) if invalid, the reason the first word of the message: ``short``,
    ``oversize``, ``crc`` or ``length``. A frame of another version or with unknown
    incompat flags is returned (see :func:`rejects`)."""
    n = len(body)
    if n < OVERHEAD:
        raise FrameError(f"short: {n} bytes, a frame has at least {OVERHEAD}")
    if n > max_frame:
        raise FrameError(f"oversize: {n} bytes, at most {max_frame}")
    (crc,) = _CRC.unpack_from(body, n - CRC_SIZE)
    if zlib.crc32(memoryview(body)[: n - CRC_SIZE]) != crc:
        raise FrameError("crc: CRC-32 mismatch")
    version, incompat, compat, msg_type, seq, plen, session = HEADER.unpack_from(body)
    sig_len = SIGNATURE_SIZE if incompat & INCOMPAT_SIGNED else 0
    if plen != n - OVERHEAD - sig_len:
        raise FrameError(f"length: header says {plen} payload bytes, frame has "
                         f"{n - OVERHEAD - sig_len}")
    end = HEADER_SIZE + plen
    return Frame(msg_type, seq, session, body[HEADER_SIZE:end], compat, incompat, version,
                 body[end:end + sig_len])


def rejects(frame: Frame) -> str:
    """Why this version must not act on a frame that passed the CRC: ``version``,
    ``incompat`` (unknown incompat flags), or "" when it may."""
    return "version" if frame.version != PROTOCOL_VERSION else \
        "incompat" if frame.incompat & ~INCOMPAT_KNOWN else ""


@dataclass
class DecoderStats:
    """Counts of what a :class:`FrameDecoder` saw: ``bytes`` fed, ``frames`` accepted; every
    other field counts a rejected chunk between delimiters."""

    bytes: int = 0
    frames: int = 0
    cobs: int = 0
    short: int = 0
    crc: int = 0
    length: int = 0
    oversize: int = 0
    version: int = 0
    incompat: int = 0
    corrected: int = 0  #: frames whose Reed-Solomon parity repaired damage
    rejoined: int = 0  #: frames put together from chunks split by bytes damaged to 0x00

    @property
    def damaged(self) -> int:
        """Chunks rejected as damaged on the line (COBS, CRC, length, short)."""
        return self.crc + self.cobs + self.length + self.short

    @property
    def errors(self) -> int:
        """All rejected chunks."""
        return self.damaged + self.oversize + self.version + self.incompat


class FrameDecoder:
    """Stream decoder: feed it any slices of the byte stream (partial reads are fine), get
    whole frames back. A chunk longer than a coded ``max_frame`` after COBS is dropped up
    to the next delimiter (counted ``oversize``, never buffered). ``rejected`` lists
    frames that passed the CRC but had another version or unknown incompat flags (the
    device NAKs them); the caller drains it.

    ``fec``: a chunk that is not a valid plain frame is read as a Reed-Solomon coded one
    (such a frame has ``fec`` set), then as one whose delimiters the line moved
    (docs/protocol.md section 2.5). Off by default: correcting costs about 3 ms per kB of
    damaged chunk.
    """

    def __init__(self, max_frame: int = FRAME_LIMIT, fec: bool = False) -> None:
        self.stats = DecoderStats()
        self.fec = fec
        self.rejected: list[Frame] = []
        #: None inside an oversize chunk: dropped up to the next delimiter.
        self._buf: bytearray | None = bytearray()
        self._split: list[bytes] = []  # the damaged chunks right before this one
        self.copied = 0  # bytes moved into the receive buffer (linear-time check)
        #: Largest decoded frame accepted (bytes, header and CRC included).
        self.max_frame = check_int("max_frame", max_frame, MIN_MAX_FRAME, FRAME_LIMIT)
        self._max_chunk = coded_len(cobs_max_len(max_frame)) + 1  # coded or not

    @property
    def buffered(self) -> int:
        """Bytes held back waiting for a delimiter."""
        return len(self._buf or b"")

    def feed(self, data: bytes) -> list[Frame]:
        """Add received bytes; return the frames they complete, in order. Never raises.
        Linear in the bytes fed whatever the read sizes (section 2.1; ``copied``)."""
        st = self.stats
        st.bytes += len(data)
        data = bytes(data)
        out: list[Frame] = []
        start = 0
        while (end := data.find(DELIMITER, start)) >= 0:
            if self._buf is None:  # the delimiter ends an oversize chunk
                self._buf = bytearray()
            elif self._buf or end > start:
                chunk = bytes(self._buf) + data[start:end]
                self._buf.clear()
                self._chunk(chunk, out)
            else:
                self._split = []  # "00 00": a frame boundary, not a damaged byte
            start = end + 1
        if self._buf is None or start >= len(data):
            return out  # inside an oversize chunk (dropped), or nothing left over
        if len(self._buf) + len(data) - start > self._max_chunk:
            st.oversize += 1
            self._buf = None
        else:
            self._buf += data[start:]
            self.copied += len(data) - start
        return out

    def _chunk(self, chunk: bytes, out: list[Frame]) -> None:
        """Decode and count one chunk; with ``fec``, a damaged chunk is tried again
        (:meth:`_retry`); that second reading counts only if it gives a frame."""
        st = self.stats
        got = self._read(chunk)
        if isinstance(got, str):
            setattr(st, got, getattr(st, got) + 1)
            if not self.fec or got == "oversize":
                return
            got = self._retry(chunk)
            if got is None:
                return
        self._split = []
        frame, corrected = got
        st.frames += 1
        st.corrected += corrected
        out.append(frame)

    def _retry(self, chunk: bytes) -> tuple[Frame, bool] | None:
        """A damaged chunk read again as a coded frame whose delimiters the line moved
        (section 2.5): joined to the last 1 to 8 damaged chunks since the last boundary,
        each join also without its first or its last byte."""
        self._split = [*self._split[-7:], chunk]
        while sum(map(len, self._split)) > self._max_chunk:
            self._split.pop(0)
        for k in range(1, len(self._split) + 1):
            whole = b"\x01".join(self._split[-k:])
            for candidate in (whole, whole[1:], whole[:-1])[k == 1:]:
                if (got := self._coded(candidate)) and not rejects(got[0]):
                    self.stats.rejoined += 1
                    return got
        return None

    def _read(self, chunk: bytes) -> tuple[Frame, bool] | str:
        """(frame, corrected by FEC), or the name of the counter its rejection goes to:
        read plain, then (with ``fec``) coded; the plain reading's reason counts."""
        if len(chunk) > self._max_chunk:
            return "oversize"
        try:
            got = decode_frame(cobs_decode(chunk), self.max_frame), False
        except FrameError as exc:
            got = self._coded(chunk) if self.fec else None
            if got is None:
                return str(exc).split(":", 1)[0].lower()
        if not (why := rejects(got[0])):
            return got
        if len(self.rejected) < 64:
            self.rejected.append(got[0])
        return why

    def _coded(self, chunk: bytes) -> tuple[Frame, bool] | None:
        """Read ``chunk`` as a coded frame, its data bytes first, corrected only if they
        fail: (frame, corrected), or None if it is not one."""
        if fec.plausible(chunk):
            for corrected, data in ((False, fec.strip), (True, fec.decode)):
                try:
                    body = fec.whiten(cobs_decode(data(chunk)))
                    return decode_frame(body, self.max_frame)._replace(fec=True), corrected
                except FrameError:
                    pass
        return None
