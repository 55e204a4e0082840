"""Message catalogue: every payload declared once with construct, with units and ranges.

Message types are split by range, so even an unknown type says who sent it::

    0x01..0x7F  request   host -> device; answered by exactly one reply with the same seq
    0x80..0xBF  reply     device -> host; header seq = the request's seq
    0xC0..0xFF  stream    device -> host, unsolicited; header seq = device stream counter

Each field is declared with :func:`u` / :func:`i` / :func:`text` / :func:`array` /
:func:`blob`, which wrap a construct subcon and attach a :class:`FieldMeta` (C type,
unit, allowed range, description). From that one declaration come the encoder's
range checks (:func:`encode_payload` raises FieldError naming the field), the
strict decoder (:func:`decode_payload` raises FrameError only), the spec tables
in ``docs/protocol.md`` (``python -m cdma_lidar.protocol.spec``) and :data:`SCHEMA_CRC`.

CONFIG_SET / CONFIG carry key-length-value items (:data:`CONFIG_KEYS`), so keys can
be added without a new protocol version. Bit 7 of a key id is the *optional* flag:
a device that does not know an optional key ignores it; an unknown key without the
flag is refused with NAK UNKNOWN_KEY naming the key.
"""

from __future__ import annotations

import dataclasses
import enum
import math
import zlib
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

import construct as cs
import numpy as np
from numpy.typing import NDArray

from cdma_lidar.errors import FieldError, FrameError, out_of_range
from cdma_lidar.protocol import columns as _columns
from cdma_lidar.protocol.columns import COLUMN_STRUCT, ColumnResult, decode_column, encode_column
from cdma_lidar.protocol.schema import FieldMeta, array, blob, i, text, u

__all__ = [
    "CONFIG_KEYS",
    "CONFIG_OPTIONAL",
    "ERROR_DOCS",
    "MESSAGES",
    "MODES",
    "REPLY_TO",
    "ROUNDINGS",
    "SCHEMA_CRC",
    "TEMPERATURE_UNKNOWN",
    "TILT_AUTO",
    "CaptureKind",
    "ConfigKey",
    "DecodedConfig",
    "ErrorCode",
    "FieldMeta",
    "Info",
    "MessageSpec",
    "MsgKind",
    "MsgType",
    "ScanEndReason",
    "State",
    "Status",
    "config_key",
    "decode_config",
    "decode_payload",
    "encode_config",
    "encode_payload",
    "kind_of",
    "mask_to_poly",
    "poly_to_mask",
]


class MsgKind(enum.Enum):
    """Who sends a message type and how it is matched."""

    REQUEST = "request"
    REPLY = "reply"
    STREAM = "stream"


def kind_of(msg_type: int) -> MsgKind:
    """Kind of a message type from its range (works for unknown types too)."""
    if msg_type >= 0xC0:
        return MsgKind.STREAM
    if msg_type >= 0x80:
        return MsgKind.REPLY
    return MsgKind.REQUEST


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
    ACK = 0x80
    NAK = 0x81
    INFO = 0x82
    CONFIG = 0x83
    STATUS = 0x84
    CAPTURE_DATA = 0x85
    COLUMN_RESULT = 0xC0
    HEARTBEAT = 0xC1
    SCAN_END = 0xC2


class ErrorCode(enum.IntEnum):
    """NAK error codes (u16)."""

    MALFORMED = 1  #: payload does not parse or a field is outside its wire range
    UNKNOWN_TYPE = 2  #: request type not implemented by this device
    UNKNOWN_KEY = 3  #: CONFIG key not known and not flagged optional
    OUT_OF_RANGE = 4  #: a value is outside what this device supports (field names it)
    READ_ONLY = 5  #: CONFIG_SET of a read-only key
    BUSY = 6  #: not allowed while a scan or calibration runs (abort it first)
    NOT_AVAILABLE = 7  #: RESEND of a column no longer kept, or CAPTURE data not available
    TOO_LARGE = 8  #: the result would not fit in the max frame size
    VERSION = 9  #: protocol version not supported (the NAK carries the device's version)
    UNSUPPORTED_FLAGS = 10  #: an incompat flag bit this device does not know
    WRONG_SESSION = 11  #: request carries another session id: send HELLO again
    INTERNAL = 12  #: the device failed while acting on the request


