"""Message catalogue: every payload declared once, with units and ranges.

From the :mod:`~cdma_lidar.protocol.schema` fields come the checked encoder (FieldError
naming the field), the strict decoder (FrameError only), the spec's tables and
:data:`SCHEMA_CRC`. The type byte says who sends it: request 0x01..0x7F, reply
0x80..0xBF, stream 0xC0..0xFF.
"""

from __future__ import annotations

import enum
import zlib
from dataclasses import dataclass, field
from typing import Any

from cdma_lidar.errors import DeviceError, FieldError, FrameError, out_of_range
from cdma_lidar.protocol.columns import (
    COLUMN_HEADER,
    ColumnResult,
    decode_column,
    encode_column,
    record_dtype,
)
from cdma_lidar.protocol.config_keys import CONFIG_KEYS
from cdma_lidar.protocol.framing import Frame
from cdma_lidar.protocol.schema import Field, Layout, array, nbytes, text, u, wire_fields
from cdma_lidar.protocol.views import Info, Status

__all__ = ["FRAGMENT_HEADER", "MAX_PIECES", "MESSAGES", "REPLY_TO",
           "SCHEMA_CRC", "Auth", "CaptureKind", "ErrorCode", "HelloFlags", "MessageSpec",
           "MsgKind", "MsgType", "Pieces", "ScanEndReason", "SessionLostReason", "decode_payload",
           "encode_payload", "head_size", "kind_of", "split_message", "type_name"]


class MsgKind(enum.Enum):
    """Who sends a message type and how it is matched."""
    REQUEST = "request"
    REPLY = "reply"
    STREAM = "stream"


def type_name(msg_type: int) -> str:
    """The name of a message type, or its hex value when unknown."""
    try:
        return MsgType(msg_type).name
    except ValueError:
        return f"0x{msg_type:02x}"


def kind_of(msg_type: int) -> MsgKind:
    """Kind of a message type from its range (works for unknown types too)."""
    return MsgKind.STREAM if msg_type >= 0xC0 else MsgKind.REPLY if msg_type >= 0x80 \
        else MsgKind.REQUEST


class MsgType(enum.IntEnum):
    """Message type byte (header offset 3)."""
    HELLO = 0x01
    CONFIG_GET = 0x02
    CONFIG_SET = 0x03
    POWER_SET = 0x04
    SCAN_START = 0x05
    SCAN_ABORT = 0x06
    RESEND = 0x07
    CALIBRATE = 0x08
    CAPTURE = 0x09
    STATUS_GET = 0x0A
    POWER_GET = 0x0B
    SESSION_END = 0x0C
    ACK = 0x80
    NAK = 0x81
    INFO = 0x82
    CONFIG = 0x83
    STATUS = 0x84
    CAPTURE_DATA = 0x85
    CHALLENGE = 0x86
    POWER = 0x87
    COLUMN_RESULT = 0xC0
    HEARTBEAT = 0xC1
    SCAN_END = 0xC2
    SESSION_LOST = 0xC3
    FRAGMENT = 0xC4
    LINE_ERROR = 0xC5


class ErrorCode(enum.IntEnum):
    """NAK error codes (u16); ``doc``: what each means (the spec's error table)."""
    doc: str

    def __new__(cls, value: int, doc: str) -> ErrorCode:
        code = int.__new__(cls, value)
        code._value_, code.doc = value, doc
        return code

    MALFORMED = 1, "payload does not parse, or a field is outside its wire range"
    UNKNOWN_TYPE = 2, "request type not implemented by this device"
    UNKNOWN_KEY = 3, "CONFIG key unknown and not flagged optional (field: `key N`)"
    OUT_OF_RANGE = 4, "value outside what this device supports (field names it)"
    READ_ONLY = 5, "CONFIG_SET of a read-only key"
    BUSY = 6, ("not allowed while a scan or calibration runs: abort it first; for HELLO "
               "(field `session`): another host owns a live session, the detail gives its age "
               "and idle time (seconds)")
    NOT_AVAILABLE = 7, "RESEND of a column no longer kept, or capture not available"
    TOO_LARGE = 8, "the result would exceed the max frame size"
    VERSION = 9, ("protocol version not supported; sent plain in the request's version "
                  "(section 9), field `version`, detail `device speaks protocol version N`")
    UNSUPPORTED_FLAGS = 10, "an incompat flag bit this device does not know"
    WRONG_SESSION = 11, "request carries another session id: send HELLO again"
    INTERNAL = 12, "the device failed while acting on the request"
    AUTH_REQUIRED = 13, "the device requires signed frames: HELLO with its key first"
    AUTH_FAILED = 14, "HELLO's MAC is wrong (the host's key differs from the device's)"


