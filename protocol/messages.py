"""Message catalogue: every payload declared once, with units and ranges.

Its :mod:`~cdma_lidar.protocol.schema` fields give the codec, the spec's tables and
:data:`SCHEMA_CRC`. :class:`Info` (reply to HELLO) and :class:`Status` (STATUS, HEARTBEAT)
are typed dataclasses whose fields, in wire units (pm, µdeg, m°C, ms, 0.001 lines/mm) and
wire order, carry their payload declaration (:func:`~.schema.wire`): ``to_fields`` gives
what ``encode_payload`` takes, ``Info.from_fields`` / ``Status(**fields)`` read a payload.
"""

from __future__ import annotations

import dataclasses
import enum
import math
import zlib
from collections.abc import Sequence
from dataclasses import MISSING, dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from cdma_lidar.errors import DeviceError, FieldError, FrameError, out_of_range
from cdma_lidar.protocol.columns import (
    COLUMN_HEADER,
    ColumnResult,
    decode_column,
    encode_column,
    record_dtype,
    udeg,
)
from cdma_lidar.protocol.config_keys import CONFIG_KEYS
from cdma_lidar.protocol.framing import PROTOCOL_VERSION, frame_size
from cdma_lidar.protocol.schema import Field, Layout, i, nbytes, text, u, wire, wire_fields

__all__ = ["FRAGMENT_HEADER", "MAX_PIECES", "MESSAGES", "REPLY_TO", "SCHEMA_CRC",
           "TEMPERATURE_UNKNOWN", "TILT_AUTO", "Auth", "CaptureKind", "ErrorCode", "HelloFlags",
           "Info", "MessageSpec", "MsgKind", "MsgType", "ScanEndReason",
           "SessionLostReason", "State", "Status", "decode_payload", "encode_payload",
           "head_size", "kind_of", "piece_room", "split_message", "type_name"]


class MsgKind(enum.Enum):
    """Who sends a message type and how it is matched."""
    REQUEST = "request"
    REPLY = "reply"
    STREAM = "stream"


def type_name(msg_type: int) -> str:
    """The name of a message type, or its hex value when unknown."""
    spec = MESSAGES.get(msg_type)  # type: ignore[call-overload]
    return f"0x{msg_type:02x}" if spec is None else spec.type.name


def kind_of(msg_type: int) -> MsgKind:
    """Kind of a message type from its range, unknown types too: request 0x01..0x7F, reply
    0x80..0xBF, stream 0xC0..0xFF."""
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


#: Sentinels of Info.tilt_udeg (no nominal tilt: the host derives it, the reference
#: wavelength horizontal at zero rotation) and Status.temperature_mc (no sensor).
TILT_AUTO = TEMPERATURE_UNKNOWN = -(2**31)


class State(enum.IntEnum):
    """Device state in STATUS / HEARTBEAT."""

    IDLE = 0
    SCANNING = 1
    CALIBRATING = 2