ERROR_DOCS = {
    ErrorCode.MALFORMED: "payload does not parse, or a field is outside its wire range",
    ErrorCode.UNKNOWN_TYPE: "request type not implemented by this device",
    ErrorCode.UNKNOWN_KEY: "CONFIG key unknown and not flagged optional (field: `key N`)",
    ErrorCode.OUT_OF_RANGE: "value outside what this device supports (field names it)",
    ErrorCode.READ_ONLY: "CONFIG_SET of a read-only key",
    ErrorCode.BUSY: "not allowed while a scan or calibration runs: abort it first",
    ErrorCode.NOT_AVAILABLE: "RESEND of a column no longer kept, or capture not available",
    ErrorCode.TOO_LARGE: "the result would exceed the max frame size",
    ErrorCode.VERSION: "protocol version not supported; header carries the device's version",
    ErrorCode.UNSUPPORTED_FLAGS: "an incompat flag bit this device does not know",
    ErrorCode.WRONG_SESSION: "request carries another session id: send HELLO again",
    ErrorCode.INTERNAL: "the device failed while acting on the request",
}


class State(enum.IntEnum):
    """Device state in STATUS / HEARTBEAT."""

    IDLE = 0
    SCANNING = 1
    CALIBRATING = 2


class ScanEndReason(enum.IntEnum):
    """Why a scan or calibration stream ended (SCAN_END.reason)."""

    COMPLETE = 0
    ABORTED = 1
    ERROR = 2


class CaptureKind(enum.IntEnum):
    """What a CAPTURE reads."""

    RAW = 0  #: raw ADC samples of one column (all periods and averages, i16)
    CORR = 1  #: correlation trace ``out`` of one channel over the gate lags


@dataclass(frozen=True)
class MessageSpec:
    """One message type: its payload declaration and, for requests, the reply type."""

    type: MsgType
    struct: cs.Struct
    doc: str
    reply: MsgType | None = None

    @property
    def kind(self) -> MsgKind:
        return kind_of(self.type)

    @property
    def fields(self) -> list[cs.Renamed]:
        """Declared fields in wire order (the terminator excluded)."""
        return [sc for sc in self.struct.subcons if getattr(sc, "name", None)]


def _msg(t: MsgType, doc: str, *fields_: cs.Renamed, reply: MsgType | None = None) -> MessageSpec:
    return MessageSpec(t, cs.Struct(*fields_, cs.Terminated), doc, reply)


#: Sentinel of Info.tilt_udeg: no nominal tilt, the host derives it (reference wavelength
#: horizontal at zero rotation).
TILT_AUTO = -(2**31)
#: Sentinel of Status.temperature_mc: no sensor.
TEMPERATURE_UNKNOWN = -(2**31)

_STATUS_FIELDS = (
    u("state", 8, "0 idle, 1 scanning, 2 calibrating", lo=0, hi=2),
    u("frame", 32, "frame id of the current or last scan"),
    u("next_column", 16, "next column (or shot) the current or last scan produces"),
    u("last_end", 8, "how the last scan ended: 0 complete, 1 aborted, 2 device error",
      lo=0, hi=2),
    u("columns_sent", 32, "COLUMN_RESULT frames sent since boot (resends included)"),
    u("uptime_ms", 32, "time since boot", "ms"),
    u("rx_frames", 32, "valid frames received since boot"),
    u("rx_errors", 32, "rejected chunks since boot (COBS, CRC, length, size, version)"),
    u("tx_frames", 32, "frames sent since boot"),
    u("replays", 32, "retransmitted requests answered from the replay cache"),
    i("temperature_mc", 32, "board temperature; -2^31 = no sensor", "m°C"),
    u("faults", 32, "device-specific fault bits, 0 = healthy"),
)