class ScanEndReason(enum.IntEnum):
    """Why a scan or calibration stream ended (SCAN_END.reason)."""
    COMPLETE = 0
    ABORTED = 1
    ERROR = 2


class HelloFlags(enum.IntFlag):
    """HELLO.flags bits."""
    TAKE_OVER = 0x01  #: end another host's live session and take the device
    KEEP_CONFIG = 0x02  #: keep configuration and power of the previous session
    FEC = 0x04  #: Reed-Solomon coded frames both ways in this session (a device that
    #: cannot code answers plain and the session stays plain)


class SessionLostReason(enum.IntEnum):
    """SESSION_LOST.reason."""
    TAKEN_OVER = 1  #: another host said HELLO with TAKE_OVER
    EXPIRED = 2  #: the session was idle longer than INFO.session_idle_ms


class Auth(enum.IntEnum):
    """INFO.auth: how the session is protected."""
    NONE = 0  #: no key (serial port, pty, loopback with --insecure)
    HMAC_SHA256 = 1  #: challenge-response HELLO, every frame signed


class CaptureKind(enum.IntEnum):
    """What a CAPTURE reads."""
    RAW = 0  #: raw ADC samples of one column (all periods and averages, i16)
    CORR = 1  #: correlation trace ``out`` of one channel over the gate lags


@dataclass(frozen=True)
class MessageSpec:
    """One message type: its payload declaration, a request's reply type, and ``rules``:
    field -> (what a device checks beyond the field's wire range, NAK code a violation
    gets); outside the wire range is always MALFORMED (the spec's "Wire ranges" table)."""

    type: MsgType
    struct: Layout  # the payload's fields in wire order, and their codec
    doc: str
    reply: MsgType | None = None
    rules: dict[str, tuple[str, ErrorCode]] = field(default_factory=dict)

    @property
    def kind(self) -> MsgKind:
        return kind_of(self.type)

    @property
    def fields(self) -> tuple[Field, ...]:
        """Declared fields in wire order."""
        return self.struct.fields


def _msg(t: MsgType, doc: str, *fields_: Field, reply: MsgType | None = None,
         rules: dict[str, str | tuple[str, ErrorCode]] | None = None) -> MessageSpec:
    """A message; a rule given as text alone gets OUT_OF_RANGE."""
    return MessageSpec(t, Layout(*fields_), doc, reply, {
        k: (r, ErrorCode.OUT_OF_RANGE) if isinstance(r, str) else r
        for k, r in (rules or {}).items()})


#: The power-matrix rectangle of POWER_SET, POWER_GET and POWER, and its values.
_RECT = (u("channel_start", 16, "first channel of the rectangle"),
         u("column_start", 16, "first column of the rectangle"),
         u("channels", 16, "rows in the rectangle", lo=1, hi=65535),
         u("columns", 16, "columns in the rectangle", lo=1, hi=65535))
_POWER = Field("power", "u16 x channels*columns", "per-pixel laser power", "1/65535 of max",
               allowed="0..65535", kind="array", fmt="H", count="channels*columns")

