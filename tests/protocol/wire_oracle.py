"""The oracle of the wire codec: construct, an independent declarative codec (tests only).

Each payload of :data:`cdma_lidar.protocol.messages.MESSAGES` and each CONFIG value
encoding is translated field by field into a construct ``Struct`` (the translation reads
only a field's name, kind and wire type); the COLUMN_RESULT payload is declared from
:data:`cdma_lidar.column_record.WIRE_FIELDS`. The tests hold the run-time codec (plain
``struct`` and numpy) to these byte for byte; ``bench protocol`` times its column codec
against :func:`encode_column_construct` / :func:`decode_column_construct`.
"""

from __future__ import annotations

import construct as cs
import numpy as np

from cdma_lidar.column_record import WIRE_FIELDS
from cdma_lidar.errors import FrameError
from cdma_lidar.protocol.columns import FLAG_CALIBRATION, MAX_PEAKS, ColumnResult, record_dtype
from cdma_lidar.protocol.messages import MESSAGES, MsgType
from cdma_lidar.protocol.schema import Field

_INT = {"B": cs.Int8ul, "H": cs.Int16ul, "I": cs.Int32ul, "Q": cs.Int64ul, "h": cs.Int16sl,
        "i": cs.Int32sl, "q": cs.Int64sl}


def field_construct(f: Field) -> cs.Construct:
    """The construct of one declared field."""
    if f.kind == "int":
        return _INT[f.fmt]
    if f.kind == "text":
        return cs.PascalString(cs.Int8ul, "utf8")
    if f.kind == "bytes":
        return cs.Bytes(f.max_items) if f.max_items else cs.GreedyBytes
    if f.kind == "klv":
        return cs.GreedyRange(cs.Struct("key" / cs.Int8ul,
                                        "value" / cs.Prefixed(cs.Int16ul, cs.GreedyBytes)))
    elem = cs.Struct(*(n / _INT[c] for n, c in zip(f.names, f.fmt, strict=True))) \
        if f.names else _INT[f.fmt]
    if f.count in ("B", "H"):
        return cs.PrefixedArray(_INT[f.count], elem)
    if f.count:
        a, b = f.count.split("*")
        return cs.Array(lambda ctx: ctx[a] * ctx[b], elem)
    return cs.GreedyRange(elem)


#: Every payload but COLUMN_RESULT's, as a construct Struct that must parse to the end.
STRUCTS = {t: cs.Struct(*(f.name / field_construct(f) for f in m.fields), cs.Terminated)
           for t, m in MESSAGES.items() if t != MsgType.COLUMN_RESULT}


def plain(v):
    """construct's containers as plain lists and dicts (private keys dropped)."""
    if isinstance(v, dict):
        return {k: plain(x) for k, x in v.items() if not k.startswith("_")}
    if isinstance(v, list):
        return [plain(x) for x in v]
    return v


def build(msg_type: MsgType, fields: dict) -> bytes:
    """Payload bytes through construct (no range checks)."""
    values = dict(fields)
    if "power" in values:
        values["power"] = np.asarray(values["power"]).ravel().tolist()
    return STRUCTS[msg_type].build(values)


def parse(msg_type: MsgType, payload: bytes) -> dict:
    """Field values through construct; raises construct's errors or UnicodeDecodeError."""
    return plain(dict(STRUCTS[msg_type].parse(payload)))


# ---- COBS: the pure-Python reference of framing.cobs_encode and cobs_decode -----------------
def cobs_encode_py(data: bytes) -> bytes:
    """COBS-encode ``data`` (reference implementation; output has no 0x00 byte)."""
    out = bytearray()
    segments = bytes(data).split(b"\x00")
    last = len(segments) - 1
    for k, seg in enumerate(segments):
        # Full 254-byte blocks first: code 0xFF, no implied zero.
        full = len(seg) // 254
        for b in range(full):
            out.append(0xFF)
            out += seg[254 * b:254 * (b + 1)]
        rest = seg[254 * full:]
        # The remainder block (code len+1) implies the zero that ended the segment. The
        # last segment has no such zero, so after full blocks it needs no block at all.
        if k < last or not (full and not rest):
            out.append(len(rest) + 1)
            out += rest
    return bytes(out)