_MESSAGE_LIST = [
    _msg(MsgType.HELLO, "Open a session: the device answers INFO, aborts any scan and "
         "clears its replay cache (except this HELLO's own entry).",
         u("host_nonce", 32, "random per host link; tells a new host from a retransmission"),
         u("host_max_frame", 16, "largest frame the host accepts", "bytes", 512, 65535),
         reply=MsgType.INFO),
    _msg(MsgType.CONFIG_GET, "Read configuration keys (empty list: all keys).",
         blob("keys", cs.GreedyRange(cs.Int8ul), "u8 x n (rest)", "key ids to read"),
         reply=MsgType.CONFIG),
    _msg(MsgType.CONFIG_SET, "Write configuration keys; all items are applied or none.",
         blob("items", cs.GreedyRange(cs.Struct("key" / cs.Int8ul,
                                                "value" / cs.Prefixed(cs.Int16ul,
                                                                      cs.GreedyBytes))),
              "KLV items (rest)", "key u8, length u16, value (see CONFIG keys)"),
         reply=MsgType.ACK),
    _msg(MsgType.POWER_SET, "Set laser power for a rectangle of the K x C power matrix "
         "(row-major, channel by channel); large matrices are sent in several requests.",
         u("channel_start", 16, "first channel of the rectangle"),
         u("column_start", 16, "first column of the rectangle"),
         u("channels", 16, "rows in the rectangle", lo=1, hi=65535),
         u("columns", 16, "columns in the rectangle", lo=1, hi=65535),
         blob("power", cs.Array(cs.this.channels * cs.this.columns, cs.Int16ul),
              "u16 x channels*columns", "per-pixel laser power", "1/65535 of max",
              "0..65535"),
         reply=MsgType.ACK),
    _msg(MsgType.SCAN_START, "Start a scan; columns then stream as COLUMN_RESULT in column "
         "order, then SCAN_END. A retransmitted SCAN_START is answered, not restarted.",
         u("frame", 32, "frame id chosen by the host, echoed in every column"),
         u("first_column", 16, "first column index"),
         u("columns", 16, "number of columns", lo=1, hi=65535),
         reply=MsgType.ACK),
    _msg(MsgType.SCAN_ABORT, "Stop a running scan or calibration (ACK even when idle).",
         reply=MsgType.ACK),
    _msg(MsgType.RESEND, "Send listed columns of a frame again from the ring buffer. ACK "
         "when each is resent or still to come; NAK NOT_AVAILABLE names the first lost one.",
         u("frame", 32, "frame id"),
         array("columns", 8, "u", 16, "column indexes", lo=0, hi=65535, max_items=255,
               allowed="1..255 items"),
         reply=MsgType.ACK),
    _msg(MsgType.CALIBRATE, "Zeroth-order calibration: stream `shots` COLUMN_RESULTs with "
         "the calibration flag (column = shot index), then SCAN_END.",
         u("frame", 32, "frame id chosen by the host"),
         u("shots", 16, "number of shots", lo=1, hi=65535),
         reply=MsgType.ACK),
    _msg(MsgType.CAPTURE, "Read debug data of one column in chunks; offset 0 takes a fresh "
         "capture, later offsets read the same capture.",
         u("kind", 8, "0 raw ADC samples, 1 correlation trace", lo=0, hi=1),
         u("column", 16, "column index"),
         u("channel", 16, "channel (kind 1 only; 0 for kind 0)"),
         u("offset", 32, "first element to read", "elements"),
         u("max_count", 16, "largest number of elements wanted", "elements", 1, 65535),
         reply=MsgType.CAPTURE_DATA),
    _msg(MsgType.STATUS_GET, "Read the device status.", reply=MsgType.STATUS),
    _msg(MsgType.ACK, "Request accepted (header seq = request seq).",
         u("request_type", 8, "type of the request answered")),
    _msg(MsgType.NAK, "Request refused (header seq = request seq).",
         u("request_type", 8, "type of the request answered"),
         u("code", 16, "error code (table below)", lo=1, hi=65535),
         text("field", "offending field or key name, empty if none"),
         text("detail", "human-readable reason (may be empty)")),
    _msg(MsgType.INFO, "Device identity, limits and nominal geometry (reply to HELLO).",
         u("protocol_version", 8, "protocol version spoken (1)"),
         u("session_id", 32, "session id chosen at boot, also in every frame header",
           lo=1, hi=2**32 - 1),
         u("schema_crc", 32, "CRC-32 of the message schema (see Versioning)"),
         u("max_frame", 16, "largest frame either side sends in this session "
           "(header + payload + CRC)", "bytes", 512, 65535),
         u("ring_columns", 16, "recent columns kept for RESEND", "columns"),
         u("heartbeat_ms", 16, "HEARTBEAT interval while scanning", "ms", 1, 65535),
         u("max_degree", 8, "largest LFSR degree m of the code family", "", 2, 32),
         u("max_channels", 16, "largest number of channels", "", 1, 65535),
         u("adc_bits", 8, "ADC resolution", "bits", 8, 16),
         u("spc_min", 16, "smallest samples per chip", "samples/chip", 1, 65535),
         u("spc_max", 16, "largest samples per chip", "samples/chip", 1, 65535),
         u("max_averages", 32, "largest number of averaged code frames", "", 1),
         u("max_uid_bits", 8, "largest UID length n", "bits", 1, 8),
         u("max_peaks", 8, "largest peaks per channel P", "", 1, 8),
         u("max_gate_len", 32, "largest lag gate", "samples", 1),
         u("max_columns", 16, "largest columns in one scan", "", 1),
         u("chip_rate_hz", 32, "code chip rate", "Hz", 1),
         u("grooves_per_mm_milli", 32, "grating groove density", "0.001 lines/mm", 1),
         i("incidence_udeg", 32, "incidence angle theta_i on the grating", "µdeg"),
         i("tilt_udeg", 32, "mounting tilt gamma; -2^31 = host derives it", "µdeg"),
         u("reference_wavelength_pm", 32, "wavelength horizontal at zero rotation", "pm"),
         i("column_start_udeg", 32, "rotation angle of column 0", "µdeg"),
         i("column_step_udeg", 32, "rotation step between columns", "µdeg"),
         u("column_count", 16, "columns in a full frame", "", 1),
         text("firmware_version", "firmware version string"),
         text("serial", "device serial number"),
         array("wavelengths_pm", 16, "u", 32, "nominal wavelength of each channel (count K)",
               "pm", 1, max_items=65535, allowed="K = 1..max_channels items"),
         ),
    _msg(MsgType.CONFIG, "Configuration values (reply to CONFIG_GET).",
         blob("items", cs.GreedyRange(cs.Struct("key" / cs.Int8ul,
                                                "value" / cs.Prefixed(cs.Int16ul,
                                                                      cs.GreedyBytes))),
              "KLV items (rest)", "key u8, length u16, value")),
    _msg(MsgType.STATUS, "Device status (reply to STATUS_GET).", *_STATUS_FIELDS),
    _msg(MsgType.CAPTURE_DATA, "One chunk of captured debug data (reply to CAPTURE).",
         u("kind", 8, "0 raw ADC samples, 1 correlation trace", lo=0, hi=1),
         u("column", 16, "column index"),
         u("channel", 16, "channel (kind 1)"),
         u("elem_bytes", 8, "bytes per element: 2 (i16), 4 (i32) or 8 (i64)", lo=2, hi=8),
         u("total", 32, "elements in the whole capture", "elements"),
         u("offset", 32, "index of the first element in this chunk", "elements"),
         blob("data", cs.GreedyBytes, "bytes (rest)", "elements, signed little-endian")),
    MessageSpec(MsgType.COLUMN_RESULT, COLUMN_STRUCT,
                "Receiver outputs of one column, all channels (layout below)."),
    _msg(MsgType.HEARTBEAT, "Status sent every heartbeat_ms while scanning (same fields as "
         "STATUS).", *_STATUS_FIELDS),
    _msg(MsgType.SCAN_END, "End of a scan or calibration stream.",
         u("frame", 32, "frame id"),
         u("first_column", 16, "first column (or shot) of the scan"),
         u("columns", 16, "columns (or shots) produced"),
         u("calibration", 8, "1 for a calibration stream", lo=0, hi=1),
         u("reason", 8, "0 complete, 1 aborted, 2 device error", lo=0, hi=2)),
]