_MESSAGE_LIST = [
    _msg(MsgType.HELLO, "Open a session: a fresh session id; the device answers INFO (or "
         "CHALLENGE when it holds a key, or NAK BUSY when another host owns a live session).",
         u("host_max_frame", 16, "largest frame the device may send in this session; longer "
           "messages come as FRAGMENTs", "bytes", 64, 65535),
         u("flags", 8, "bit 0: take over another host's session; bit 1: keep the previous "
           "session's configuration and power; bit 2: Reed-Solomon coded frames (FEC) both "
           "ways, if the device can", lo=0, hi=7),
         nbytes("host_nonce", 16, "random per host link: tells a new host from a "
                "retransmission or the owner's own new HELLO; the host's challenge"),
         nbytes("device_nonce", 16, "the nonce of the device's last CHALLENGE; zeros if none"),
         nbytes("mac", 32, "HMAC-SHA256 proof of the key (see Access control); zeros if none"),
         reply=MsgType.INFO,
         rules={"flags": ("another host owns a live session and bit 0 (take over) is clear",
                          ErrorCode.BUSY),
                "mac": ("with a key: not HMAC(key, ...) of this HELLO and the last "
                        "CHALLENGE's nonce (a wrong nonce gets a new CHALLENGE)",
                        ErrorCode.AUTH_FAILED)}),
    _msg(MsgType.CONFIG_GET, "Read configuration keys (empty list: all keys).",
         Field("keys", "u8 x n (rest)", "key ids to read", kind="array", fmt="B"),
         reply=MsgType.CONFIG,
         rules={"keys": ("a key id this device does not know", ErrorCode.UNKNOWN_KEY)}),
    _msg(MsgType.CONFIG_SET, "Write configuration keys; all items are applied or none.",
         Field("items", "KLV items (rest)", "key u8, length u16, value (see CONFIG keys)",
               kind="klv"),
         reply=MsgType.ACK,
         rules={"items": "a key unknown and not optional: UNKNOWN_KEY; read-only: READ_ONLY; "
                "a key twice or a value outside the key's wire range: MALFORMED; outside the "
                "key's device range (CONFIG keys table, range column): OUT_OF_RANGE; while a "
                "scan runs: BUSY"}),
    _msg(MsgType.POWER_SET, "Set laser power for a rectangle of the K x C power matrix "
         "(row-major, channel by channel); large matrices are sent in several requests.",
         *_RECT, _POWER,
         reply=MsgType.ACK,
         rules={"channel_start": "channel_start + channels > K",
                "column_start": "column_start + columns > INFO.column_count",
                "power": "the sum over a column's channels above the cap "
                "(INFO.column_power_cap_uw; field `power`)"}),
    _msg(MsgType.SCAN_START, "Start a scan; columns then stream as COLUMN_RESULT in column "
         "order, then SCAN_END. A retransmitted SCAN_START is answered, not restarted.",
         u("frame", 32, "frame id chosen by the host, echoed in every column"),
         u("first_column", 16, "first column index"),
         u("columns", 16, "number of columns", lo=1, hi=65535),
         reply=MsgType.ACK,
         rules={"first_column": "first_column >= INFO.column_count",
                "columns": "first_column + columns > INFO.column_count, or columns > "
                "INFO.max_columns; while a scan runs: BUSY"}),
    _msg(MsgType.SCAN_ABORT, "Stop a running scan or calibration (ACK even when idle).",
         reply=MsgType.ACK),
    _msg(MsgType.RESEND, "Send listed columns (all their fragments) and listed fragments of "
         "a frame again from the ring buffer. ACK when each is resent or still to come; NAK "
         "NOT_AVAILABLE names the first lost one.",
         u("frame", 32, "frame id"),
         array("columns", 8, "u", 16, "whole columns to send again", lo=0, hi=65535,
               max_items=255, allowed="0..255 items"),
         Field("fragments", "u8 n + n x (u16 column, u8 index)",
               "single fragments to send again", allowed="0..255 items; columns + fragments "
               ">= 1", kind="array", fmt="HB", count="B", names=("column", "index"), max_items=255),
         reply=MsgType.ACK,
         rules={"columns": ("neither kept in the ring nor still to come in the running scan "
                            "(field `columns[i]` / `fragments[i]`); both lists empty: "
                            "MALFORMED", ErrorCode.NOT_AVAILABLE)}),
    _msg(MsgType.CALIBRATE, "Zeroth-order calibration: stream `shots` COLUMN_RESULTs with "
         "the calibration flag (column = shot index), then SCAN_END.",
         u("frame", 32, "frame id chosen by the host"),
         u("shots", 16, "number of shots", lo=1, hi=65535),
         reply=MsgType.ACK,
         rules={"shots": ("while a scan runs: BUSY", ErrorCode.BUSY)}),
    _msg(MsgType.CAPTURE, "Read debug data of one column in chunks; offset 0 takes a fresh "
         "capture, later offsets read the same capture.",
         u("kind", 8, "0 raw ADC samples, 1 correlation trace", lo=0, hi=1),
         u("column", 16, "column index"),
         u("channel", 16, "channel (kind 1 only; 0 for kind 0)"),
         u("offset", 32, "first element to read", "elements"),
         u("max_count", 16, "largest number of elements wanted", "elements", 1, 65535),
         reply=MsgType.CAPTURE_DATA,
         rules={"column": "column >= INFO.column_count",
                "channel": "kind 1 and channel >= K",
                "offset": "offset > total: OUT_OF_RANGE; offset > 0 with no capture of this "
                "(kind, column, channel) held: NOT_AVAILABLE"}),
    _msg(MsgType.STATUS_GET, "Read the device status.", reply=MsgType.STATUS),
    _msg(MsgType.POWER_GET, "Read back a rectangle of the K x C power matrix.",
         *_RECT,
         reply=MsgType.POWER,
         rules={"channels": "channel_start + channels > K",
                "columns": "column_start + columns > INFO.column_count"}),
    _msg(MsgType.SESSION_END, "End this session (a host closing its link): any scan stops "
         "without SCAN_END, another host's HELLO then needs no take-over.",
         reply=MsgType.ACK),
    _msg(MsgType.ACK, "Request accepted (header seq = request seq).",
         u("request_type", 8, "type of the request answered")),
    _msg(MsgType.NAK, "Request refused (header seq = request seq).",
         u("request_type", 8, "type of the request answered"),
         u("code", 16, "error code (table below)", lo=1, hi=65535),
         text("field", "offending field or key name, empty if none"),
         text("detail", "human-readable reason (may be empty)")),
    _msg(MsgType.INFO, "Device identity, limits and nominal geometry (reply to HELLO).",
         *wire_fields(Info)),
    _msg(MsgType.CONFIG, "Configuration values (reply to CONFIG_GET).",
         Field("items", "KLV items (rest)", "key u8, length u16, value", kind="klv")),
    _msg(MsgType.STATUS, "Device status (reply to STATUS_GET).", *wire_fields(Status)),
    _msg(MsgType.CAPTURE_DATA, "One chunk of captured debug data (reply to CAPTURE).",
         u("kind", 8, "0 raw ADC samples, 1 correlation trace", lo=0, hi=1),
         u("column", 16, "column index"),
         u("channel", 16, "channel (kind 1)"),
         u("elem_bytes", 8, "bytes per element: 2 (i16), 4 (i32) or 8 (i64)", lo=2, hi=8),
         u("total", 32, "elements in the whole capture", "elements"),
         u("offset", 32, "index of the first element in this chunk", "elements"),
         Field("data", "bytes (rest)", "elements, signed little-endian", kind="bytes")),
    _msg(MsgType.CHALLENGE, "Reply to a HELLO without a valid MAC from a device that holds "
         "a key: say HELLO again with this nonce and the MAC.",
         nbytes("device_nonce", 16, "fresh random nonce; valid for the next HELLO only")),
    _msg(MsgType.POWER, "A rectangle of the power matrix (reply to POWER_GET).",
         *_RECT, _POWER),
    MessageSpec(MsgType.COLUMN_RESULT, COLUMN_HEADER,
                "Receiver outputs of one column, all channels (layout below)."),
    _msg(MsgType.HEARTBEAT, "Status sent every heartbeat_ms while scanning (same fields as "
         "STATUS).", *wire_fields(Status)),
    _msg(MsgType.SCAN_END, "End of a scan or calibration stream.",
         u("frame", 32, "frame id"),
         u("first_column", 16, "first column (or shot) of the scan"),
         u("columns", 16, "columns (or shots) produced"),
         u("calibration", 8, "1 for a calibration stream", lo=0, hi=1),
         u("reason", 8, "0 complete, 1 aborted, 2 device error", lo=0, hi=2)),
    _msg(MsgType.FRAGMENT, "One piece of a message longer than the session's max frame (a "
         "COLUMN_RESULT, a reply such as INFO, or a notice): `count` = ceil(len / L) pieces, "
         "in order, of L = max_frame - 27 bytes (- 24 more when signed) each but the last.",
         u("msg_type", 8, "type of the whole message"),
         u("seq", 16, "reply: the request's seq; COLUMN_RESULT: 0"),
         u("frame", 32, "COLUMN_RESULT: frame id; else 0"),
         u("column", 16, "COLUMN_RESULT: column index; else 0"),
         u("index", 8, "this piece, 0..count-1", lo=0, hi=253),
         u("count", 8, "pieces of the whole message", lo=2, hi=254),
         Field("data", "bytes (rest)", "bytes index*L .. of the whole payload",
               allowed="1..L bytes (L = max_frame-27, -24 when signed)", kind="bytes")),
    _msg(MsgType.LINE_ERROR, "The device rejected a damaged chunk (CRC, COBS, length); "
         "information only (section 6.4): a host words its timeout diagnosis with it.",
         u("rx_errors", 32, "rejected chunks since boot")),
    _msg(MsgType.SESSION_LOST, "The session in the header has ended; the device will "
         "answer its requests NAK WRONG_SESSION.",
         u("reason", 8, "1 another host took over, 2 expired after session_idle_ms", lo=1,
           hi=2),
         text("detail", "human-readable reason")),
]

