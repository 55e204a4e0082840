"""COLUMN_RESULT: the receiver's integer outputs for one grating column, all channels.

The payload is a 19-byte column header (:data:`COLUMN_HEADER`) and one record per channel
(little-endian, packed), the record declared in :mod:`cdma_lidar.column_record`: ``41 +
10 * (P - 1)`` bytes with P peaks. The spec's rows, the numpy dtype (the codec, a few
microseconds per 40-channel column; the tests hold it to a construct codec byte for
byte), the range checks, the size and the properties of :class:`ColumnResult` all come
from that declaration.

UID signs travel as two masks (``uid_neg``, ``uid_zero``) and a lag -1 (no peak) as
:data:`NO_PEAK`: docs/protocol.md, "COLUMN_RESULT layout".
"""

from __future__ import annotations

import struct
from dataclasses import dataclass
from functools import lru_cache
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from cdma_lidar.checks import check_int
from cdma_lidar.column_record import (
    FIELD_NAMES,
    NO_PEAK,
    RECORD,
    WIRE_FIELDS,
    WireField,
    record_field,
    record_size,
)
from cdma_lidar.errors import FieldError, FrameError, out_of_range
from cdma_lidar.protocol.schema import Field, Layout, i, u

__all__ = ["COLUMN_HEADER", "FLAG_CALIBRATION", "MAX_PEAKS", "MAX_UID_BITS", "NO_PEAK",
           "RECORD_FIELDS", "ColumnResult", "column_payload_size", "decode_column",
           "encode_column", "record_dtype", "udeg"]

MAX_PEAKS = 8
MAX_UID_BITS = 8
#: flags bit 0: the column is a zeroth-order calibration shot (column = shot index).
FLAG_CALIBRATION = 0x01

COLUMN_HEADER = Layout(
    u("frame", 32, "frame id given in SCAN_START / CALIBRATE"),
    u("column", 16, "column index (calibration: shot index)"),
    u("flags", 8, "bit 0: calibration shot; other bits 0", lo=0, hi=1),
    u("uid_bits", 8, "n, UID code periods", "periods", 1, MAX_UID_BITS),
    u("peaks", 8, "P, peaks per channel", "", 1, MAX_PEAKS),
    u("channels", 16, "K, channel records that follow", "", 1, 65535),
    i("angle_udeg", 32, "grating rotation angle of the column", "µdeg"),
    u("timestamp_us", 32, "device clock when the column was measured (wraps)", "µs"),
)
_HEAD = struct.Struct("<" + "".join(f.fmt for f in COLUMN_HEADER.fields))  # its codec


def _record_field(w: WireField) -> Field:
    """The declaration (spec row) of one wire field of the channel record."""
    if not w.axes:
        return u(w.name, int(w.ctype[1:]), w.doc, w.unit, allowed=w.allowed, kind=w.ctype[0])
    return Field(w.name, w.spec_type, w.doc, w.unit, allowed=w.allowed, kind="array")


#: The channel record's fields in wire order (the spec's table; the codec is record_dtype).
RECORD_FIELDS = tuple(_record_field(w) for w in WIRE_FIELDS)


@lru_cache(maxsize=16)
def record_dtype(peaks: int) -> np.dtype:
    """Packed little-endian structured dtype of one channel record for ``peaks`` peaks."""
    check_int("peaks", peaks, 1, MAX_PEAKS, cls=FieldError)
    return np.dtype([(w.name, w.numpy_type, w.shape(peaks)) if w.axes else
                     (w.name, w.numpy_type) for w in WIRE_FIELDS])


def column_payload_size(channels: int, peaks: int) -> int:
    """Bytes of a COLUMN_RESULT payload for K channels and P peaks: ``19 + K*(41+10(P-1))``."""
    return _HEAD.size + channels * record_size(peaks)


#: What :meth:`ColumnResult.from_arrays` accepts per field: integers and lags the limits of
#: their wire type (a lag -1 travels as NO_PEAK), flags 0..1, signs -1..+1.
_LIMITS = {f.name: (0, 1) if f.encoding == "flag" else (-1, 1) if f.encoding == "signs"
           else f.wire[0].limits for f in RECORD}
_LAG_FIELDS = frozenset(f.name for f in RECORD if f.encoding == "lag")
#: The first wire field repeated per extra peak: its length is P - 1.
_FIRST_EXTRA = next(f for f in RECORD if f.per_extra_peak)


_FORMS = {"lag": "int64, -1 where the wire says NO_PEAK", "flag": "bool",
          "signs": "int8 in {-1, 0, +1}"}


