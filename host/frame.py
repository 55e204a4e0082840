"""One frame of receiver results, gathered column by column into (channel, column) arrays.

The device sends one ``ColumnResult`` per grating column, holding for each of its K
channels every field of the column record (:mod:`cdma_lidar.column_record`: every
``ReceiverOutput`` field except ``corr``). The host keeps a frame as a
:class:`FrameData`: the same fields stacked into arrays whose first two axes are
``(K channels, C columns)``, plus a ``done`` mask that says
which columns have arrived. That makes every later step (ranging, UID filtering,
point-cloud assembly) a vectorised numpy expression over the whole frame, and it is
also what a resumable partial scan saves to disk (:meth:`FrameData.to_arrays`).

Units: lags in samples (``0 .. N*S - 1``), correlator outputs in integer correlator
units (``out`` of the receive chain), grating angles in degrees.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field, fields
from typing import Any

import numpy as np
from numpy.typing import NDArray

from cdma_lidar.column_record import RECORD
from cdma_lidar.errors import ConfigError, out_of_range
from cdma_lidar.protocol.columns import ColumnResult

__all__ = ["SUMSQ_UNKNOWN", "FrameData", "clamp_sumsq"]


#: ``noise_sumsq`` at or above this (int64's maximum) means "the noise floor is unknown":
#: the exact sum passed the host's int64 word (it can need up to 88 bits, and travels
#: saturated to 2^64 - 1 on the wire, docs/firmware.md section 3). Such a pixel has no SNR.
SUMSQ_UNKNOWN = np.iinfo(np.int64).max


def clamp_sumsq(values: Any) -> NDArray[np.int64]:
    """``noise_sumsq`` values as int64, anything above :data:`SUMSQ_UNKNOWN` clamped to it."""
    arr = np.asarray(values)
    if arr.dtype == np.int64:
        return arr
    if arr.dtype == np.uint64:  # the wire's u64
        return np.minimum(arr, np.uint64(SUMSQ_UNKNOWN)).astype(np.int64)
    return np.array([min(int(v), SUMSQ_UNKNOWN) for v in arr.ravel()],
                    dtype=np.int64).reshape(arr.shape)


@dataclass
class FrameData:
    """Receiver results of one frame as ``(K, C, ...)`` arrays (K channels, C columns).

    Its fields are one array per field of the column record, in its order
    (:data:`cdma_lidar.column_record.RECORD`: the ``ReceiverOutput`` shapes with the
    column axis C added; a test checks the two lists agree), then:

    angle_deg (C,) float64: grating rotation of each column (deg), NaN until it arrives.
    done (C,) bool: True for columns that have arrived.
    timestamp_us (C,) int64: the device clock when each column was measured (us, the
    wire's u32 that wraps every 71.6 min; 0 until it arrives).
    frame: frame number.
    """

    #: (K, C) [samples] lag of the strongest peak; -1: no eligible lag
    peak_lag: NDArray[np.int64]
    #: (K, C) [out LSB] scaled correlation out at peak_lag
    peak: NDArray[np.int64]
    #: (K, C, 2) [out LSB] out at peak_lag-1, peak_lag+1
    neighbours: NDArray[np.int64]
    #: (K, C) [lags] gate lags in the noise floor
    noise_count: NDArray[np.int64]
    #: (K, C) [out LSB] sum of out over the noise lags
    noise_sum: NDArray[np.int64]
    #: (K, C) [out LSB^2] sum of out^2 over the noise lags
    noise_sumsq: NDArray[np.int64]
    #: (K, C, n) sign of each period's raw correlation at peak_lag
    uid_signs: NDArray[np.int8]
    #: (K, C) observed UID: bit p set where period p's sign is -1
    uid_observed: NDArray[np.int64]
    #: (K, C) no sign is 0 and uid_observed == uid
    uid_match: NDArray[np.bool_]
    #: (K, C) peak is at a rail of out_bits (it may have been clipped, so peak_lag can sit early
    #: on a plateau)
    saturated: NDArray[np.bool_]
    #: (K, C, P-1) [samples] lags of peaks 2..P; -1: no such peak
    extra_lag: NDArray[np.int64]
    #: (K, C, P-1) [out LSB] out at peaks 2..P
    extra_peak: NDArray[np.int64]
    #: (K, C, P-1, n) signs of each period at peaks 2..P
    extra_signs: NDArray[np.int8]
    angle_deg: NDArray[np.float64]
    done: NDArray[np.bool_]
    timestamp_us: NDArray[np.int64] = field(default_factory=lambda: np.zeros(0, np.int64))
    frame: int = 0

    def __post_init__(self) -> None:
        if self.timestamp_us.shape != self.done.shape:
            self.timestamp_us = np.zeros(self.done.shape, np.int64)

    @classmethod
    def empty(cls, channels: int, columns: int, uid_bits: int = 1, peaks: int = 1,
              frame: int = 0) -> FrameData:
        """A frame with no column yet: zeros everywhere, ``done`` all False."""
        if channels < 1:
            raise out_of_range("channels", "at least 1", channels)
        if columns < 1:
            raise out_of_range("columns", "at least 1", columns)
        if uid_bits < 1:
            raise out_of_range("uid_bits", "at least 1", uid_bits)
        if peaks < 1:
            raise out_of_range("peaks", "at least 1", peaks)
        arrays = {f.name: np.zeros((channels, columns, *f.shape(uid_bits, peaks)), dtype=f.dtype)
                  for f in RECORD}
        return cls(**arrays, angle_deg=np.full(columns, np.nan), done=np.zeros(columns, bool),
                   frame=frame)

    @property
    def shape(self) -> tuple[int, int]:
        """(K channels, C columns)."""
        return self.peak_lag.shape  # type: ignore[return-value]

    @property
    def uid_bits(self) -> int:
        """Number of UID periods n."""
        return int(self.uid_signs.shape[-1])

    @property
    def peaks(self) -> int:
        """Number of peaks reported per channel (primary plus extras)."""
        return int(self.extra_lag.shape[-1]) + 1

    def set_column(self, index: int, result: Any, angle_deg: float | None = None) -> None:
        """Store one column result (any object or mapping with the ReceiverOutput field names).

        ``index`` is the position in this frame (0 .. C-1). ``angle_deg`` defaults to the
        result's ``angle_deg`` attribute or key. A ``ColumnResult`` is stored as it is:
        its header and every value were checked against the session where the wire's
        column was decoded (:class:`~cdma_lidar.protocol.trust.ColumnChecker`); other
        results must carry every field in this frame's shapes.
        """
        c = self.shape[1]
        if not 0 <= index < c:
            raise out_of_range("column", f"from 0 to {c - 1}", index)
        get = result.get if isinstance(result, Mapping) else (
            lambda name, default=None: getattr(result, name, default))
        trusted = isinstance(result, ColumnResult)
        for f in RECORD:
            name = f.name
            value = get(name)
            if trusted:
                if not (f.per_extra_peak and self.peaks == 1):
                    getattr(self, name)[:, index] = \
                        clamp_sumsq(value) if name == "noise_sumsq" else value
                continue
            if value is None:
                if f.per_extra_peak and self.peaks == 1:
                    continue
                raise ConfigError(f"column result lacks field {name!r}", field=name)
            arr = np.asarray(value)
            target = getattr(self, name)
            want = target.shape[:1] + target.shape[2:]
            if arr.size == 0 and 0 in want:
                continue
            if arr.shape != want:
                raise out_of_range(f"{name} shape", f"{want}", arr.shape)
            if name == "noise_sumsq":
                arr = clamp_sumsq(arr)
            target[:, index] = arr
        ts = get("timestamp_us")
        if ts is not None:
            self.timestamp_us[index] = int(ts)
        if angle_deg is None:
            angle_deg = get("angle_deg")
        if angle_deg is not None:
            self.angle_deg[index] = float(angle_deg)
        self.done[index] = True

    def to_arrays(self) -> dict[str, NDArray]:
        """Every field as a plain array (for ``np.savez``); inverse of :meth:`from_arrays`."""
        out = {f.name: np.asarray(getattr(self, f.name)) for f in fields(self)}
        return out

    @classmethod
    def from_arrays(cls, arrays: Mapping[str, Any]) -> FrameData:
        """Rebuild a frame from :meth:`to_arrays` output (e.g. an opened ``.npz``)."""
        optional = ("timestamp_us",)  # partial scans saved before it existed lack it
        missing = [f.name for f in fields(cls) if f.name not in arrays
                   and f.name not in optional]
        if missing:
            raise ConfigError(f"frame data lacks {', '.join(missing)}", field=missing[0])
        kw = {f.name: np.array(arrays[f.name]) for f in fields(cls) if f.name in arrays}
        kw["frame"] = int(kw["frame"])
        return cls(**kw)

    @classmethod
    def from_columns(cls, results: Iterable[Any], channels: int, columns: int,
                     first_column: int = 0, uid_bits: int = 1, peaks: int = 1,
                     frame: int = 0) -> FrameData:
        """Assemble a frame from column results that carry a ``column`` index."""
        data = cls.empty(channels, columns, uid_bits, peaks, frame)
        for res in results:
            col = res["column"] if isinstance(res, Mapping) else res.column
            data.set_column(int(col) - first_column, res)
        return data