#: Every message type, by type.
MESSAGES: dict[MsgType, MessageSpec] = {m.type: m for m in _MESSAGE_LIST}


def head_size(msg_type: MsgType) -> int:
    """Payload bytes before the trailing data field (FRAGMENT, CAPTURE_DATA)."""
    return sum(f.size for f in MESSAGES[msg_type].fields[:-1])  # type: ignore[misc]
#: FRAGMENT payload bytes before the data (11).
FRAGMENT_HEADER = head_size(MsgType.FRAGMENT)
#: Most FRAGMENTs one message may take (FRAGMENT.count is 2..254).
MAX_PIECES = 254


@dataclass
class Pieces:
    """FRAGMENTs of one message (a column, a reply, a notice) received so far."""

    count: int
    data: dict[int, bytes] = field(default_factory=dict)
    frames: list[Frame] = field(default_factory=list)  # the pieces as they came

    def add(self, frame: Frame, body: dict[str, Any]) -> bytes | None:
        """Keep one piece (``body``: the decoded FRAGMENT ``frame``); the whole payload
        once every piece is in."""
        if body["index"] not in self.data:
            self.frames.append(frame)
        self.data[body["index"]] = body["data"]
        return None if len(self.data) < self.count else b"".join(
            self.data[i] for i in range(self.count))