def _view(name: str) -> property:
    """Read-only property of ColumnResult presenting record field ``name`` in the receiver's
    form (:data:`_FORMS`; plain integers as on the wire)."""
    f = record_field(name)
    wire = [w.name for w in f.wire]  # signs: the -1 mask, then the 0 mask

    def get(self: ColumnResult) -> NDArray:
        r = self.records[wire[0]]
        if f.encoding == "lag":
            return np.where(r == NO_PEAK, -1, r.astype(np.int64))
        if f.encoding == "signs":  # (..., n): bit p of the -1 mask and of the 0 mask
            bits = np.arange(self.uid_bits, dtype=np.uint8)
            neg, zero = ((self.records[w][..., None] >> bits) & 1 for w in wire)
            return np.where(zero == 1, 0, np.where(neg == 1, -1, 1)).astype(np.int8)
        return r.astype(bool) if f.encoding == "flag" else r

    get.__name__ = name
    unit = f" ({f.unit})" if f.unit else ""
    form = _FORMS.get(f.encoding, f"{f.wire[0].ctype} as on the wire")
    get.__doc__ = f"(K{''.join(', ' + str(a) for a in f.axes)}) {f.doc}{unit}; {form}."
    return property(get)


def udeg(angle_deg: float) -> int:
    """A column's angle on the wire: micro-degrees, rounded to the nearest (half to even)."""
    return round(float(angle_deg) * 1e6)


@dataclass(frozen=True, eq=False)
class ColumnResult:
    """One column of receiver outputs: the payload of a COLUMN_RESULT frame.

    One read-only property per field of :data:`cdma_lidar.column_record.RECORD` (the
    receiver's shapes) views ``records`` (:func:`record_dtype`): integers as their wire
    type, lags as int64 with -1 for :data:`NO_PEAK`, flags as bool, signs as int8 in
    {-1, 0, +1}. :meth:`from_arrays` and :meth:`from_receiver` check every value against
    its wire field; :func:`decode_column` builds one from the wire bytes.

    Attributes:
        frame: frame id (u32) given by the host in SCAN_START / CALIBRATE.
        column: column index (u16); for calibration shots, the shot index.
        angle_udeg: grating rotation angle (micro-degrees, i32).
        records: structured array of shape (K,).
        uid_bits: n, UID code periods (1..8).
        calibration: True for a zeroth-order calibration shot.
        timestamp_us: device clock at measurement (us, u32, wraps).
    """

    frame: int
    column: int
    angle_udeg: int
    records: np.ndarray
    uid_bits: int = 1
    calibration: bool = False
    timestamp_us: int = 0

    # ---- one read-only view per field of column_record.RECORD (a test checks the list) --
    peak_lag = _view("peak_lag")
    peak = _view("peak")
    neighbours = _view("neighbours")
    noise_count = _view("noise_count")
    noise_sum = _view("noise_sum")
    noise_sumsq = _view("noise_sumsq")
    uid_signs = _view("uid_signs")
    uid_observed = _view("uid_observed")
    uid_match = _view("uid_match")
    saturated = _view("saturated")
    extra_lag = _view("extra_lag")
    extra_peak = _view("extra_peak")
    extra_signs = _view("extra_signs")

    # ---- derived views ------------------------------------------------------------------
    @property
    def channels(self) -> int:
        """K, number of channel records."""
        return int(self.records.shape[0])

    @property
    def peaks(self) -> int:
        """P, peaks per channel (1 + extra peaks)."""
        return 1 + int(self.records.dtype[_FIRST_EXTRA.wire[0].name].shape[0])

    @property
    def angle_deg(self) -> float:
        """Grating rotation angle (deg)."""
        return self.angle_udeg * 1e-6

    def _key(self) -> tuple:
        return (self.frame, self.column, self.angle_udeg, self.uid_bits, self.calibration,
                self.timestamp_us, self.records.dtype, self.records.tobytes())

    def __eq__(self, other: object) -> bool:
        return self._key() == other._key() if isinstance(other, ColumnResult) else NotImplemented

    __hash__ = None  # type: ignore[assignment]

    # ---- construction ---------------------------------------------------------------
    @classmethod
    def from_arrays(cls, frame: int, column: int, angle_deg: float, *,
                    calibration: bool = False, timestamp_us: int = 0,
                    **fields: ArrayLike | None) -> ColumnResult:
        """Check every value against its wire field and pack the records. ``fields``: the
        record's fields by name, shaped as in ``firmware_model.output.ReceiverOutput`` (K
        channels, n UID bits, P peaks); the ``extra_*`` ones may be left out (or None) for
        P = 1. Raises FieldError naming the first bad field."""
        if unknown := sorted(set(fields) - set(FIELD_NAMES)):  # as for a bad keyword argument
            raise TypeError(f"from_arrays() got an unexpected keyword argument {unknown[0]!r}")
        if missing := [f.name for f in RECORD if not f.per_extra_peak and f.name not in fields]:
            raise TypeError(f"from_arrays() missing required keyword-only argument {missing[0]!r}")
        signs = np.asarray(fields["uid_signs"])
        if signs.ndim != 2:
            raise out_of_range("uid_signs", "a (K, n) array", f"shape {signs.shape}",
                               FieldError)
        k, n = signs.shape  # channels and UID bits
        angle_udeg = udeg(angle_deg)
        for name, value in (("frame", frame), ("column", column), ("uid_bits", n),
                            ("channels", k), ("angle_udeg", angle_udeg),
                            ("timestamp_us", timestamp_us)):  # the header's declared ranges
            COLUMN_HEADER.field(name).check(name, value)
        first_extra = fields.get(_FIRST_EXTRA.name)
        e = 0 if first_extra is None else np.asarray(first_extra).reshape(k, -1).shape[1]
        rec = np.zeros(k, dtype=record_dtype(e + 1))
        for f in RECORD:
            if f.per_extra_peak and not e:
                continue
            arr = _checked_array(f.name, fields.get(f.name), (k, *f.shape(n, e + 1)))
            if f.encoding == "signs":  # two masks: bit p of each is period p
                weights = (1 << np.arange(n)).astype(np.uint8)
                for w, mask in zip(f.wire, (arr < 0, arr == 0), strict=True):
                    rec[w.name] = mask.astype(np.uint8) @ weights
            else:
                rec[f.name] = arr
            if f.name == "uid_observed" and int(arr.max()) >= 1 << n:
                raise out_of_range(f.name, f"below 2^uid_bits = {1 << n}", int(arr.max()),
                                   FieldError)
        rec.flags.writeable = False
        return cls(int(frame), int(column), angle_udeg, rec, n, bool(calibration),
                   int(timestamp_us))

    @classmethod
    def from_receiver(cls, frame: int, column: int, angle_deg: float, out: Any, *,
                      calibration: bool = False, timestamp_us: int = 0) -> ColumnResult:
        """Pack a ``ReceiverOutput`` (every field but ``corr``; extras of P = 1 empty or
        absent) into a column."""
        return cls.from_arrays(frame, column, angle_deg, calibration=calibration,
                               timestamp_us=timestamp_us,
                               **{f.name: getattr(out, f.name, None) for f in RECORD})