#: Every message type, by type.
MESSAGES: dict[MsgType, MessageSpec] = {m.type: m for m in _MESSAGE_LIST}
#: Reply type of each request.
REPLY_TO: dict[MsgType, MsgType] = {m.type: m.reply for m in _MESSAGE_LIST if m.reply}


# ---- encode / decode ------------------------------------------------------------------
def _check_value(path: str, meta: FieldMeta, value: Any) -> None:
    if meta.kind == "int":
        if isinstance(value, bool) or not isinstance(value, int | np.integer) or \
                not meta.lo <= int(value) <= meta.hi:
            raise out_of_range(path, f"an integer from {meta.lo} to {meta.hi}", value,
                               FieldError)
    elif meta.kind == "text":
        if not isinstance(value, str) or len(value.encode("utf-8")) > 255:
            raise out_of_range(path, "a string of at most 255 UTF-8 bytes", value, FieldError)
    elif meta.kind == "array":
        try:
            items = list(value)
        except TypeError:
            raise out_of_range(path, "a sequence of integers", value, FieldError) from None
        if len(items) > (meta.max_items or 0):
            raise out_of_range(path, f"at most {meta.max_items} items", len(items), FieldError)
        for k, v in enumerate(items):
            if isinstance(v, bool) or not isinstance(v, int | np.integer) or \
                    not meta.lo <= int(v) <= meta.hi:
                raise out_of_range(f"{path}[{k}]", f"an integer from {meta.lo} to {meta.hi}",
                                   v, FieldError)


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
    values = dict(fields_ or {})
    name = spec.type.name
    for sc in spec.fields:
        if sc.name not in values:
            raise FieldError(f"{name}.{sc.name} is required", field=sc.name)
        _check_value(f"{name}.{sc.name}", sc.meta, values[sc.name])
    extra = set(values) - {sc.name for sc in spec.fields}
    if extra:
        raise out_of_range(f"{name}.{sorted(extra)[0]}", "a declared field of " + name,
                           "unknown field", FieldError)
    if spec.type == MsgType.POWER_SET:
        n = values["channels"] * values["columns"]
        power = np.asarray(values["power"]).ravel()
        if power.size != n or power.dtype.kind not in "iu" or \
                (n and (power.min() < 0 or power.max() > 65535)):
            raise out_of_range("POWER_SET.power", f"{n} integers from 0 to 65535",
                               f"{power.size} values of {power.dtype}", FieldError)
        values["power"] = power.tolist()
    try:
        return spec.struct.build(values)
    except cs.ConstructError as exc:
        path = str(exc.path or "").split("->")[-1].strip() if hasattr(exc, "path") else ""
        raise FieldError(f"{name}.{path or '?'} cannot be encoded: {exc}",
                         field=path or None) from None