@dataclass(frozen=True, kw_only=True)
class Info:
    """INFO payload: identity, limits and nominal geometry (wire units, see the spec). The
    device endpoint fills ``protocol_version``, ``session_id``, ``schema_crc``, ``max_frame``,
    ``ring_columns``, ``heartbeat_ms``, ``session_idle_ms``, ``auth`` and ``device_mac``;
    the device application the rest (:meth:`nominal`)."""

    protocol_version: int = wire(PROTOCOL_VERSION, u, 8,
                                 f"protocol version spoken ({PROTOCOL_VERSION})")
    session_id: int = wire(1, u, 32, "session id chosen for this HELLO, also in every frame "
                           "header", lo=1, hi=2**32 - 1)
    session_idle_ms: int = wire(10_000, u, 32, "a session idle this long may be taken by "
                                "another host without take-over", "ms", 1)
    auth: int = wire(0, u, 8, "0 no key; 1 HMAC-SHA256 challenge-response, every frame "
                     "signed", lo=0, hi=1)
    device_mac: bytes = wire(bytes(32), nbytes, 32, "HMAC-SHA256 proof that the device "
                             "holds the key; zeros when auth is 0")
    pixel_power_max_uw: int = wire(0, u, 32, "laser power of one pixel at power 65535; 0: "
                                   "no power control", "µW")
    column_power_cap_uw: int = wire(0, u, 32, "eye-safety cap on the sum over a column's "
                                    "channels; 0: none", "µW")
    schema_crc: int = wire(0, u, 32, "CRC-32 of the message schema (see Versioning)")
    max_frame: int = wire(16384, u, 16, "largest frame the device accepts (header + payload "
                          "+ signature + CRC); the host's requests stay within "
                          "min(max_frame, max(host_max_frame, 256))", "bytes", 256, 65535)
    ring_columns: int = wire(1024, u, 16, "recent columns kept for RESEND", "columns")
    heartbeat_ms: int = wire(200, u, 16, "HEARTBEAT interval while scanning", "ms", 1, 65535)
    max_degree: int = wire(20, u, 8, "largest LFSR degree m of the code family", "", 2, 32)
    max_channels: int = wire(64, u, 16, "largest number of channels", "", 1, 65535)
    adc_bits: int = wire(12, u, 8, "ADC resolution", "bits", 8, 16)
    spc_min: int = wire(1, u, 16, "smallest samples per chip", "samples/chip", 1, 65535)
    spc_max: int = wire(64, u, 16, "largest samples per chip", "samples/chip", 1, 65535)
    max_averages: int = wire(1 << 20, u, 32, "largest number of averaged code repetitions",
                             "", 1)
    max_uid_bits: int = wire(8, u, 8, "largest UID length n", "bits", 1, 8)
    max_peaks: int = wire(8, u, 8, "largest peaks per channel P", "", 1, 8)
    max_gate_len: int = wire(1 << 20, u, 32, "largest lag gate", "samples", 1)
    max_columns: int = wire(65535, u, 16, "largest columns in one scan", "", 1)
    chip_rate_hz: int = wire(1_000_000_000, u, 32, "code chip rate", "Hz", 1)
    grooves_per_mm_milli: int = wire(600_000, u, 32, "grating groove density",
                                     "0.001 lines/mm", 1)
    incidence_udeg: int = wire(60_000_000, i, 32, "incidence angle theta_i on the grating",
                               "µdeg")
    tilt_udeg: int = wire(TILT_AUTO, i, 32, "mounting tilt gamma; -2^31 = host derives it",
                          "µdeg")
    reference_wavelength_pm: int = wire(1_587_000, u, 32, "wavelength horizontal at zero "
                                        "rotation", "pm")
    column_start_udeg: int = wire(0, i, 32, "rotation angle of column 0", "µdeg")
    column_step_udeg: int = wire(100_000, i, 32, "rotation step between columns", "µdeg")
    column_count: int = wire(1, u, 16, "columns in a full frame", "", 1)
    firmware_version: str = wire(MISSING, text, "firmware version string")
    serial: str = wire(MISSING, text, "device serial number")
    wavelengths_pm: tuple[int, ...] = wire(
        MISSING, Field, "u16 n + n x u32", "nominal wavelength of each channel (count K)",
        unit="pm", lo=1, hi=2**32 - 1, allowed="K = 1..max_channels items", kind="array",
        fmt="I", count="H", min_items=1, max_items=65535)

    @classmethod
    def nominal(cls, *, wavelengths_m: Sequence[float], grooves_per_mm: float,
                incidence_deg: float, tilt_deg: float | None, reference_wavelength_m: float,
                chip_rate_hz: float, column_start_deg: float, column_step_deg: float,
                **fields: Any) -> Info:
        """Build from SI units and degrees (rounded to the wire's pm / µdeg / 0.001 /mm);
        ``fields``: the others as on the wire (serial, firmware_version, column_count, limits)."""
        return cls(
            wavelengths_pm=tuple(round(w * 1e12) for w in wavelengths_m),
            grooves_per_mm_milli=round(grooves_per_mm * 1e3), incidence_udeg=udeg(incidence_deg),
            tilt_udeg=TILT_AUTO if tilt_deg is None else udeg(tilt_deg),
            reference_wavelength_pm=round(reference_wavelength_m * 1e12),
            chip_rate_hz=round(chip_rate_hz), column_start_udeg=udeg(column_start_deg),
            column_step_udeg=udeg(column_step_deg), **fields)

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

    #: The field dict encode_payload(MsgType.INFO, ...) takes.
    to_fields = dataclasses.asdict

    @classmethod
    def from_fields(cls, d: dict[str, Any]) -> Info:
        """From a decoded INFO payload."""
        return cls(**{**d, "wavelengths_pm": tuple(d["wavelengths_pm"])})


