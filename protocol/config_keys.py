"""CONFIG keys: the key-length-value set carried by CONFIG_SET and CONFIG.

Each key is declared once as a :class:`ConfigKey` (id, name, value type, unit, range and,
where the host value is not the wire value, the mapping: exponent tuples <-> polynomial
masks, names <-> codes, window pairs <-> structs) for :func:`encode_config`, the strict
:func:`decode_config`, the spec's table and the schema CRC. Bit 7 of a key id is the
*optional* flag (:data:`CONFIG_OPTIONAL`): a device ignores an unknown optional key and
refuses another unknown one with NAK UNKNOWN_KEY naming it.
"""

from __future__ import annotations

import struct
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from cdma_lidar.checks import is_int
from cdma_lidar.errors import FieldError, FrameError, out_of_range
from cdma_lidar.poly import mask_to_poly, tap_mask
from cdma_lidar.protocol.schema import Field, Layout, u
from cdma_lidar.rounding import ROUNDING_MODES

__all__ = ["CONFIG_KEYS", "CONFIG_OPTIONAL", "MODES", "ConfigKey", "DecodedConfig", "config_key",
           "decode_config", "encode_config"]

#: Bit 7 of a key id: a device that does not know this key ignores it.
CONFIG_OPTIONAL = 0x80

#: Measurement mode names; the index of each is its wire code (key ``mode``).
MODES: tuple[str, ...] = ("ranging", "calibration")


# ---- host value <-> wire value -------------------------------------------------------------
def _poly_to_wire(poly: Sequence[int] | int) -> int:
    """Exponent tuple ``(11, 2)`` (x^11 + x^2 + 1), or a wire mask, to the wire mask: the
    tap mask of :mod:`cdma_lidar.poly`, bit e - 1 the x^e term (e = 1..32), x^0 implied
    ((11, 2) is 0x402). FieldError: what it takes."""
    if is_int(poly):
        mask = int(poly)  # type: ignore[arg-type]
    else:
        try:
            exps = [int(e) for e in poly]  # type: ignore[union-attr]
        except (TypeError, ValueError):
            raise FieldError("a tuple of exponents like (11, 2)") from None
        if len(set(exps)) != len(exps) or any(not 1 <= e <= 32 for e in exps):
            raise FieldError("distinct exponents from 1 to 32")
        mask = tap_mask(exps)
    if not 0 < mask < 2**32:
        raise FieldError("a nonzero mask of bits 0..31 (bit e - 1: the x^e term)")
    return mask


def _wire_to_poly(mask: int) -> tuple[int, ...]:
    """Exponent tuple (highest first) of a wire mask (bit e - 1: the x^e term)."""
    return mask_to_poly(int(mask) << 1)


@dataclass(frozen=True)
class ConfigKey:
    """One key of the CONFIG key-length-value set."""

    id: int
    name: str
    ctype: str  # value encoding (fills the whole length): a key of _SUBS
    unit: str
    allowed: str
    doc: str
    lo: int | None = None
    hi: int | None = None
    read_only: bool = False
    to_wire: Callable[[Any], Any] = lambda v: v  # host -> wire value; FieldError(what it takes)
    from_wire: Callable[[Any], Any] = lambda v: v

    @property
    def sub(self) -> Layout:
        """The layout of the value (one field ``v`` that fills the item's whole length)."""
        return _SUBS[self.ctype]

    def outside(self, w: Any) -> Any:
        """The first wire value of ``w`` outside lo..hi (None: all within, or no range)."""
        if self.lo is None or self.hi is None:
            return None
        return next((v for v in (w if isinstance(w, list | tuple | np.ndarray) else [w])
                     if not is_int(v) or not self.lo <= int(v) <= self.hi), None)

    def encode(self, value: Any, *, check: bool = True) -> bytes:
        """Value bytes; raises FieldError naming the key. ``check``: hold the value to the
        key's range (the host's one check of what it sends); False for a value its model
        already checked (the device's own configuration): only what the wire cannot hold fails."""
        try:
            w = self.to_wire(value)
            if check and self.outside(w) is not None:
                # Not check_int: the message gives the device's limit and the wire range.
                each = "each " if isinstance(w, list | tuple | np.ndarray) else ""
                raise FieldError(f"{self.allowed} ({each}{self.lo}..{self.hi} on the wire)")
            return self.sub.build({"v": w})
        except FieldError as exc:  # what to_wire takes, or the range
            raise out_of_range(self.name, str(exc), value, FieldError) from None
        except (struct.error, TypeError, ValueError, KeyError) as exc:
            raise out_of_range(self.name, self.allowed, value, FieldError) from exc

    def decode(self, data: bytes) -> Any:
        """Python value of the wire bytes; FrameError if malformed or out of range (the
        receiving side's one check of the wire range)."""
        try:
            w = self.sub.parse(data, self.name)["v"]
        except FrameError:
            raise FrameError(f"{self.name}: malformed value ({len(data)} bytes)",
                             field=self.name) from None
        if (bad := self.outside(w)) is not None:
            raise FrameError(f"{self.name}: {bad} not in {self.lo}..{self.hi}", field=self.name)
        return self.from_wire(w)