def decode_payload(msg_type: int, payload: bytes) -> dict[str, Any] | ColumnResult:
    """Decode one payload strictly; raises FrameError (only), whose ``args[0]`` names the field.

    Unknown types, short or long payloads and out-of-range values are all errors.
    Returns a plain dict (lists for arrays) or, for COLUMN_RESULT, a ColumnResult.
    """
    try:
        spec = MESSAGES[MsgType(msg_type)]
    except ValueError:
        raise FrameError(f"unknown message type 0x{msg_type:02x}") from None
    if spec.type == MsgType.COLUMN_RESULT:
        return decode_column(payload)
    try:
        c = spec.struct.parse(payload)
    except (cs.ConstructError, UnicodeDecodeError, ValueError) as exc:
        raise FrameError(f"{spec.type.name}: malformed payload ({type(exc).__name__})") \
            from None
    out: dict[str, Any] = {}
    for sc in spec.fields:
        v = c[sc.name]
        if isinstance(v, list):
            v = [dict((k, x) for k, x in e.items() if not k.startswith("_"))
                 if isinstance(e, dict) else e for e in v]
        try:
            _check_value(sc.name, sc.meta, v)
        except FieldError as exc:
            err = FrameError(f"{spec.type.name}: {exc}")
            err.field = sc.name  # type: ignore[attr-defined]
            raise err from None
        out[sc.name] = v
    return out


# ---- configuration keys (KLV) -----------------------------------------------------------
#: Bit 7 of a key id: a device that does not know this key ignores it.
CONFIG_OPTIONAL = 0x80

ROUNDINGS = ("truncate", "half_up", "convergent")
MODES = ("ranging", "calibration")


def poly_to_mask(poly: Sequence[int] | int) -> int:
    """Exponent tuple ``(11, 2)`` (x^11 + x^2 + 1) to the wire mask (bit e = x^e term)."""
    if isinstance(poly, int | np.integer) and not isinstance(poly, bool):
        mask = int(poly)
    else:
        try:
            exps = [int(e) for e in poly]
        except (TypeError, ValueError):
            raise out_of_range("poly", "a tuple of exponents like (11, 2)", poly,
                               FieldError) from None
        if len(set(exps)) != len(exps) or any(not 1 <= e <= 31 for e in exps):
            raise out_of_range("poly", "distinct exponents from 1 to 31", poly, FieldError)
        mask = sum(1 << e for e in exps)
    if not 0 < mask < 2**32 or mask & 1:
        raise out_of_range("poly", "a mask with bits 1..31 (constant term implied)", mask,
                           FieldError)
    return mask


def mask_to_poly(mask: int) -> tuple[int, ...]:
    """Wire mask to the exponent tuple, highest first (constant term implied)."""
    return tuple(e for e in range(31, 0, -1) if mask >> e & 1)


def _enum(names: tuple[str, ...], key: str) -> tuple[Callable, Callable]:
    def to_wire(v: Any) -> int:
        if isinstance(v, str):
            if v not in names:
                raise out_of_range(key, "one of " + ", ".join(names), v, FieldError)
            return names.index(v)
        return v

    def from_wire(v: int) -> str | int:
        return names[v] if 0 <= v < len(names) else v

    return to_wire, from_wire


def _ident(v: Any) -> Any:
    return v


@dataclass(frozen=True)
class ConfigKey:
    """One key of the CONFIG key-length-value set."""

    id: int
    name: str
    sub: cs.Construct  # value encoding (fills the whole length)
    ctype: str
    unit: str
    allowed: str
    doc: str
    lo: int | None = None
    hi: int | None = None
    read_only: bool = False
    to_wire: Callable[[Any], Any] = _ident
    from_wire: Callable[[Any], Any] = _ident

    def encode(self, value: Any) -> bytes:
        """Value bytes; raises FieldError naming the key."""
        try:
            w = self.to_wire(value)
        except FieldError as exc:
            msg = str(exc) if str(exc).startswith(self.name) else f"{self.name}: {exc}"
            raise FieldError(msg, field=self.name) from None
        if self.lo is not None:
            items = w if isinstance(w, list | tuple | np.ndarray) else [w]
            each = "each " if isinstance(w, list | tuple | np.ndarray) else ""
            for v in items:
                if isinstance(v, bool) or not isinstance(v, int | np.integer) or \
                        not self.lo <= int(v) <= self.hi:
                    raise out_of_range(self.name, f"{self.allowed} ({each}{self.lo}.."
                                       f"{self.hi} on the wire)", value, FieldError)
        try:
            return self.sub.build(w)
        except (cs.ConstructError, TypeError, ValueError) as exc:
            raise out_of_range(self.name, self.allowed, value, FieldError) from exc

    def decode(self, data: bytes) -> Any:
        """Python value of the wire bytes; raises FrameError if malformed or out of range."""
        try:
            w = self.sub.parse(data)
        except cs.ConstructError:
            raise FrameError(f"{self.name}: malformed value ({len(data)} bytes)") from None
        if isinstance(w, list):
            w = [tuple(int(x) for x in (e.start, e.length)) if isinstance(e, dict) else int(e)
                 for e in w]
        if self.lo is not None:
            for v in w if isinstance(w, list) else [w]:
                if not self.lo <= v <= self.hi:
                    raise FrameError(f"{self.name}: {v} not in {self.lo}..{self.hi}")
        return self.from_wire(w)


