"""Field declarations shared by every payload: a construct subcon plus what the spec says.

:func:`u`, :func:`i`, :func:`text`, :func:`array` and :func:`blob` each return a
named construct field (``"name" / subcon * "doc"``) with a :class:`FieldMeta`
attached as ``.meta``: its C-like type, unit, allowed range and description. The
encoders' range checks, the strict decoders and the tables of ``docs/protocol.md``
(:mod:`cdma_lidar.protocol.spec`) all read that one declaration.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import construct as cs

__all__ = ["FieldMeta", "array", "blob", "i", "nbytes", "text", "u", "wire", "wire_fields"]


@dataclass(frozen=True)
class FieldMeta:
    """What the spec says about one field."""

    ctype: str  # C-like wire type, e.g. "u16", "i32", "u8 len + UTF-8"
    unit: str
    lo: int | None
    hi: int | None
    doc: str
    kind: str = "int"  # int | text | array | blob
    max_items: int | None = None
    allowed: str = ""  # range text for the spec; derived from lo/hi when empty
    min_items: int = 0

    @property
    def range_text(self) -> str:
        if self.allowed:
            return self.allowed
        if self.lo is None:
            return ""
        return f"{_num(self.lo)}..{_num(self.hi)}"


def _num(v: int | None) -> str:
    """Spec form of a bound: powers of two for big ones (2^32-1, -2^31)."""
    if v is None:
        return ""
    if abs(v) < 1 << 17:
        return str(v)
    if v > 0 and (v + 1) & v == 0:
        return f"2^{(v + 1).bit_length() - 1}-1"
    if v < 0 and -v & (-v - 1) == 0:
        return f"-2^{(-v).bit_length() - 1}"
    return str(v)


_INT = {  # (construct subcon, C type, natural lo, natural hi)
    ("u", 8): (cs.Int8ul, "u8", 0, 2**8 - 1),
    ("u", 16): (cs.Int16ul, "u16", 0, 2**16 - 1),
    ("u", 32): (cs.Int32ul, "u32", 0, 2**32 - 1),
    ("u", 64): (cs.Int64ul, "u64", 0, 2**64 - 1),
    ("i", 16): (cs.Int16sl, "i16", -(2**15), 2**15 - 1),
    ("i", 32): (cs.Int32sl, "i32", -(2**31), 2**31 - 1),
    ("i", 64): (cs.Int64sl, "i64", -(2**63), 2**63 - 1),
}


def _named(name: str, sub: cs.Construct, meta: FieldMeta) -> cs.Renamed:
    r = name / sub * meta.doc
    r.meta = meta  # read by the validator and by cdma_lidar.protocol.spec
    return r


def u(name: str, bits: int, doc: str, unit: str = "", lo: int | None = None,
      hi: int | None = None, allowed: str = "", kind: str = "u") -> cs.Renamed:
    """Little-endian integer field of ``bits`` bits, unsigned (``kind`` "u") or two's
    complement ("i"), optionally limited to [lo, hi]."""
    sub, ctype, nlo, nhi = _INT[(kind, bits)]
    return _named(name, sub, FieldMeta(ctype, unit, nlo if lo is None else lo,
                                       nhi if hi is None else hi, doc, allowed=allowed))


def i(name: str, bits: int, doc: str, unit: str = "", lo: int | None = None,
      hi: int | None = None, allowed: str = "") -> cs.Renamed:
    """Signed two's-complement little-endian integer field."""
    return u(name, bits, doc, unit, lo, hi, allowed, kind="i")


def text(name: str, doc: str) -> cs.Renamed:
    """UTF-8 string with a u8 byte-length prefix (at most 255 bytes)."""
    return _named(name, cs.PascalString(cs.Int8ul, "utf8"),
                  FieldMeta("u8 len + UTF-8", "", None, None, doc, kind="text",
                            allowed="0..255 bytes"))


def array(name: str, count_bits: int, elem: str, elem_bits: int, doc: str, unit: str = "",
          lo: int | None = None, hi: int | None = None, max_items: int | None = None,
          allowed: str = "", min_items: int = 0) -> cs.Renamed:
    """Count-prefixed array of integers: ``u<count_bits>`` count, then the elements."""
    csub, cctype, _, cmax = _INT[("u", count_bits)]
    esub, ectype, nlo, nhi = _INT[(elem, elem_bits)]
    return _named(name, cs.PrefixedArray(csub, esub),
                  FieldMeta(f"{cctype} n + n x {ectype}", unit, nlo if lo is None else lo,
                            nhi if hi is None else hi, doc, kind="array",
                            max_items=cmax if max_items is None else max_items,
                            allowed=allowed, min_items=min_items))


def blob(name: str, sub: cs.Construct, ctype: str, doc: str, unit: str = "",
         allowed: str = "") -> cs.Renamed:
    """Any other construct (validated by construct itself)."""
    return _named(name, sub, FieldMeta(ctype, unit, None, None, doc, kind="blob",
                                       allowed=allowed))


def nbytes(name: str, size: int, doc: str) -> cs.Renamed:
    """Fixed-size opaque bytes (nonces, MACs): ``size`` bytes, any values."""
    return _named(name, cs.Bytes(size), FieldMeta(f"u8 x {size}", "", None, None, doc,
                                                  kind="bytes", max_items=size,
                                                  allowed=f"{size} bytes"))


def wire(default: Any, make: Callable[..., cs.Renamed], *args: Any, **kw: Any) -> Any:
    """A dataclass field that is a payload field too: ``make(name, *args, **kw)`` (``u``,
    ``text``, ...) named as the dataclass field; ``default`` MISSING: required."""
    return dataclasses.field(default=default, metadata={"wire": (make, args, kw)})


def wire_fields(cls: type) -> list[cs.Renamed]:
    """The payload fields of a dataclass declared with :func:`wire`, in field order."""
    return [f.metadata["wire"][0](f.name, *f.metadata["wire"][1], **f.metadata["wire"][2])
            for f in dataclasses.fields(cls)]
