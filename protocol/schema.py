"""The wire's one declaration: payload fields (type, unit, range, meaning) and their codec.

A :class:`Field` is what the spec says about one payload field (C-like wire type, unit,
allowed range, meaning); a :class:`Layout`, the fields of one payload in wire order, is
also its codec (``struct``, little-endian, no padding). From them come the encoders'
checks (FieldError naming the field and its range), the strict decoders (FrameError
only), the tables of ``docs/protocol.md`` and the schema CRC. Field kinds and their bytes:

    int    one integer, ``u8`` .. ``u64`` or ``i16`` .. ``i64`` (two's complement)
    text   ``u8 len + UTF-8``: a byte count, then at most 255 bytes of UTF-8
    bytes  opaque bytes: a fixed number (nonces, MACs, ``max_items``), or all that remain
    array  integers (or small structs, given ``names``) after a ``u8``/``u16`` count, or
           filling the rest of the payload (``count`` ""), or as many as the product of
           earlier fields (``count`` "channels*columns")
    klv    key-length-value items to the end: ``u8 key, u16 length, value``
"""

from __future__ import annotations

import dataclasses
import functools
import struct
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from cdma_lidar.checks import check_int
from cdma_lidar.errors import FieldError, FrameError, out_of_range

__all__ = ["INTS", "Field", "Layout", "i", "nbytes", "text", "u", "wire", "wire_fields"]

#: C type -> (struct format, lowest, highest).
INTS = {"u8": ("B", 0, 2**8 - 1), "u16": ("H", 0, 2**16 - 1), "u32": ("I", 0, 2**32 - 1),
        "u64": ("Q", 0, 2**64 - 1), "i16": ("h", -(2**15), 2**15 - 1),
        "i32": ("i", -(2**31), 2**31 - 1), "i64": ("q", -(2**63), 2**63 - 1)}
_LIMITS = {fmt: (lo, hi) for fmt, lo, hi in INTS.values()}
_KLV = struct.Struct("<BH")


@dataclass(frozen=True)
class Field:
    """One payload field: what the spec says about it, and how it travels."""

    name: str
    ctype: str  # C-like wire type as the spec writes it, e.g. "u16", "u8 len + UTF-8"
    doc: str
    unit: str = ""
    lo: int | None = None  # range of an int, or of each integer of an array
    hi: int | None = None
    allowed: str = ""  # range text for the spec; derived from lo/hi when empty
    kind: str = "int"  # int | text | bytes | array | klv (module docstring)
    fmt: str = ""  # struct format of one array element ("H", "HB"); an int's: from ctype
    count: str = ""  # array count: its prefix's format ("B", "H"), "" (rest) or "a*b"
    names: tuple[str, ...] = ()  # an array of structs: the element's fields (dicts)
    min_items: int = 0
    max_items: int | None = None  # most array items; a bytes field's size (None: the rest)

    def __post_init__(self) -> None:
        if self.kind == "int":  # the struct format of its C type
            object.__setattr__(self, "fmt", INTS[self.ctype][0])

    @property
    def range_text(self) -> str:
        """The range column of the spec: ``allowed``, else ``lo..hi`` (``2^32-1``)."""
        return self.allowed or ("" if self.lo is None else f"{_num(self.lo)}..{_num(self.hi)}")  # type: ignore[arg-type]

    @property
    def size(self) -> int | None:
        """Bytes of the field, None when they vary."""
        return struct.calcsize("<" + self.fmt) if self.kind == "int" else \
            self.max_items if self.kind == "bytes" else None

    def check(self, path: str, value: Any) -> Any:
        """``value`` as it is packed; raises FieldError naming ``path`` and the range."""
        if self.kind == "int":
            return check_int(path, value, self.lo, self.hi, cls=FieldError)  # type: ignore[arg-type]
        if self.kind == "text" and (not isinstance(value, str) or len(value.encode()) > 255):
            raise out_of_range(path, "a string of at most 255 UTF-8 bytes", value, FieldError)
        if self.kind == "bytes" and (not isinstance(value, bytes | bytearray) or
                                     len(value) != (self.max_items or len(value))):
            raise out_of_range(path, f"{self.max_items or 'any number of'} bytes", value,
                               FieldError)
        if self.kind in ("text", "bytes"):
            return value
        if isinstance(value, str | dict) or not hasattr(value, "__iter__"):
            raise out_of_range(path, "a sequence", value, FieldError)
        items = value.ravel().tolist() if isinstance(value, np.ndarray) else list(value)
        if not self.min_items <= len(items) <= (self.max_items or len(items)):
            raise out_of_range(path, f"{self.min_items} to {self.max_items} items", len(items),
                               FieldError)
        try:
            if self.kind == "klv":
                for k, e in enumerate(items):
                    check_int(f"{path}[{k}].key", e["key"], 0, 255, cls=FieldError)
                    if not isinstance(e["value"], bytes | bytearray) or len(e["value"]) > 65535:
                        raise out_of_range(f"{path}[{k}].value", "at most 65535 bytes",
                                           e["value"], FieldError)
                return items
            if self.names:  # small structs: each a dict of the element's fields
                return [{n: check_int(f"{path}[{k}].{n}", e[n], *_LIMITS[fmt], cls=FieldError)
                         for n, fmt in zip(self.names, self.fmt, strict=True)}
                        for k, e in enumerate(items)]
        except (TypeError, KeyError, IndexError):
            raise out_of_range(path, "items with the fields " + ", ".join(
                self.names or ("key", "value")), value, FieldError) from None
        lo, hi = (self.lo, self.hi) if self.lo is not None else _LIMITS[self.fmt]
        if isinstance(value, np.ndarray) and value.dtype.kind in "iu" and \
                (not value.size or (lo <= value.min() and value.max() <= hi)):  # type: ignore[operator]
            return items  # a numpy array of integers in range: one check for all of them
        return [check_int(f"{path}[{k}]", v, lo, hi, cls=FieldError)  # type: ignore[arg-type]
                for k, v in enumerate(items)]