@dataclass(frozen=True)
class Status:
    """STATUS / HEARTBEAT payload."""

    state: int = wire(0, u, 8, "0 idle, 1 scanning, 2 calibrating", lo=0, hi=2)
    frame: int = wire(0, u, 32, "frame id of the current or last scan")
    next_column: int = wire(0, u, 16, "next column (or shot) the current or last scan "
                            "produces")
    last_end: int = wire(0, u, 8, "how the last scan ended: 0 complete, 1 aborted, 2 device "
                         "error", lo=0, hi=2)
    columns_sent: int = wire(0, u, 32, "COLUMN_RESULT frames sent since boot (resends "
                             "included)")
    uptime_ms: int = wire(0, u, 32, "time since boot", "ms")
    rx_frames: int = wire(0, u, 32, "valid frames received since boot")
    rx_errors: int = wire(0, u, 32, "rejected chunks since boot (COBS, CRC, length, size, "
                          "version)")
    tx_frames: int = wire(0, u, 32, "frames sent since boot")
    replays: int = wire(0, u, 32, "retransmitted requests answered from the replay cache")
    temperature_mc: int = wire(TEMPERATURE_UNKNOWN, i, 32, "board temperature; -2^31 = no "
                               "sensor", "m°C")
    faults: int = wire(0, u, 32, "device-specific fault bits, 0 = healthy")
    column_time_ms: int = wire(0, u, 32, "longest the device may take to deliver its next "
                               "column with the current configuration (a batch of columns "
                               "computed together included); the host's no-progress limit "
                               "follows it; 0: not stated", "ms")

    @property
    def state_name(self) -> str:
        """``idle``, ``scanning`` or ``calibrating``."""
        return State(self.state).name.lower() if self.state in iter(State) else str(self.state)

    @property
    def temperature_c(self) -> float:
        """Board temperature (°C), NaN without a sensor."""
        return math.nan if self.temperature_mc == TEMPERATURE_UNKNOWN else \
            self.temperature_mc * 1e-3

    #: The field dict encode_payload(MsgType.STATUS or HEARTBEAT, ...) takes.
    to_fields = dataclasses.asdict


class MessageSpec(Layout):
    """One message type: its payload's fields in wire order and their codec (a Layout), a
    request's reply type, and ``rules``: field -> (what a device checks beyond the field's wire
    range, NAK code a violation gets; text alone: OUT_OF_RANGE); outside the wire range is
    always MALFORMED (the spec's "Wire ranges" table)."""

    def __init__(self, type_: MsgType, doc: str, *fields: Field, reply: MsgType | None = None,
                 rules: dict[str, str | tuple[str, ErrorCode]] | None = None) -> None:
        super().__init__(*fields)
        self.type, self.doc, self.reply, self.kind = type_, doc, reply, kind_of(type_)
        self.rules = {k: (r, ErrorCode.OUT_OF_RANGE) if isinstance(r, str) else r
                      for k, r in (rules or {}).items()}


#: The power-matrix rectangle of POWER_SET, POWER_GET and POWER, and its values.
_RECT = (u("channel_start", 16, "first channel of the rectangle"),
         u("column_start", 16, "first column of the rectangle"),
         u("channels", 16, "rows in the rectangle", lo=1, hi=65535),
         u("columns", 16, "columns in the rectangle", lo=1, hi=65535))
