"""The per-channel column record, declared once.

For every channel of a grating column the receive chain reports the same dozen
integers; the receiver model returns them (``ReceiverOutput``), the wire carries
them (a COLUMN_RESULT channel record), the host stacks them into frames
(``FrameData``) and the RTL co-simulation decodes them. :data:`RECORD` is the one
declaration all of those views are derived from or checked against (the classes write
their fields out, and tests compare them with :data:`FIELD_NAMES`): per field its name, logical
dtype and trailing shape (after the channel axis), unit, meaning, allowed range
and how it travels on the wire.

Trailing axes are symbols resolved by :meth:`RecordField.shape`: ``2`` (the two
neighbours), ``"n"`` (UID periods, ``uid_bits``) and ``"P-1"`` (extra peaks).

Wire encodings (:data:`Encoding`), every wire integer little-endian, packed:

* ``int``   the integer itself in the wire type (u32, i32, i64, u64, u8);
* ``lag``   a lag in samples; the receiver's -1 (no peak) travels as :data:`NO_PEAK`;
* ``flag``  a bool as u8 0 or 1;
* ``signs`` signs in {-1, 0, +1} along the ``n`` axis travel as two u8 masks, the
  first with bit p set where the sign is -1, the second where it is 0 (neither: +1).

The wire layout is the record's wire fields in order (:data:`WIRE_FIELDS`); fields
with a ``P-1`` axis repeat per extra peak, so a record is
``fixed_size + extra_size * (P - 1)`` bytes (:func:`record_size`).
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass
from typing import Literal

import numpy as np

__all__ = [
    "FIELD_NAMES",
    "NO_PEAK",
    "RECORD",
    "RECORD_EXTRA_SIZE",
    "RECORD_FIXED_SIZE",
    "WIRE_FIELDS",
    "Encoding",
    "RecordField",
    "WireField",
    "WireLayout",
    "record_field",
    "record_size",
    "wire_layout",
]

#: Wire value of a lag where the receiver found no eligible peak (it reports lag -1).
NO_PEAK = 0xFFFF_FFFF

Encoding = Literal["int", "lag", "flag", "signs"]
Axis = int | Literal["n", "P-1"]

# wire type -> (numpy type, bytes, lowest value, highest value)
_WIRE_TYPES: dict[str, tuple[str, int, int, int]] = {
    "u8": ("u1", 1, 0, 2**8 - 1),
    "u32": ("<u4", 4, 0, 2**32 - 1),
    "u64": ("<u8", 8, 0, 2**64 - 1),
    "i32": ("<i4", 4, -(2**31), 2**31 - 1),
    "i64": ("<i8", 8, -(2**63), 2**63 - 1),
}


def _resolve(axes: tuple[Axis, ...], uid_bits: int, peaks: int) -> tuple[int, ...]:
    sizes = {"n": uid_bits, "P-1": peaks - 1}
    return tuple(a if isinstance(a, int) else sizes[a] for a in axes)


@dataclass(frozen=True)
class WireField:
    """One field of the COLUMN_RESULT channel record as it travels.

    ``ctype`` is the element type (u8, u32, u64, i32, i64); ``axes`` its repetition
    (``()`` one value, ``(2,)``, ``("P-1",)``). ``allowed`` is the range the spec
    states; empty means the whole range of the type.
    """

    name: str
    ctype: str
    axes: tuple[Axis, ...]
    unit: str
    doc: str
    allowed: str = ""

    @property
    def numpy_type(self) -> str:
        """numpy type string of one element (``"<u4"``, ``"u1"``, ...)."""
        return _WIRE_TYPES[self.ctype][0]

    @property
    def item_size(self) -> int:
        """Bytes of one element."""
        return _WIRE_TYPES[self.ctype][1]

    @property
    def limits(self) -> tuple[int, int]:
        """(lowest, highest) integer the wire type holds."""
        return _WIRE_TYPES[self.ctype][2:]

    @property
    def spec_type(self) -> str:
        """Type as the spec writes it: ``u32``, ``i32[2]``, ``u8[P-1]``."""
        return self.ctype + "".join(f"[{a}]" for a in self.axes)

    def shape(self, peaks: int) -> tuple[int, ...]:
        """Element shape for ``peaks`` peaks per channel."""
        return _resolve(self.axes, 0, peaks)

    @property
    def fixed_size(self) -> int:
        """Bytes that do not depend on P (0 for a field repeated per extra peak)."""
        return 0 if "P-1" in self.axes else self.item_size * int(np.prod(self.shape(1)))

    @property
    def extra_size(self) -> int:
        """Bytes per extra peak (P - 1)."""
        if "P-1" not in self.axes:
            return 0
        return self.item_size * int(np.prod(self.shape(2)))


@dataclass(frozen=True)
class RecordField:
    """One reported field of a channel: what the receiver means and how the wire carries it.

    ``dtype`` and ``shape`` are the logical form (receiver model, host frame arrays,
    per channel); ``wire`` the one field (two for ``signs``) it becomes on the wire.
    """

    name: str
    dtype: type[np.generic]
    axes: tuple[Axis, ...]
    unit: str
    doc: str
    allowed: str
    encoding: Encoding
    wire: tuple[WireField, ...]

    def shape(self, uid_bits: int, peaks: int) -> tuple[int, ...]:
        """Trailing shape (after the channel axis) for n = ``uid_bits`` and P = ``peaks``."""
        return _resolve(self.axes, uid_bits, peaks)

    @property
    def axes_text(self) -> str:
        """Trailing axes as text: ``""``, ``"2"``, ``"n"``, ``"P-1, n"``."""
        return ", ".join(str(a) for a in self.axes)

    @property
    def per_extra_peak(self) -> bool:
        """True for fields that describe peaks 2..P (one entry per extra peak)."""
        return "P-1" in self.axes


def _field(name: str, dtype: type[np.generic], axes: tuple[Axis, ...], unit: str, doc: str,
           allowed: str, ctype: str, *, encoding: Encoding = "int", wire_doc: str = "",
           wire_allowed: str | None = None) -> RecordField:
    """A field that travels as one wire field of the same name and axes."""
    wire = WireField(name, ctype, axes, unit, wire_doc or doc,
                     allowed if wire_allowed is None else wire_allowed)
    return RecordField(name, dtype, axes, unit, doc, allowed, encoding, (wire,))


def _signs(name: str, axes: tuple[Axis, ...], doc: str, neg: tuple[str, str],
           zero: tuple[str, str]) -> RecordField:
    """Signs along the last (``n``) axis; they travel as a -1 mask and a 0 mask."""
    mask_axes = axes[:-1]
    wire = tuple(WireField(w_name, "u8", mask_axes, "mask", w_doc, "bits 0..n-1")
                 for w_name, w_doc in (neg, zero))
    return RecordField(name, np.int8, axes, "", doc, "-1, 0, +1", "signs", wire)


_NO_PEAK_TEXT = f"0x{NO_PEAK:08X}"

#: The channel record, in wire order. ``corr`` (the whole gated trace) is receiver-only.
RECORD: tuple[RecordField, ...] = (
    _field("peak_lag", np.int64, (), "samples", "lag of the strongest peak; -1: no eligible lag",
           "0..N*S-1 or -1", "u32", encoding="lag",
           wire_doc=f"lag of the strongest peak; {_NO_PEAK_TEXT}: no eligible lag",
           wire_allowed=f"0..N*S-1 or {_NO_PEAK_TEXT}"),
    _field("peak", np.int64, (), "out LSB", "scaled correlation out at peak_lag",
           "signed out_bits", "i32"),
    _field("neighbours", np.int64, (2,), "out LSB", "out at peak_lag-1, peak_lag+1",
           "signed out_bits", "i32"),
    _field("noise_count", np.int64, (), "lags", "gate lags in the noise floor", "0..gate_len",
           "u32"),
    _field("noise_sum", np.int64, (), "out LSB", "sum of out over the noise lags", "", "i64"),
    _field("noise_sumsq", np.int64, (), "out LSB^2", "sum of out^2 over the noise lags", "",
           "u64"),
    _signs("uid_signs", ("n",), "sign of each period's raw correlation at peak_lag",
           ("uid_neg", "bit p: period p's sign at the peak is -1"),
           ("uid_zero", "bit p: period p's sign at the peak is 0")),
    _field("uid_observed", np.int64, (), "", "observed UID: bit p set where period p's sign is -1",
           "0..2^n-1", "u8"),
    _field("uid_match", np.bool_, (), "", "no sign is 0 and uid_observed == uid", "False, True",
           "u8", encoding="flag", wire_doc="1 when no sign is 0 and uid_observed == uid",
           wire_allowed="0..1"),
    _field("saturated", np.bool_, (), "", "peak is at a rail of out_bits (it may have been "
           "clipped, so peak_lag can sit early on a plateau)", "False, True", "u8",
           encoding="flag", wire_doc="1 when peak is +-(2^(out_bits-1)) or 2^(out_bits-1)-1 "
           "(a clipped peak: peak_lag may be early)", wire_allowed="0..1"),
    _field("extra_lag", np.int64, ("P-1",), "samples", "lags of peaks 2..P; -1: no such peak",
           "0..N*S-1 or -1", "u32", encoding="lag",
           wire_doc=f"lags of peaks 2..P; {_NO_PEAK_TEXT}: no such peak",
           wire_allowed=f"0..N*S-1 or {_NO_PEAK_TEXT}"),
    _field("extra_peak", np.int64, ("P-1",), "out LSB", "out at peaks 2..P", "signed out_bits",
           "i32"),
    _signs("extra_signs", ("P-1", "n"), "signs of each period at peaks 2..P",
           ("extra_neg", "sign masks (-1) of peaks 2..P"),
           ("extra_zero", "sign masks (0) of peaks 2..P")),
)

#: Field names in record order.
FIELD_NAMES: tuple[str, ...] = tuple(f.name for f in RECORD)

#: The wire fields of one channel record, in wire order.
WIRE_FIELDS: tuple[WireField, ...] = tuple(w for f in RECORD for w in f.wire)

#: Bytes of a channel record that do not depend on P (41).
RECORD_FIXED_SIZE: int = sum(w.fixed_size for w in WIRE_FIELDS)
#: Bytes a channel record grows by per extra peak (10).
RECORD_EXTRA_SIZE: int = sum(w.extra_size for w in WIRE_FIELDS)


def record_size(peaks: int) -> int:
    """Bytes of one channel record with P = ``peaks`` peaks: ``41 + 10 (P - 1)``."""
    return RECORD_FIXED_SIZE + RECORD_EXTRA_SIZE * (peaks - 1)


_BY_NAME = {f.name: f for f in RECORD}

# The packed layout puts every per-extra-peak field after the fixed ones (wire_layout).
if any(a.extra_size and not b.extra_size for a, b in itertools.pairwise(WIRE_FIELDS)):
    raise RuntimeError("column record: a fixed-size wire field follows a per-peak one")


def record_field(name: str) -> RecordField:
    """The declaration of field ``name`` (KeyError for names not in the record)."""
    return _BY_NAME[name]


@dataclass(frozen=True)
class WireLayout:
    """Where a wire field sits: ``offset + offset_per_extra * (P - 1)`` bytes into a record."""

    wire: WireField
    offset: int
    offset_per_extra: int


def wire_layout() -> tuple[WireLayout, ...]:
    """Offsets of every wire field of a channel record, in terms of P."""
    out, off, extra = [], 0, 0
    for w in WIRE_FIELDS:
        if w.extra_size:
            out.append(WireLayout(w, RECORD_FIXED_SIZE, extra))
            extra += w.extra_size
        else:
            out.append(WireLayout(w, off, 0))
            off += w.fixed_size
    return tuple(out)