def _full(sub: cs.Construct) -> cs.Construct:
    return cs.FocusedSeq("v", "v" / sub, cs.Terminated)


_ROUND_TO, _ROUND_FROM = _enum(ROUNDINGS, "rounding")
_MODE_TO, _MODE_FROM = _enum(MODES, "mode")
_WINDOW = cs.Struct("start" / cs.Int32ul, "length" / cs.Int32ul)


def _windows_to_wire(v: Any) -> list[dict[str, int]]:
    try:
        pairs = [(int(s), int(n)) for s, n in v]
    except (TypeError, ValueError):
        raise out_of_range("ghost_windows", "a list of (start, length) pairs", v,
                           FieldError) from None
    if any(not 0 <= s < 2**32 or not 0 <= n < 2**32 for s, n in pairs):
        raise out_of_range("ghost_windows", "u32 starts and lengths (samples)", v, FieldError)
    return [{"start": s, "length": n} for s, n in pairs]


CONFIG_KEYS: tuple[ConfigKey, ...] = (
    ConfigKey(1, "poly_u", _full(cs.Int32ul), "u32", "", "mask, degree 2..max_degree",
              "first Gold polynomial: bit e set = x^e term, x^0 implied (host: exponent "
              "tuple, highest first)", to_wire=poly_to_mask, from_wire=mask_to_poly),
    ConfigKey(2, "poly_v", _full(cs.Int32ul), "u32", "", "mask, same degree as poly_u",
              "second Gold polynomial, same encoding", to_wire=poly_to_mask,
              from_wire=mask_to_poly),
    ConfigKey(3, "code_index", _full(cs.GreedyRange(cs.Int16ul)), "u16 x K", "",
              "0..2^m (N+1), K items", "Gold family member of each channel", 0, 65535,
              to_wire=lambda v: [int(x) for x in v], from_wire=tuple),
    ConfigKey(4, "uid_bits", _full(cs.Int8ul), "u8", "code periods", "1..max_uid_bits",
              "UID length n", 1, 8),
    ConfigKey(5, "uid", _full(cs.Int8ul), "u8", "", "0..2^uid_bits-1",
              "this device's UID (bit p = polarity of period p)", 0, 255),
    ConfigKey(6, "samples_per_chip", _full(cs.Int16ul), "u16", "samples/chip",
              "spc_min..spc_max", "ADC samples per chip S", 1, 65535),
    ConfigKey(7, "averages", _full(cs.Int32ul), "u32", "code frames", "1..max_averages",
              "coherently summed code frames", 1, 2**32 - 1),
    ConfigKey(8, "adc_bits", _full(cs.Int8ul), "u8", "bits", "8..16, read-only",
              "ADC resolution", 8, 16, read_only=True),
    ConfigKey(9, "gate_start", _full(cs.Int32ul), "u32", "samples", "0..N*S-1",
              "first lag of the gate", 0, 2**32 - 1),
    ConfigKey(10, "gate_len", _full(cs.Int32ul), "u32", "samples", "1..min(N*S, max_gate_len)",
              "lags in the gate", 1, 2**32 - 1),
    ConfigKey(11, "peak_exclude", _full(cs.Int32ul), "u32", "samples", "0..N*S",
              "W: peaks at least W+1 lags apart; noise excludes |j - j_peak| <= W",
              0, 2**32 - 1),
    ConfigKey(12, "ghost_windows", _full(cs.GreedyRange(_WINDOW)), "(u32 start, u32 len) x n",
              "samples", "lags mod N*S",
              "absolute lags (start, start+len-1, mod N*S) ignored by peak search and noise floor",
              to_wire=_windows_to_wire, from_wire=tuple),
    ConfigKey(13, "out_shift", _full(cs.Int8ul), "u8", "bits", "0..63",
              "out = round(raw / 2^out_shift)", 0, 63),
    ConfigKey(14, "rounding", _full(cs.Int8ul), "u8", "", "0 truncate, 1 half_up, "
              "2 convergent", "rounding of the output shift", 0, 2,
              to_wire=_ROUND_TO, from_wire=_ROUND_FROM),
    ConfigKey(15, "out_bits", _full(cs.Int8ul), "u8", "bits", "8..32",
              "outputs saturate to signed out_bits", 8, 32),
    ConfigKey(16, "peaks", _full(cs.Int8ul), "u8", "", "1..max_peaks",
              "peaks reported per channel P", 1, 8),
    ConfigKey(17, "columns_per_frame", _full(cs.Int16ul), "u16", "columns",
              "1..max_columns", "columns in a default scan frame", 1, 65535),
    ConfigKey(18, "mode", _full(cs.Int8ul), "u8", "", "0 ranging, 1 calibration",
              "measurement mode (calibration = zeroth-order beam)", 0, 1,
              to_wire=_MODE_TO, from_wire=_MODE_FROM),
)
_KEY_BY_NAME = {k.name: k for k in CONFIG_KEYS}
_KEY_BY_ID = {k.id: k for k in CONFIG_KEYS}