def split_message(msg_type: int, payload: bytes, room: int, seq: int = 0,
                  key: tuple[int, int] = (0, 0)) -> list[bytes]:
    """The FRAGMENT payloads of one message, ``room`` data bytes each but the last.
    ``seq``: a request's or reply's seq (a notice's counter, 0 for a COLUMN_RESULT); ``key``:
    a COLUMN_RESULT's (frame, column), else (0, 0). DeviceError TOO_LARGE above MAX_PIECES."""
    count = -(-len(payload) // room)
    if count > MAX_PIECES:
        raise DeviceError(f"{type_name(msg_type)} of {len(payload)} bytes needs {count} "
                          f"fragments of {room} bytes (at most {MAX_PIECES})",
                          code=ErrorCode.TOO_LARGE, field="payload")
    return [encode_payload(MsgType.FRAGMENT, {
        "msg_type": int(msg_type), "seq": seq, "frame": key[0], "column": key[1],
        "index": k, "count": count, "data": payload[k * room:(k + 1) * room]})
        for k in range(count)]


#: Reply type of each request.
REPLY_TO: dict[MsgType, MsgType] = {m.type: m.reply for m in _MESSAGE_LIST if m.reply}


# ---- encode / decode ------------------------------------------------------------------
def encode_payload(msg_type: int, fields_: dict[str, Any] | ColumnResult | None = None) -> bytes:
    """Payload bytes of one message; raises FieldError naming the first bad field."""
    try:
        spec = MESSAGES[MsgType(msg_type)]
    except ValueError:
        raise out_of_range("msg_type", "a known message type", msg_type, FieldError) from None
    if spec.type == MsgType.COLUMN_RESULT:
        if not isinstance(fields_, ColumnResult):
            raise out_of_range("COLUMN_RESULT", "a ColumnResult", type(fields_).__name__,
                               FieldError)
        return encode_column(fields_)
    return spec.struct.encode(dict(fields_ or {}), spec.type.name)


def decode_payload(msg_type: int, payload: bytes) -> dict[str, Any] | ColumnResult:
    """A plain dict (lists for arrays) or, for COLUMN_RESULT, a ColumnResult; FrameError
    (only) naming the field for an unknown type, a short or long payload, a value out of range."""
    if msg_type == MsgType.COLUMN_RESULT:  # the hot path: no enum lookup
        return decode_column(payload)
    try:
        spec = MESSAGES[MsgType(msg_type)]
    except ValueError:
        raise FrameError(f"unknown message type 0x{msg_type:02x}") from None
    out = spec.struct.decode(payload, spec.type.name)
    if spec.type == MsgType.FRAGMENT and not (out["index"] < out["count"] and out["data"]):
        raise FrameError("FRAGMENT: index must be below count, data not empty", field="index")
    return out


# ---- schema hash ------------------------------------------------------------------------------
def _schema_text() -> str:
    """What SCHEMA_CRC covers: each message's fields and wire types (COLUMN_RESULT: its
    header's names and the record's dtype at P = 2), then each CONFIG key."""
    col = f"{[f.name for f in COLUMN_HEADER.fields]} {record_dtype(2).descr}"
    return "\n".join([f"{m.type:#04x} {m.type.name} " + (
        col if m.type == MsgType.COLUMN_RESULT else
        " ".join(f"{f.name}:{f.ctype}" for f in m.fields)) for m in _MESSAGE_LIST] +
        [f"key {k.id} {k.name} {k.ctype} ro={k.read_only}" for k in CONFIG_KEYS])


#: CRC-32 of the declared schema (message layouts and config keys), announced in INFO.
SCHEMA_CRC = zlib.crc32(_schema_text().encode()) & 0xFFFFFFFF