#: What CAPTURE reads and CAPTURE_DATA carries.
_CAPTURED = (u("kind", 8, "0 raw ADC samples, 1 correlation trace", lo=0, hi=1),
             u("column", 16, "column index"),
             u("channel", 16, "channel (kind 1 only; 0 for kind 0)"))
_POWER = Field("power", "u16 x channels*columns", "per-pixel laser power", "1/65535 of max",
               allowed="0..65535", kind="array", fmt="H", count="channels*columns")

_MESSAGE_LIST = [
    MessageSpec(MsgType.HELLO, "Open a session: a fresh session id; the device answers INFO "
                "(or CHALLENGE when it holds a key, or NAK BUSY when another host owns a live "
                "session).",
                u("host_max_frame", 16, "largest frame the device may send in this session; "
                  "longer messages come as FRAGMENTs", "bytes", 64, 65535),
                u("flags", 8, "bit 0: take over another host's session; bit 1: keep the previous "
                  "session's configuration and power; bit 2: Reed-Solomon coded frames (FEC) both "
                  "ways, if the device can", lo=0, hi=7),
                nbytes("host_nonce", 16, "random per host link: tells a new host from a "
                       "retransmission or the owner's own new HELLO; the host's challenge"),
                nbytes("device_nonce", 16, "the nonce of the device's last CHALLENGE; zeros if "
                       "none"),
                nbytes("mac", 32, "HMAC-SHA256 proof of the key (see Access control); zeros "
                       "if none"),
                reply=MsgType.INFO,
                rules={"flags": ("another host owns a live session and bit 0 (take over) is clear",
                                 ErrorCode.BUSY),
                       "mac": ("with a key: not HMAC(key, ...) of this HELLO and the last "
                               "CHALLENGE's nonce (a wrong nonce gets a new CHALLENGE)",
                               ErrorCode.AUTH_FAILED)}),
    MessageSpec(MsgType.CONFIG_GET, "Read configuration keys (empty list: all keys).",
                Field("keys", "u8 x n (rest)", "key ids to read", kind="array", fmt="B"),
                reply=MsgType.CONFIG,
                rules={"keys": ("a key id this device does not know", ErrorCode.UNKNOWN_KEY)}),
    MessageSpec(MsgType.CONFIG_SET, "Write configuration keys; all items are applied or none.",
                Field("items", "KLV items (rest)", "key u8, length u16, value (see CONFIG keys)",
                      kind="klv"),
                reply=MsgType.ACK,
                rules={"items": "a key unknown and not optional: UNKNOWN_KEY; read-only: "
                       "READ_ONLY; a key twice or a value outside the key's wire range: "
                       "MALFORMED; outside the key's device range (CONFIG keys table, range "
                       "column): OUT_OF_RANGE; while a scan runs: BUSY"}),
    MessageSpec(MsgType.POWER_SET, "Set laser power for a rectangle of the K x C power matrix "
                "(row-major, channel by channel); large matrices are sent in several requests.",
                *_RECT, _POWER,
                reply=MsgType.ACK,
                rules={"channel_start": "channel_start + channels > K",
                       "column_start": "column_start + columns > INFO.column_count",
                       "power": "the sum over a column's channels above the cap "
                       "(INFO.column_power_cap_uw; field `power`)"}),
    MessageSpec(MsgType.SCAN_START, "Start a scan; columns then stream as COLUMN_RESULT in column "
                "order, then SCAN_END. A retransmitted SCAN_START is answered, not restarted.",
                u("frame", 32, "frame id chosen by the host, echoed in every column"),
                u("first_column", 16, "first column index"),
                u("columns", 16, "number of columns", lo=1, hi=65535),
                reply=MsgType.ACK,
                rules={"first_column": "first_column >= INFO.column_count",
                       "columns": "first_column + columns > INFO.column_count, or columns > "
                       "INFO.max_columns; while a scan runs: BUSY"}),
    MessageSpec(MsgType.SCAN_ABORT, "Stop a running scan or calibration (ACK even when idle).",
                reply=MsgType.ACK),
    MessageSpec(MsgType.RESEND, "Send listed columns (all their fragments) and listed fragments of "
                "a frame again from the ring buffer. ACK when each is resent or still to come; NAK "
                "NOT_AVAILABLE names the first lost one.",
                u("frame", 32, "frame id"),
                Field("columns", "u8 n + n x u16", "whole columns to send again",
                      allowed="0..255 items", kind="array", fmt="H", count="B", max_items=255),
                Field("fragments", "u8 n + n x (u16 column, u8 index)",
                      "single fragments to send again", allowed="0..255 items; columns + "
                      "fragments >= 1", kind="array", fmt="HB", count="B",
                      names=("column", "index"), max_items=255),
                reply=MsgType.ACK,
                rules={"columns": ("neither kept in the ring nor still to come in the running scan "
                                   "(field `columns[i]` / `fragments[i]`); both lists empty: "
                                   "MALFORMED", ErrorCode.NOT_AVAILABLE)}),
    MessageSpec(MsgType.CALIBRATE, "Zeroth-order calibration: stream `shots` COLUMN_RESULTs with "
                "the calibration flag (column = shot index), then SCAN_END.",
                u("frame", 32, "frame id chosen by the host"),
                u("shots", 16, "number of shots", lo=1, hi=65535),
                reply=MsgType.ACK,
                rules={"shots": ("while a scan runs: BUSY", ErrorCode.BUSY)}),
    MessageSpec(MsgType.CAPTURE, "Read debug data of one column in chunks; offset 0 takes a fresh "
                "capture, later offsets read the same capture.",
                *_CAPTURED,
                u("offset", 32, "first element to read", "elements"),
                u("max_count", 16, "largest number of elements wanted", "elements", 1, 65535),
                reply=MsgType.CAPTURE_DATA,
                rules={"column": "column >= INFO.column_count",
                       "channel": "kind 1 and channel >= K",
                       "offset": "offset > total: OUT_OF_RANGE; offset > 0 with no capture of this "
                       "(kind, column, channel) held: NOT_AVAILABLE"}),
    MessageSpec(MsgType.STATUS_GET, "Read the device status.", reply=MsgType.STATUS),
    MessageSpec(MsgType.POWER_GET, "Read back a rectangle of the K x C power matrix.",
                *_RECT,
                reply=MsgType.POWER,
                rules={"channels": "channel_start + channels > K",
                       "columns": "column_start + columns > INFO.column_count"}),
    MessageSpec(MsgType.SESSION_END, "End this session (a host closing its link): any scan stops "
                "without SCAN_END, another host's HELLO then needs no take-over.",
                reply=MsgType.ACK),
    MessageSpec(MsgType.ACK, "Request accepted (header seq = request seq).",
                u("request_type", 8, "type of the request answered")),
    MessageSpec(MsgType.NAK, "Request refused (header seq = request seq).",
                u("request_type", 8, "type of the request answered"),
                u("code", 16, "error code (table below)", lo=1, hi=65535),
                text("field", "offending field or key name, empty if none"),
                text("detail", "human-readable reason (may be empty)")),
    MessageSpec(MsgType.INFO, "Device identity, limits and nominal geometry (reply to HELLO).",
                *wire_fields(Info)),
    MessageSpec(MsgType.CONFIG, "Configuration values (reply to CONFIG_GET).",
                Field("items", "KLV items (rest)", "key u8, length u16, value", kind="klv")),
    MessageSpec(MsgType.STATUS, "Device status (reply to STATUS_GET).", *wire_fields(Status)),
    MessageSpec(MsgType.CAPTURE_DATA, "One chunk of captured debug data (reply to CAPTURE).",
                *_CAPTURED,
                u("elem_bytes", 8, "bytes per element: 2 (i16), 4 (i32) or 8 (i64)", lo=2, hi=8),
                u("total", 32, "elements in the whole capture", "elements"),
                u("offset", 32, "index of the first element in this chunk", "elements"),
                Field("data", "bytes (rest)", "elements, signed little-endian", kind="bytes")),
    MessageSpec(MsgType.CHALLENGE, "Reply to a HELLO without a valid MAC from a device that holds "
                "a key: say HELLO again with this nonce and the MAC.",
                nbytes("device_nonce", 16, "fresh random nonce; valid for the next HELLO only")),
    MessageSpec(MsgType.POWER, "A rectangle of the power matrix (reply to POWER_GET).",
                *_RECT, _POWER),
    MessageSpec(MsgType.COLUMN_RESULT, "Receiver outputs of one column, all channels (layout "
                       "below).", *COLUMN_HEADER.fields),
    MessageSpec(MsgType.HEARTBEAT, "Status sent every heartbeat_ms while scanning (same fields as "
                "STATUS).", *wire_fields(Status)),
    MessageSpec(MsgType.SCAN_END, "End of a scan or calibration stream.",
                u("frame", 32, "frame id"),
                u("first_column", 16, "first column (or shot) of the scan"),
                u("columns", 16, "columns (or shots) produced"),
                u("calibration", 8, "1 for a calibration stream", lo=0, hi=1),
                u("reason", 8, "0 complete, 1 aborted, 2 device error", lo=0, hi=2)),
    MessageSpec(MsgType.FRAGMENT, "One piece of a message longer than the session's max frame "
                "(a COLUMN_RESULT, a reply such as INFO, or a notice): `count` = ceil(len / L) "
                "pieces, in order, of L = max_frame - 27 bytes (- 24 more when signed) each but "
                "the last.",
                u("msg_type", 8, "type of the whole message"),
                u("seq", 16, "reply: the request's seq; COLUMN_RESULT: 0"),
                u("frame", 32, "COLUMN_RESULT: frame id; else 0"),
                u("column", 16, "COLUMN_RESULT: column index; else 0"),
                u("index", 8, "this piece, 0..count-1", lo=0, hi=253),
                u("count", 8, "pieces of the whole message", lo=2, hi=254),
                Field("data", "bytes (rest)", "bytes index*L .. of the whole payload",
                      allowed="1..L bytes (L = max_frame-27, -24 when signed)", kind="bytes")),
    MessageSpec(MsgType.LINE_ERROR, "The device rejected a damaged chunk (CRC, COBS, length); "
                "information only (section 6.4): a host words its timeout diagnosis with it.",
                u("rx_errors", 32, "rejected chunks since boot")),
    MessageSpec(MsgType.SESSION_LOST, "The session in the header has ended; the device will "
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
#: Most FRAGMENTs one message may take (254, FRAGMENT.count's bound).
MAX_PIECES: int = MESSAGES[MsgType.FRAGMENT].field("count").hi  # type: ignore[assignment]


def piece_room(max_frame: int, signed: bool) -> int:
    """Data bytes of one FRAGMENT in a frame of ``max_frame`` bytes (spec section 6.3)."""
    return max_frame - frame_size(FRAGMENT_HEADER, signed)


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
    if (spec := MESSAGES.get(msg_type)) is None:  # type: ignore[call-overload]
        raise out_of_range("msg_type", "a known message type", msg_type, FieldError)
    if spec.type == MsgType.COLUMN_RESULT:
        if not isinstance(fields_, ColumnResult):
            raise out_of_range("COLUMN_RESULT", "a ColumnResult", type(fields_).__name__,
                               FieldError)
        return encode_column(fields_)
    return spec.encode(dict(fields_ or {}), spec.type.name)


def decode_payload(msg_type: int, payload: bytes) -> dict[str, Any] | ColumnResult:
    """A plain dict (lists for arrays) or, for COLUMN_RESULT, a ColumnResult; FrameError
    (only) naming the field for an unknown type, a short or long payload, a value out of range."""
    if msg_type == MsgType.COLUMN_RESULT:  # the hot path: no enum lookup
        return decode_column(payload)
    if (spec := MESSAGES.get(msg_type)) is None:  # type: ignore[call-overload]
        raise FrameError(f"unknown message type 0x{msg_type:02x}")
    out = spec.decode(payload, spec.type.name)
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