def _num(v: int) -> str:
    """Spec form of a bound: powers of two for big ones (2^32-1, -2^31)."""
    if v >= 1 << 17 and (v + 1) & v == 0:
        return f"2^{v.bit_length()}-1"
    if v <= -(1 << 17) and -v & (-v - 1) == 0:
        return f"-2^{(-v).bit_length() - 1}"
    return str(v)


class Layout:
    """The fields of one payload in wire order, and its codec: :meth:`encode` and
    :meth:`decode` check every value; :meth:`build` (``struct.error`` for a value its wire
    type cannot hold) and :meth:`parse` (FrameError) are their unchecked halves."""

    def __init__(self, *fields: Field) -> None:
        self.fields = fields

    def field(self, name: str) -> Field:
        """The field called ``name``."""
        return next(f for f in self.fields if f.name == name)

    def sizeof(self) -> int:
        """Bytes of a payload whose fields all have a fixed size."""
        return sum(f.size for f in self.fields)  # type: ignore[misc]

    def encode(self, values: dict[str, Any], what: str) -> bytes:
        """Payload bytes of ``values``; FieldError naming ``what.field`` (and its range) for a
        field missing, unknown or outside its range."""
        checked: dict[str, Any] = {}
        for f in self.fields:
            if f.name not in values:
                raise FieldError(f"{what}.{f.name} is required", field=f.name)
            checked[f.name] = v = f.check(f"{what}.{f.name}", values[f.name])
            if "*" in f.count and len(v) != (n := self._product(f, checked)):
                raise out_of_range(f"{what}.{f.name}", f"{n} items ({f.count})", len(v),
                                   FieldError)
        if extra := sorted(set(values) - set(checked)):
            raise out_of_range(f"{what}.{extra[0]}", f"a declared field of {what}",
                               "unknown field", FieldError)
        return self.build(checked)

    def decode(self, payload: bytes, what: str) -> dict[str, Any]:
        """Field values of ``payload``; FrameError (only) naming a field out of range."""
        out = self.parse(payload, what)
        for f in self.fields:
            if f.lo is not None:  # the ints, and the arrays declared with a range
                try:
                    f.check(f.name, out[f.name])
                except FieldError as exc:
                    raise FrameError(f"{what}: {exc}", field=f.name) from None
        return out

    def build(self, values: dict[str, Any]) -> bytes:
        """Payload bytes of ``values`` (one per field, by name), unchecked."""
        out = bytearray()
        for f in self.fields:
            v = values[f.name]
            if f.kind == "int":
                out += struct.pack("<" + f.fmt, v)
            elif f.kind in ("text", "bytes"):
                data = v.encode() if f.kind == "text" else v
                out += bytes([len(data)]) + data if f.kind == "text" else data
            elif f.kind == "klv":
                for e in v:
                    out += _KLV.pack(e["key"], len(e["value"])) + e["value"]
            else:
                if f.count in ("B", "H"):
                    out += struct.pack("<" + f.count, len(v))
                flat = [e[n] for e in v for n in f.names] if f.names else v
                out += struct.pack("<" + f.fmt * len(v), *flat)
        return bytes(out)

    def parse(self, payload: bytes, what: str = "payload") -> dict[str, Any]:
        """Field values of ``payload``, unchecked; FrameError naming ``what`` and the field
        that does not parse (short, not UTF-8, bytes left after the last field)."""
        out: dict[str, Any] = {}
        off, end, at = 0, len(payload), "end"
        try:
            for f in self.fields:
                at = f.name
                if f.kind == "int":
                    (out[f.name],) = struct.unpack_from("<" + f.fmt, payload, off)
                    off += f.size  # type: ignore[operator]
                elif f.kind in ("text", "bytes"):
                    n = payload[off] if f.kind == "text" else f.max_items or end - off
                    off += f.kind == "text"
                    data = bytes(payload[off:off + n])
                    if len(data) != n:
                        raise FrameError("short")
                    out[f.name] = data.decode() if f.kind == "text" else data
                    off += n
                elif f.kind == "klv":
                    out[f.name] = items = []
                    while off < end:
                        key, n = _KLV.unpack_from(payload, off)
                        off += _KLV.size + n
                        if off > end:
                            raise FrameError("short")
                        items.append({"key": key, "value": bytes(payload[off - n:off])})
                else:
                    out[f.name], off = self._array(f, payload, off, out)
            at = "end"
            if off != end:
                raise FrameError("trailing bytes")
        except (struct.error, ValueError, IndexError, FrameError) as exc:  # not UTF-8: ValueError
            why = exc if isinstance(exc, FrameError) else "short" if isinstance(
                exc, struct.error | IndexError) else type(exc).__name__
            raise FrameError(f"{what}: malformed payload at {at} ({why})",
                             field=None if at == "end" else at) from None
        return out

    @staticmethod
    def _product(f: Field, done: dict[str, Any]) -> int:
        """Items of an array whose count is the product of earlier fields."""
        return int(np.prod([done[name] for name in f.count.split("*")]))

    def _array(self, f: Field, payload: bytes, off: int, done: dict[str, Any]
               ) -> tuple[list, int]:
        size = struct.calcsize("<" + f.fmt)
        if f.count in ("B", "H"):
            (n,) = struct.unpack_from("<" + f.count, payload, off)
            off += struct.calcsize(f.count)
        elif f.count:
            n = self._product(f, done)
        else:  # the rest; a part item left over fails as trailing bytes
            n = (len(payload) - off) // size
        if off + n * size > len(payload):  # before building a format of n items
            raise FrameError("short")
        flat = struct.unpack_from("<" + f.fmt * n, payload, off)
        k = len(f.names)
        items = [dict(zip(f.names, flat[j:j + k], strict=True))
                 for j in range(0, n * k, k)] if k else list(flat)
        return items, off + n * size