def encode_config(values: dict[str, Any], *, allow_read_only: bool = True) -> list[dict]:
    """KLV items (for CONFIG_SET / CONFIG) of ``{name: python value}``.

    Raises FieldError naming an unknown key, a read-only one (when not allowed) or a
    value its key cannot hold.
    """
    items = []
    for name, value in values.items():
        key = _KEY_BY_NAME.get(name)
        if key is None:
            raise out_of_range(name, "a configuration key (" + ", ".join(_KEY_BY_NAME) + ")",
                               "unknown key", FieldError)
        if key.read_only and not allow_read_only:
            raise FieldError(f"{name} is read-only", field=name)
        data = key.encode(value)
        if len(data) > 65535:
            raise out_of_range(name, "at most 65535 value bytes", len(data), FieldError)
        items.append({"key": key.id, "value": data})
    return items


@dataclass
class DecodedConfig:
    """Result of :func:`decode_config`."""

    values: dict[str, Any] = field(default_factory=dict)
    unknown: list[int] = field(default_factory=list)  # mandatory keys not known
    ignored: list[int] = field(default_factory=list)  # optional keys not known


def decode_config(items: list[dict]) -> DecodedConfig:
    """Python values of KLV items; raises FrameError (naming the key) on a bad value."""
    out = DecodedConfig()
    for it in items:
        kid, data = int(it["key"]), bytes(it["value"])
        key = _KEY_BY_ID.get(kid & ~CONFIG_OPTIONAL)
        if key is None:
            (out.ignored if kid & CONFIG_OPTIONAL else out.unknown).append(kid)
            continue
        try:
            out.values[key.name] = key.decode(data)
        except FrameError as exc:
            err = FrameError(str(exc))
            err.field = key.name  # type: ignore[attr-defined]
            raise err from None
    return out


def config_key(name_or_id: str | int) -> ConfigKey:
    """The :class:`ConfigKey` of a name or id; raises FieldError if unknown."""
    k = _KEY_BY_NAME.get(name_or_id) if isinstance(name_or_id, str) else \
        _KEY_BY_ID.get(int(name_or_id) & ~CONFIG_OPTIONAL)
    if k is None:
        raise out_of_range("key", "a configuration key", name_or_id, FieldError)
    return k