def _enum_key(kid: int, key: str, names: tuple[str, ...], doc: str) -> ConfigKey:
    """A u8 key whose wire code is the index of its name in ``names`` (spec range text:
    ``0 truncate, 1 half_up, 2 convergent``)."""
    def to_wire(v: Any) -> int:  # a name, or its code as it is
        if isinstance(v, str) and v not in names:
            raise FieldError("one of " + ", ".join(names))
        return names.index(v) if isinstance(v, str) else v

    return ConfigKey(kid, key, "u8", "", ", ".join(f"{c} {n}" for c, n in enumerate(names)),
                     doc, 0, len(names) - 1, to_wire=to_wire, from_wire=names.__getitem__)


#: Each value encoding (ConfigKey.ctype) as a layout of one field ``v``.
_SUBS = {**{f"u{bits}": Layout(u("v", bits, "")) for bits in (8, 16, 32)},
         "u16 x K": Layout(Field("v", "u16 x K", "", kind="array", fmt="H")),
         "(u32 start, u32 len) x n": Layout(Field("v", "", "", kind="array", fmt="II",
                                                  names=("start", "length")))}


def _windows_to_wire(v: Any) -> list[dict[str, int]]:
    try:
        pairs = [(int(s), int(n)) for s, n in v]
    except (TypeError, ValueError):
        raise FieldError("a list of (start, length) pairs") from None
    if any(not 0 <= s < 2**32 or not 0 <= n < 2**32 for s, n in pairs):
        raise FieldError("u32 starts and lengths (samples)")
    return [{"start": s, "length": n} for s, n in pairs]