#: Fields whose exact value may exceed the wire word: the model carries noise_sumsq as exact
#: Python ints when its width passes 63 bits (docs/firmware.md section 3); the u64 wire field
#: then carries it saturated to 2^64 - 1, which the host reads as "noise floor unknown".
_WIRE_SATURATES = frozenset({"noise_sumsq"})


def _checked_array(name: str, value: Any, shape: tuple[int, ...]) -> NDArray:
    arr = np.asarray(value)
    if name in _WIRE_SATURATES and arr.dtype == object:
        hi = _LIMITS[name][1]
        arr = np.array([min(int(v), hi) for v in arr.ravel()], dtype=np.uint64).reshape(arr.shape)
    if name in _LAG_FIELDS and arr.dtype.kind == "i" and arr.size and int(arr.min()) == -1:
        arr = np.where(arr == -1, NO_PEAK, arr).astype(np.int64)  # "no peak" on the wire
    if arr.shape != shape:
        raise out_of_range(name, f"an array of shape {shape}", f"shape {arr.shape}", FieldError)
    if arr.dtype.kind not in "iub":
        raise out_of_range(name, "an integer array", f"dtype {arr.dtype}", FieldError)
    lo, hi = _LIMITS[name]
    if arr.size:
        amin, amax = int(arr.min()), int(arr.max())
        if amin < lo or amax > hi:
            raise out_of_range(name, f"integers from {lo} to {hi}", amin if amin < lo else amax,
                               FieldError)
    return arr


# ---- fast codec (numpy) -------------------------------------------------------------
def encode_column(col: ColumnResult) -> bytes:
    """COLUMN_RESULT payload bytes of ``col`` (fast path)."""
    rec = col.records
    head = _HEAD.pack(col.frame, col.column, FLAG_CALIBRATION if col.calibration else 0,
                      col.uid_bits, col.peaks, rec.shape[0], col.angle_udeg, col.timestamp_us)
    return head + rec.tobytes()


def decode_column(payload: bytes) -> ColumnResult:
    """Parse a COLUMN_RESULT payload (fast path); raises FrameError (only) if malformed."""
    if len(payload) < _HEAD.size:
        raise FrameError(f"column: payload of {len(payload)} bytes, header needs {_HEAD.size}")
    frame, column, flags, n, p, k, angle, ts = _HEAD.unpack_from(payload)
    if not 1 <= n <= MAX_UID_BITS or not 1 <= p <= MAX_PEAKS or k == 0 or flags & ~1:
        raise FrameError(f"column: uid_bits {n}, peaks {p}, channels {k}, flags {flags:#x}")
    if len(payload) != (need := column_payload_size(k, p)):
        raise FrameError(f"column: {len(payload)} bytes, {k} channels x {p} peaks need {need}")
    rec = np.frombuffer(payload, dtype=record_dtype(p), count=k, offset=_HEAD.size)
    # Same as ColumnResult(...) minus the frozen-dataclass __setattr__ calls (hot path).
    col = object.__new__(ColumnResult)
    col.__dict__.update(frame=frame, column=column, angle_udeg=angle, records=rec, uid_bits=n,
                        calibration=bool(flags & FLAG_CALIBRATION), timestamp_us=ts)
    return col
