"""COLUMN_RESULT: the receiver's integer outputs for one grating column, all channels.

The payload is a 19-byte column header followed by one fixed-size record per
channel (array of structs, little-endian, packed, no padding). With P peaks and
n UID bits a record is ``40 + 10 * (P - 1)`` bytes::

    column header                      channel record (K of them)
    off size                           off      size
      0   4  frame        u32            0        4  peak_lag     u32  samples
      4   2  column       u16            4        4  peak         i32  out units
      6   1  flags        u8             8        8  neighbours   2 x i32 (lag-1, lag+1)
      7   1  uid_bits     u8  n         16        4  noise_count  u32
      8   1  peaks        u8  P         20        8  noise_sum    i64
      9   2  channels     u16 K         28        8  noise_sumsq  u64
     11   4  angle_udeg   i32           36        1  uid_neg      u8 mask
     15   4  timestamp_us u32           37        1  uid_zero     u8 mask
                                        38        1  uid_observed u8
                                        39        1  uid_match    u8 (0 or 1)
                                        40  4(P-1)  extra_lag    u32[P-1]
                                          4(P-1)  extra_peak   i32[P-1]
                                          1(P-1)  extra_neg    u8[P-1]
                                          1(P-1)  extra_zero   u8[P-1]

UID signs travel as two masks: bit p of ``uid_neg`` is set where the per-period
sign at the peak is -1, bit p of ``uid_zero`` where it is 0 (neither: +1).

Two codecs produce the same bytes: the fast one (numpy structured dtype, a few
microseconds per 40-channel column) used on the link, and the declarative one
(construct, :data:`COLUMN_STRUCT`) that documents the layout and serves as the
baseline in ``bench/bench_protocol.py``. ``tests/protocol`` proves them equal.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass
from functools import lru_cache
from typing import Any

import construct as cs
import numpy as np
from numpy.typing import ArrayLike, NDArray

from cdma_lidar.errors import FieldError, FrameError, out_of_range
from cdma_lidar.protocol.schema import blob, i, u

__all__ = [
    "COLUMN_HEADER",
    "COLUMN_STRUCT",
    "FLAG_CALIBRATION",
    "MAX_PEAKS",
    "MAX_UID_BITS",
    "NO_PEAK",
    "ColumnResult",
    "column_payload_size",
    "decode_column",
    "decode_column_construct",
    "encode_column",
    "encode_column_construct",
    "record_dtype",
]

MAX_PEAKS = 8
MAX_UID_BITS = 8
#: flags bit 0: the column is a zeroth-order calibration shot (column = shot index).
FLAG_CALIBRATION = 0x01

_HEAD = struct.Struct("<IHBBBHiI")

COLUMN_HEADER = cs.Struct(
    u("frame", 32, "frame id given in SCAN_START / CALIBRATE"),
    u("column", 16, "column index (calibration: shot index)"),
    u("flags", 8, "bit 0: calibration shot; other bits 0", lo=0, hi=1),
    u("uid_bits", 8, "n, UID code periods", "periods", 1, MAX_UID_BITS),
    u("peaks", 8, "P, peaks per channel", "", 1, MAX_PEAKS),
    u("channels", 16, "K, channel records that follow", "", 1, 65535),
    i("angle_udeg", 32, "grating rotation angle of the column", "µdeg"),
    u("timestamp_us", 32, "device clock when the column was measured (wraps)", "µs"),
)

_E = cs.this._.peaks - 1  # extra peaks per channel
_RECORD_STRUCT = cs.Struct(
    u("peak_lag", 32, "lag of the strongest peak; 0xFFFFFFFF: no eligible lag", "samples",
      0, None, "0..N*S-1 or 0xFFFFFFFF"),
    i("peak", 32, "scaled correlation out at peak_lag", "out LSB", allowed="signed out_bits"),
    blob("neighbours", cs.Array(2, cs.Int32sl), "i32[2]", "out at peak_lag-1, peak_lag+1",
         "out LSB", "signed out_bits"),
    u("noise_count", 32, "gate lags in the noise floor", "lags", allowed="0..gate_len"),
    i("noise_sum", 64, "sum of out over the noise lags", "out LSB"),
    u("noise_sumsq", 64, "sum of out^2 over the noise lags", "out LSB^2"),
    u("uid_neg", 8, "bit p: period p's sign at the peak is -1", "mask",
      allowed="bits 0..n-1"),
    u("uid_zero", 8, "bit p: period p's sign at the peak is 0", "mask",
      allowed="bits 0..n-1"),
    u("uid_observed", 8, "observed UID: bit p set where period p's sign is -1", "",
      allowed="0..2^n-1"),
    u("uid_match", 8, "1 when no sign is 0 and uid_observed == uid", "", 0, 1),
    blob("extra_lag", cs.Array(_E, cs.Int32ul), "u32[P-1]",
         "lags of peaks 2..P; 0xFFFFFFFF: no such peak", "samples", "0..N*S-1 or 0xFFFFFFFF"),
    blob("extra_peak", cs.Array(_E, cs.Int32sl), "i32[P-1]", "out at peaks 2..P", "out LSB",
         "signed out_bits"),
    blob("extra_neg", cs.Array(_E, cs.Int8ul), "u8[P-1]", "sign masks (-1) of peaks 2..P",
         "mask", "bits 0..n-1"),
    blob("extra_zero", cs.Array(_E, cs.Int8ul), "u8[P-1]", "sign masks (0) of peaks 2..P",
         "mask", "bits 0..n-1"),
)

#: Declarative form of the whole COLUMN_RESULT payload (documentation and baseline codec).
COLUMN_STRUCT = cs.Struct(
    *COLUMN_HEADER.subcons,
    "records" / cs.Array(cs.this.channels, _RECORD_STRUCT),
)


@lru_cache(maxsize=16)
def record_dtype(peaks: int) -> np.dtype:
    """Packed little-endian structured dtype of one channel record for ``peaks`` peaks."""
    if not 1 <= peaks <= MAX_PEAKS:
        raise out_of_range("peaks", f"an integer from 1 to {MAX_PEAKS}", peaks, FieldError)
    e = peaks - 1
    return np.dtype([
        ("peak_lag", "<u4"), ("peak", "<i4"), ("neighbours", "<i4", (2,)),
        ("noise_count", "<u4"), ("noise_sum", "<i8"), ("noise_sumsq", "<u8"),
        ("uid_neg", "u1"), ("uid_zero", "u1"), ("uid_observed", "u1"), ("uid_match", "u1"),
        ("extra_lag", "<u4", (e,)), ("extra_peak", "<i4", (e,)),
        ("extra_neg", "u1", (e,)), ("extra_zero", "u1", (e,)),
    ])


def column_payload_size(channels: int, peaks: int) -> int:
    """Bytes of a COLUMN_RESULT payload for K channels and P peaks: ``19 + K*(40+10(P-1))``."""
    return _HEAD.size + channels * (40 + 10 * (peaks - 1))


#: Wire value of a lag where the receiver found no eligible peak (it reports lag -1).
NO_PEAK = 0xFFFF_FFFF

_LAG_FIELDS = ("peak_lag", "extra_lag")

_INT_LIMITS = {
    "peak_lag": (0, 2**32 - 1), "peak": (-(2**31), 2**31 - 1),
    "neighbours": (-(2**31), 2**31 - 1), "noise_count": (0, 2**32 - 1),
    "noise_sum": (-(2**63), 2**63 - 1), "noise_sumsq": (0, 2**64 - 1),
    "uid_observed": (0, 255), "extra_lag": (0, 2**32 - 1), "extra_peak": (-(2**31), 2**31 - 1),
}


def _masks(signs: NDArray, n: int) -> tuple[NDArray, NDArray]:
    """(negative mask, zero mask) along the last axis of a sign array in {-1, 0, +1}."""
    weights = _WEIGHTS[:n]
    neg = (signs < 0).astype(np.uint8) @ weights
    zero = (signs == 0).astype(np.uint8) @ weights
    return neg, zero


_WEIGHTS = (1 << np.arange(MAX_UID_BITS)).astype(np.uint8)


def _signs(neg: NDArray, zero: NDArray, n: int) -> NDArray[np.int8]:
    """Sign array (..., n) in {-1, 0, +1} from the two masks."""
    bits = np.arange(n, dtype=np.uint8)
    neg_b = (np.asarray(neg)[..., None] >> bits) & 1
    zero_b = (np.asarray(zero)[..., None] >> bits) & 1
    return np.where(zero_b == 1, 0, np.where(neg_b == 1, -1, 1)).astype(np.int8)


@dataclass(frozen=True, eq=False)
class ColumnResult:
    """One column of receiver outputs: the payload of a COLUMN_RESULT frame.

    Per-channel fields are read-only numpy views of ``records`` (one structured
    record per channel, :func:`record_dtype`). Build one with :meth:`from_arrays`
    or :meth:`from_receiver` (both check every value against its wire field);
    :func:`decode_column` builds one straight from the wire bytes.

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

    # ---- derived views -------------------------------------------------------------
    @property
    def channels(self) -> int:
        """K, number of channel records."""
        return int(self.records.shape[0])

    @property
    def peaks(self) -> int:
        """P, peaks per channel (1 + extra peaks)."""
        return 1 + int(self.records.dtype["extra_lag"].shape[0])

    @property
    def angle_deg(self) -> float:
        """Grating rotation angle (deg)."""
        return self.angle_udeg * 1e-6

    @property
    def peak_lag(self) -> NDArray[np.int64]:
        """(K,) lag of the strongest peak (samples); -1 where no lag was eligible."""
        return _lags_from_wire(self.records["peak_lag"])

    @property
    def peak(self) -> NDArray[np.int32]:
        """(K,) scaled correlation at the peak."""
        return self.records["peak"]

    @property
    def neighbours(self) -> NDArray[np.int32]:
        """(K, 2) scaled correlation at peak_lag - 1 and peak_lag + 1."""
        return self.records["neighbours"]

    @property
    def noise_count(self) -> NDArray[np.uint32]:
        """(K,) number of lags in the noise floor."""
        return self.records["noise_count"]

    @property
    def noise_sum(self) -> NDArray[np.int64]:
        """(K,) sum of the noise-floor outputs."""
        return self.records["noise_sum"]

    @property
    def noise_sumsq(self) -> NDArray[np.uint64]:
        """(K,) sum of squares of the noise-floor outputs."""
        return self.records["noise_sumsq"]

    @property
    def uid_signs(self) -> NDArray[np.int8]:
        """(K, n) per-period sign at the peak, in {-1, 0, +1}."""
        return _signs(self.records["uid_neg"], self.records["uid_zero"], self.uid_bits)

    @property
    def uid_observed(self) -> NDArray[np.uint8]:
        """(K,) observed UID (bit p set where period p's sign is negative)."""
        return self.records["uid_observed"]

    @property
    def uid_match(self) -> NDArray[np.bool_]:
        """(K,) True when the observed UID equals the configured one and no sign is 0."""
        return self.records["uid_match"].astype(bool)

    @property
    def extra_lag(self) -> NDArray[np.int64]:
        """(K, P-1) lags of peaks 2..P (samples); -1 where there was no such peak."""
        return _lags_from_wire(self.records["extra_lag"])

    @property
    def extra_peak(self) -> NDArray[np.int32]:
        """(K, P-1) values of peaks 2..P."""
        return self.records["extra_peak"]

    @property
    def extra_signs(self) -> NDArray[np.int8]:
        """(K, P-1, n) per-period signs at peaks 2..P."""
        return _signs(self.records["extra_neg"], self.records["extra_zero"], self.uid_bits)

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, ColumnResult):
            return NotImplemented
        return (self.frame, self.column, self.angle_udeg, self.uid_bits, self.calibration,
                self.timestamp_us) == (other.frame, other.column, other.angle_udeg,
                                       other.uid_bits, other.calibration, other.timestamp_us) \
            and self.records.dtype == other.records.dtype \
            and self.records.tobytes() == other.records.tobytes()

    __hash__ = None  # type: ignore[assignment]

    # ---- construction ---------------------------------------------------------------
    @classmethod
    def from_arrays(cls, frame: int, column: int, angle_deg: float, *,
                    peak_lag: ArrayLike, peak: ArrayLike, neighbours: ArrayLike,
                    noise_count: ArrayLike, noise_sum: ArrayLike, noise_sumsq: ArrayLike,
                    uid_signs: ArrayLike, uid_observed: ArrayLike, uid_match: ArrayLike,
                    extra_lag: ArrayLike | None = None, extra_peak: ArrayLike | None = None,
                    extra_signs: ArrayLike | None = None, calibration: bool = False,
                    timestamp_us: int = 0) -> ColumnResult:
        """Check every value against its wire field and pack the records.

        Shapes are those of ``cdma_lidar.firmware_model.receiver.ReceiverOutput`` (K channels,
        n UID bits, P peaks). Raises FieldError naming the first bad field.
        """
        _check_int("frame", frame, 0, 2**32 - 1)
        _check_int("column", column, 0, 2**16 - 1)
        _check_int("timestamp_us", timestamp_us, 0, 2**32 - 1)
        angle_udeg = round(float(angle_deg) * 1e6)
        _check_int("angle_deg (micro-degrees)", angle_udeg, -(2**31), 2**31 - 1)
        signs = np.asarray(uid_signs)
        if signs.ndim != 2:
            raise out_of_range("uid_signs", "a (K, n) array", f"shape {signs.shape}",
                               FieldError)
        k, n = signs.shape
        if not 1 <= n <= MAX_UID_BITS:
            raise out_of_range("uid_bits", f"1 to {MAX_UID_BITS} (uid_signs columns)", n,
                               FieldError)
        if not 1 <= k <= 65535:
            raise out_of_range("channels", "1 to 65535", k, FieldError)
        e = 0 if extra_lag is None else np.asarray(extra_lag).reshape(k, -1).shape[1]
        rec = np.zeros(k, dtype=record_dtype(e + 1))
        arrays: dict[str, Any] = {
            "peak_lag": (peak_lag, (k,)), "peak": (peak, (k,)),
            "neighbours": (neighbours, (k, 2)), "noise_count": (noise_count, (k,)),
            "noise_sum": (noise_sum, (k,)), "noise_sumsq": (noise_sumsq, (k,)),
            "uid_observed": (uid_observed, (k,)),
        }
        if e:
            arrays["extra_lag"] = (extra_lag, (k, e))
            arrays["extra_peak"] = (extra_peak, (k, e))
        for name, (value, shape) in arrays.items():
            rec[name] = _checked_array(name, value, shape)
        _check_signs("uid_signs", signs)
        rec["uid_neg"], rec["uid_zero"] = _masks(signs, n)
        if int(np.max(rec["uid_observed"])) >= 1 << n:
            raise out_of_range("uid_observed", f"below 2^uid_bits = {1 << n}",
                               int(np.max(rec["uid_observed"])), FieldError)
        match = np.asarray(uid_match)
        if match.shape != (k,) or match.dtype.kind not in "biu" or \
                (k and (match.min() < 0 or match.max() > 1)):
            raise out_of_range("uid_match", f"a ({k},) array of booleans", match, FieldError)
        rec["uid_match"] = match
        if e:
            es = np.asarray(extra_signs) if extra_signs is not None else None
            if es is None or es.shape != (k, e, n):
                raise out_of_range("extra_signs", f"a ({k}, {e}, {n}) array",
                                   None if es is None else f"shape {es.shape}", FieldError)
            _check_signs("extra_signs", es)
            rec["extra_neg"], rec["extra_zero"] = _masks(es, n)
        rec.flags.writeable = False
        return cls(int(frame), int(column), angle_udeg, rec, n, bool(calibration),
                   int(timestamp_us))

    @classmethod
    def from_receiver(cls, frame: int, column: int, angle_deg: float, out: Any, *,
                      calibration: bool = False, timestamp_us: int = 0) -> ColumnResult:
        """Pack a ``ReceiverOutput`` (every field but ``corr``) into a column."""
        extra = getattr(out, "extra_lag", None)
        has_extra = extra is not None and np.asarray(extra).size > 0
        return cls.from_arrays(
            frame, column, angle_deg, peak_lag=out.peak_lag, peak=out.peak,
            neighbours=out.neighbours, noise_count=out.noise_count, noise_sum=out.noise_sum,
            noise_sumsq=out.noise_sumsq, uid_signs=out.uid_signs,
            uid_observed=out.uid_observed, uid_match=out.uid_match,
            extra_lag=out.extra_lag if has_extra else None,
            extra_peak=out.extra_peak if has_extra else None,
            extra_signs=out.extra_signs if has_extra else None,
            calibration=calibration, timestamp_us=timestamp_us)