CONFIG_KEYS: tuple[ConfigKey, ...] = (
    ConfigKey(1, "poly_u", "u32", "", "mask, degree 2..max_degree",
              "first Gold polynomial: bit e - 1 set = x^e term (e = 1..32), x^0 implied "
              "(host: exponent tuple, highest first)", to_wire=_poly_to_wire,
              from_wire=_wire_to_poly),
    ConfigKey(2, "poly_v", "u32", "", "mask, same degree as poly_u",
              "second Gold polynomial, same encoding", to_wire=_poly_to_wire,
              from_wire=_wire_to_poly),
    ConfigKey(3, "code_index", "u16 x K", "", "0..2^m (N+1), K items",
              "Gold family member of each channel", 0, 65535,
              to_wire=list, from_wire=tuple),
    ConfigKey(4, "uid_bits", "u8", "code periods", "1..max_uid_bits", "UID length n", 1, 8),
    ConfigKey(5, "uid", "u8", "", "0..2^uid_bits-1",
              "this device's UID (bit p = polarity of period p)", 0, 255),
    ConfigKey(6, "samples_per_chip", "u16", "samples/chip", "spc_min..spc_max",
              "ADC samples per chip S", 1, 65535),
    ConfigKey(7, "averages", "u32", "repetitions", "1..max_averages",
              "coherently summed code repetitions R", 1, 2**32 - 1),
    ConfigKey(8, "adc_bits", "u8", "bits", "8..16, read-only", "ADC resolution", 8, 16,
              read_only=True),
    ConfigKey(9, "gate_start", "u32", "samples", "0..N*S-1", "first lag of the gate", 0,
              2**32 - 1),
    ConfigKey(10, "gate_len", "u32", "samples", "1..min(N*S, max_gate_len)",
              "lags in the gate", 1, 2**32 - 1),
    ConfigKey(11, "peak_exclude", "u32", "samples", "0..N*S",
              "W: peaks at least W+1 lags apart; noise excludes |j - j_peak| <= W",
              0, 2**32 - 1),
    ConfigKey(12, "ghost_windows", "(u32 start, u32 len) x n", "samples", "lags mod N*S",
              "absolute lags (start, start+len-1, mod N*S) ignored by peak search and noise floor",
              to_wire=_windows_to_wire,
              from_wire=lambda w: tuple((e["start"], e["length"]) for e in w)),
    ConfigKey(13, "out_shift", "u8", "bits", "0..63", "out = round(raw / 2^out_shift)", 0, 63),
    _enum_key(14, "rounding", ROUNDING_MODES, "rounding of the output shift"),
    ConfigKey(15, "out_bits", "u8", "bits", "8..32", "outputs saturate to signed out_bits", 8,
              32),
    ConfigKey(16, "peaks", "u8", "", "1..max_peaks", "peaks reported per channel P", 1, 8),
    ConfigKey(17, "columns_per_frame", "u16", "columns", "1..max_columns",
              "columns in a default scan frame", 1, 65535),
    _enum_key(18, "mode", MODES, "measurement mode (calibration = zeroth-order beam)"),
    ConfigKey(19, "cancel_rounds", "u8", "rounds", "0..4",
              "rounds of parallel interference cancellation; 0: none", 0, 4),
    ConfigKey(20, "cancel_snr_q8", "u32", "Q8 power ratio", "0..2^32-1",
              "SNR_XC power ratio in Q8 at which a found echo is subtracted "
              "(10192 = 16 dB)", 0, 2**32 - 1),
)
_KEY_BY_NAME = {k.name: k for k in CONFIG_KEYS}
_KEY_BY_ID = {k.id: k for k in CONFIG_KEYS}


def encode_config(values: dict[str, Any], *, allow_read_only: bool = True,
                  check: bool = True) -> list[dict]:
    """KLV items (for CONFIG_SET / CONFIG) of ``{name: python value}``; FieldError naming
    an unknown key, a read-only one (when not allowed) or a value its key cannot hold
    (outside its range unless ``check`` is False: :meth:`ConfigKey.encode`)."""
    items = []
    for name, value in values.items():
        key = config_key(name)
        if key.read_only and not allow_read_only:
            raise FieldError(f"{name} is read-only", field=name)
        items.append({"key": key.id, "value": key.encode(value, check=check)})
    return items


@dataclass
class DecodedConfig:
    """Result of :func:`decode_config`."""

    values: dict[str, Any] = field(default_factory=dict)
    unknown: list[int] = field(default_factory=list)  # mandatory keys not known
    ignored: list[int] = field(default_factory=list)  # optional keys not known


def decode_config(items: list[dict]) -> DecodedConfig:
    """Python values of KLV items; FrameError (``field`` = the key) on a bad value or a
    key given twice (a device answers NAK MALFORMED naming it)."""
    out = DecodedConfig()
    for it in items:
        kid, data = int(it["key"]), bytes(it["value"])
        key = _KEY_BY_ID.get(kid & ~CONFIG_OPTIONAL)
        if key is None:
            (out.ignored if kid & CONFIG_OPTIONAL else out.unknown).append(kid)
            continue
        if key.name in out.values:
            raise FrameError(f"{key.name}: key given twice", field=key.name)
        out.values[key.name] = key.decode(data)
    return out


def config_key(name_or_id: str | int) -> ConfigKey:
    """The :class:`ConfigKey` of a name or id; raises FieldError naming it if unknown."""
    k = _KEY_BY_NAME.get(name_or_id) if isinstance(name_or_id, str) else \
        _KEY_BY_ID.get(int(name_or_id) & ~CONFIG_OPTIONAL)
    if k is None:
        raise out_of_range(str(name_or_id), "a configuration key (" + ", ".join(_KEY_BY_NAME)
                           + ")", "unknown key", FieldError)
    return k