# ---- declaring fields ----------------------------------------------------------------------
def u(name: str, bits: int, doc: str, unit: str = "", lo: int | None = None,
      hi: int | None = None, allowed: str = "", kind: str = "u") -> Field:
    """Little-endian integer of ``bits`` bits, unsigned (``kind`` "u") or two's complement
    ("i"), optionally limited to [lo, hi]."""
    _, nlo, nhi = INTS[f"{kind}{bits}"]
    return Field(name, f"{kind}{bits}", doc, unit, nlo if lo is None else lo,
                 nhi if hi is None else hi, allowed)


#: Signed two's-complement little-endian integer field: :func:`u` with ``kind`` "i".
i = functools.partial(u, kind="i")


def text(name: str, doc: str) -> Field:
    """UTF-8 string with a u8 byte-length prefix (at most 255 bytes)."""
    return Field(name, "u8 len + UTF-8", doc, allowed="0..255 bytes", kind="text")


def nbytes(name: str, size: int, doc: str) -> Field:
    """Fixed-size opaque bytes (nonces, MACs): ``size`` bytes, any values."""
    return Field(name, f"u8 x {size}", doc, allowed=f"{size} bytes", kind="bytes",
                 max_items=size)


def wire(default: Any, make: Callable[..., Field], *args: Any, **kw: Any) -> Any:
    """A dataclass field that is also the payload field ``make(name, *args, **kw)`` (``u``,
    ``text``, ...) of the same name; ``default`` MISSING: required."""
    return dataclasses.field(default=default,
                             metadata={"wire": lambda name: make(name, *args, **kw)})


def wire_fields(cls: type) -> list[Field]:
    """The payload fields of a dataclass declared with :func:`wire`, in field order."""
    return [f.metadata["wire"](f.name) for f in dataclasses.fields(cls)]