def _check_int(name: str, value: Any, lo: int, hi: int) -> None:
    if isinstance(value, bool) or not isinstance(value, int | np.integer) or \
            not lo <= int(value) <= hi:
        raise out_of_range(name, f"an integer from {lo} to {hi}", value, FieldError)


def _lags_from_wire(lags: NDArray[np.uint32]) -> NDArray[np.int64]:
    """Wire lags as int64, with NO_PEAK turned back into the receiver's -1."""
    out = lags.astype(np.int64)
    out[lags == NO_PEAK] = -1
    return out


def _checked_array(name: str, value: Any, shape: tuple[int, ...]) -> NDArray:
    arr = np.asarray(value)
    if name in _LAG_FIELDS and arr.dtype.kind == "i" and arr.size and int(arr.min()) == -1:
        arr = np.where(arr == -1, NO_PEAK, arr).astype(np.int64)  # "no peak" on the wire
    if arr.shape != shape:
        raise out_of_range(name, f"an array of shape {shape}", f"shape {arr.shape}", FieldError)
    if arr.dtype.kind not in "iub":
        raise out_of_range(name, "an integer array", f"dtype {arr.dtype}", FieldError)
    lo, hi = _INT_LIMITS[name]
    if arr.size:
        amin, amax = int(arr.min()), int(arr.max())
        if amin < lo or amax > hi:
            raise out_of_range(name, f"integers from {lo} to {hi}", amin if amin < lo else amax,
                               FieldError)
    return arr