def cobs_decode_py(enc: bytes) -> bytes:
    """Decode one COBS block sequence (no delimiters); raises FrameError if malformed."""
    enc = bytes(enc)
    out = bytearray()
    i, n = 0, len(enc)
    if n == 0:
        raise FrameError("COBS: empty input")
    while i < n:
        code = enc[i]
        if code == 0:
            raise FrameError(f"COBS: zero byte at offset {i}")
        end = i + code
        if end > n:
            raise FrameError(f"COBS: block at offset {i} runs past the end")
        block = enc[i + 1:end]
        if 0 in block:
            raise FrameError(f"COBS: zero byte inside block at offset {i}")
        out += block
        i = end
        if code != 0xFF and i < n:
            out.append(0)
    return bytes(out)


# ---- COLUMN_RESULT --------------------------------------------------------------------------
_CS = {"u8": cs.Int8ul, "u32": cs.Int32ul, "u64": cs.Int64ul, "i32": cs.Int32sl, "i64": cs.Int64sl}
_E = cs.this._.peaks - 1  # extra peaks per channel


def _record_field(w) -> cs.Renamed:
    sub: cs.Construct = _CS[w.ctype]
    for axis in reversed(w.axes):
        sub = cs.Array(_E if axis == "P-1" else axis, sub)
    return w.name / sub


#: One channel record, and the whole COLUMN_RESULT payload.
RECORD_STRUCT = cs.Struct(*(_record_field(w) for w in WIRE_FIELDS))
COLUMN_STRUCT = cs.Struct(
    "frame" / cs.Int32ul, "column" / cs.Int16ul, "flags" / cs.Int8ul, "uid_bits" / cs.Int8ul,
    "peaks" / cs.Int8ul, "channels" / cs.Int16ul, "angle_udeg" / cs.Int32sl,
    "timestamp_us" / cs.Int32ul, "records" / cs.Array(cs.this.channels, RECORD_STRUCT))


def encode_column_construct(col: ColumnResult) -> bytes:
    """COLUMN_RESULT payload bytes built through :data:`COLUMN_STRUCT`."""
    names = [w.name for w in WIRE_FIELDS]
    per_field = [col.records[name].tolist() for name in names]  # Python ints and lists
    recs = [dict(zip(names, values, strict=True)) for values in zip(*per_field, strict=True)]
    return COLUMN_STRUCT.build({
        "frame": col.frame, "column": col.column,
        "flags": FLAG_CALIBRATION if col.calibration else 0, "uid_bits": col.uid_bits,
        "peaks": col.peaks, "channels": col.channels, "angle_udeg": col.angle_udeg,
        "timestamp_us": col.timestamp_us, "records": recs})


def decode_column_construct(payload: bytes) -> ColumnResult:
    """Parse a COLUMN_RESULT payload through :data:`COLUMN_STRUCT`."""
    try:
        c = COLUMN_STRUCT.parse(payload)
    except cs.ConstructError as exc:
        raise FrameError(f"column: {exc}") from None
    if not 1 <= c.peaks <= MAX_PEAKS:
        raise FrameError(f"column: peaks {c.peaks}")
    rec = np.zeros(c.channels, dtype=record_dtype(c.peaks))
    for idx, r in enumerate(c.records):
        rec[idx] = tuple(list(r[w.name]) if w.axes else r[w.name] for w in WIRE_FIELDS)
    rec.flags.writeable = False
    return ColumnResult(c.frame, c.column, c.angle_udeg, rec, c.uid_bits,
                        bool(c.flags & FLAG_CALIBRATION), c.timestamp_us)