# ---- typed views of INFO and STATUS -------------------------------------------------------
@dataclass(frozen=True)
class Info:
    """INFO payload: identity, limits and nominal geometry (wire units, see the spec).

    The device endpoint fills ``protocol_version``, ``session_id``, ``schema_crc``,
    ``max_frame``, ``ring_columns`` and ``heartbeat_ms``; the device application
    fills the rest (see :meth:`nominal`).
    """

    firmware_version: str
    serial: str
    wavelengths_pm: tuple[int, ...]
    protocol_version: int = 1
    session_id: int = 1
    schema_crc: int = 0
    max_frame: int = 16384
    ring_columns: int = 1024
    heartbeat_ms: int = 200
    max_degree: int = 20
    max_channels: int = 64
    adc_bits: int = 12
    spc_min: int = 1
    spc_max: int = 64
    max_averages: int = 1 << 20
    max_uid_bits: int = 8
    max_peaks: int = 8
    max_gate_len: int = 1 << 20
    max_columns: int = 65535
    chip_rate_hz: int = 1_000_000_000
    grooves_per_mm_milli: int = 600_000
    incidence_udeg: int = 60_000_000
    tilt_udeg: int = TILT_AUTO
    reference_wavelength_pm: int = 1_587_000
    column_start_udeg: int = 0
    column_step_udeg: int = 100_000
    column_count: int = 1

    @classmethod
    def nominal(cls, *, serial: str, firmware_version: str, wavelengths_m: Sequence[float],
                grooves_per_mm: float, incidence_deg: float, tilt_deg: float | None,
                reference_wavelength_m: float, chip_rate_hz: float,
                column_start_deg: float, column_step_deg: float, column_count: int,
                **limits: int) -> Info:
        """Build from SI units and degrees (rounded to the wire's pm / µdeg / 0.001 /mm)."""
        return cls(
            firmware_version=firmware_version, serial=serial,
            wavelengths_pm=tuple(round(w * 1e12) for w in wavelengths_m),
            grooves_per_mm_milli=round(grooves_per_mm * 1e3),
            incidence_udeg=round(incidence_deg * 1e6),
            tilt_udeg=TILT_AUTO if tilt_deg is None else round(tilt_deg * 1e6),
            reference_wavelength_pm=round(reference_wavelength_m * 1e12),
            chip_rate_hz=round(chip_rate_hz), column_start_udeg=round(column_start_deg * 1e6),
            column_step_udeg=round(column_step_deg * 1e6), column_count=column_count,
            **limits)

    @property
    def channels(self) -> int:
        """K, number of channels."""
        return len(self.wavelengths_pm)

    @property
    def wavelengths_m(self) -> NDArray[np.float64]:
        """(K,) nominal channel wavelengths (m)."""
        return np.asarray(self.wavelengths_pm, dtype=np.float64) * 1e-12

    @property
    def column_angles_deg(self) -> NDArray[np.float64]:
        """(C,) nominal grating rotation angle of each column (deg)."""
        return (self.column_start_udeg + self.column_step_udeg *
                np.arange(self.column_count, dtype=np.float64)) * 1e-6

    @property
    def grooves_per_mm(self) -> float:
        """Grating groove density (lines/mm)."""
        return self.grooves_per_mm_milli * 1e-3

    @property
    def incidence_deg(self) -> float:
        """Incidence angle (deg)."""
        return self.incidence_udeg * 1e-6

    @property
    def tilt_deg(self) -> float | None:
        """Mounting tilt (deg), or None when the host should derive it."""
        return None if self.tilt_udeg == TILT_AUTO else self.tilt_udeg * 1e-6

    @property
    def reference_wavelength_m(self) -> float:
        """Wavelength made horizontal by the default tilt (m)."""
        return self.reference_wavelength_pm * 1e-12

    def to_fields(self) -> dict[str, Any]:
        """Field dict for :func:`encode_payload` (MsgType.INFO)."""
        d = dataclasses.asdict(self)
        d["wavelengths_pm"] = list(self.wavelengths_pm)
        return d

    @classmethod
    def from_fields(cls, d: dict[str, Any]) -> Info:
        """From a decoded INFO payload."""
        d = dict(d)
        d["wavelengths_pm"] = tuple(d["wavelengths_pm"])
        return cls(**d)


@dataclass(frozen=True)
class Status:
    """STATUS / HEARTBEAT payload."""

    state: int = 0
    frame: int = 0
    next_column: int = 0
    last_end: int = 0
    columns_sent: int = 0
    uptime_ms: int = 0
    rx_frames: int = 0
    rx_errors: int = 0
    tx_frames: int = 0
    replays: int = 0
    temperature_mc: int = TEMPERATURE_UNKNOWN
    faults: int = 0

    @property
    def state_name(self) -> str:
        """``idle``, ``scanning`` or ``calibrating``."""
        return State(self.state).name.lower() if self.state in iter(State) else str(self.state)

    @property
    def temperature_c(self) -> float:
        """Board temperature (°C), NaN without a sensor."""
        return math.nan if self.temperature_mc == TEMPERATURE_UNKNOWN else \
            self.temperature_mc * 1e-3

    def to_fields(self) -> dict[str, Any]:
        """Field dict for :func:`encode_payload`."""
        return dataclasses.asdict(self)


# ---- schema hash ------------------------------------------------------------------------------
def _schema_text() -> str:
    lines = []
    for m in _MESSAGE_LIST:
        if m.type == MsgType.COLUMN_RESULT:
            names = [sc.name for sc in _columns.COLUMN_HEADER.subcons]
            rec = _columns.record_dtype(2)
            lines.append(f"{m.type:#04x} {m.type.name} {names} {rec.descr}")
            continue
        lines.append(f"{m.type:#04x} {m.type.name} " +
                     " ".join(f"{sc.name}:{sc.meta.ctype}" for sc in m.fields))
    for k in CONFIG_KEYS:
        lines.append(f"key {k.id} {k.name} {k.ctype} ro={k.read_only}")
    return "\n".join(lines)


#: CRC-32 of the declared schema (message layouts and config keys), announced in INFO.
SCHEMA_CRC = zlib.crc32(_schema_text().encode()) & 0xFFFFFFFF