def _check_signs(name: str, signs: NDArray) -> None:
    if signs.dtype.kind not in "iu" or (signs.size and (signs.min() < -1 or signs.max() > 1)):
        raise out_of_range(name, "values in {-1, 0, +1}", signs, FieldError)


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
    dt = record_dtype(p)
    if len(payload) != _HEAD.size + k * dt.itemsize:
        raise FrameError(f"column: {len(payload)} bytes, {k} channels x {p} peaks need "
                         f"{_HEAD.size + k * dt.itemsize}")
    rec = np.frombuffer(payload, dtype=dt, count=k, offset=_HEAD.size)
    # Same as ColumnResult(...) minus the frozen-dataclass __setattr__ calls (hot path).
    col = object.__new__(ColumnResult)
    col.__dict__.update(frame=frame, column=column, angle_udeg=angle, records=rec, uid_bits=n,
                        calibration=bool(flags & FLAG_CALIBRATION), timestamp_us=ts)
    return col


# ---- declarative codec (construct) --------------------------------------------------
def encode_column_construct(col: ColumnResult) -> bytes:
    """COLUMN_RESULT payload bytes built through :data:`COLUMN_STRUCT` (baseline path)."""
    recs = []
    e = col.peaks - 1
    for r in col.records:
        recs.append({
            "peak_lag": int(r["peak_lag"]), "peak": int(r["peak"]),
            "neighbours": [int(v) for v in r["neighbours"]],
            "noise_count": int(r["noise_count"]), "noise_sum": int(r["noise_sum"]),
            "noise_sumsq": int(r["noise_sumsq"]), "uid_neg": int(r["uid_neg"]),
            "uid_zero": int(r["uid_zero"]), "uid_observed": int(r["uid_observed"]),
            "uid_match": int(r["uid_match"]),
            "extra_lag": [int(v) for v in r["extra_lag"]][:e],
            "extra_peak": [int(v) for v in r["extra_peak"]][:e],
            "extra_neg": [int(v) for v in r["extra_neg"]][:e],
            "extra_zero": [int(v) for v in r["extra_zero"]][:e],
        })
    return COLUMN_STRUCT.build({
        "frame": col.frame, "column": col.column,
        "flags": FLAG_CALIBRATION if col.calibration else 0, "uid_bits": col.uid_bits,
        "peaks": col.peaks, "channels": col.channels, "angle_udeg": col.angle_udeg,
        "timestamp_us": col.timestamp_us, "records": recs})


def decode_column_construct(payload: bytes) -> ColumnResult:
    """Parse a COLUMN_RESULT payload through :data:`COLUMN_STRUCT` (baseline path)."""
    try:
        c = COLUMN_STRUCT.parse(payload)
    except cs.ConstructError as exc:
        raise FrameError(f"column: {exc}") from None
    if not 1 <= c.peaks <= MAX_PEAKS:
        raise FrameError(f"column: peaks {c.peaks}")
    rec = np.zeros(c.channels, dtype=record_dtype(c.peaks))
    for idx, r in enumerate(c.records):
        rec[idx] = (r.peak_lag, r.peak, list(r.neighbours), r.noise_count, r.noise_sum,
                  r.noise_sumsq, r.uid_neg, r.uid_zero, r.uid_observed, r.uid_match,
                  list(r.extra_lag), list(r.extra_peak), list(r.extra_neg),
                  list(r.extra_zero))
    rec.flags.writeable = False
    return ColumnResult(c.frame, c.column, c.angle_udeg, rec, c.uid_bits,
                        bool(c.flags & FLAG_CALIBRATION), c.timestamp_us)
