"""CONFIG keys: the key-length-value set carried by CONFIG_SET and CONFIG.

Each key is declared once as a :class:`ConfigKey`, the payload field of its value (value
type, unit, wire range ``lo..hi``, the device's range ``allowed``) with its id and, where the
host value is not the wire value, the mapping (exponent tuples <-> polynomial masks, names
<-> codes, window pairs <-> structs), for :func:`encode_config`, the strict
:func:`decode_config`, the spec's table and the schema CRC. Bit 7 of a key id is the
*optional* flag (:data:`CONFIG_OPTIONAL`): a device ignores an unknown optional key and
refuses another unknown one with NAK UNKNOWN_KEY naming it.
"""

from __future__ import annotations

import struct
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

from cdma_lidar.checks import is_int
from cdma_lidar.errors import FieldError, FrameError, out_of_range
from cdma_lidar.poly import mask_to_poly, tap_mask
from cdma_lidar.protocol.schema import Field, Layout
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


def _windows_to_wire(v: Any) -> list[dict[str, int]]:
    """(start, length) pairs to the wire's structs; FieldError: what it takes."""
    try:
        return [{"start": int(s), "length": int(n)} for s, n in v]
    except (TypeError, ValueError):
        raise FieldError("a list of (start, length) pairs") from None


@dataclass(frozen=True, kw_only=True)
class ConfigKey(Field):
    """One key of the CONFIG key-length-value set: the field of its value (which fills the
    item's whole length; ``lo..hi``: its wire range, None: any that parses; ``allowed``:
    the device's range), its ``id`` and the host value's mapping to the wire value."""

    id: int
    read_only: bool = False
    to_wire: Callable[[Any], Any] = lambda v: v  # host -> wire value; FieldError(what it takes)
    from_wire: Callable[[Any], Any] = lambda v: v

    def encode(self, value: Any, *, check: bool = True) -> bytes:
        """Value bytes; raises FieldError naming the key. ``check``: hold the value to the
        key's range (the host's one check of what it sends); False for a value its model
        already checked (the device's own configuration): only what the wire cannot hold fails."""
        try:
            w = self.to_wire(value)
            if check and self.lo is not None:
                self.check(self.name, w)
            return Layout(self).build({self.name: w})
        except FieldError as exc:  # to_wire's (no field): what it takes; check's: the range,
            each = "each " if self.kind == "array" else ""  # as the device's and the wire's
            why = str(exc) if exc.field is None else \
                f"{self.allowed} ({each}{self.lo}..{self.hi} on the wire)"
            raise out_of_range(self.name, why, value, FieldError) from None
        except (struct.error, TypeError, ValueError, KeyError) as exc:
            raise out_of_range(self.name, self.allowed, value, FieldError) from exc

    def decode(self, data: bytes) -> Any:
        """Python value of the wire bytes; FrameError naming the key if malformed or out of
        its wire range (the receiving side's one check of the wire range)."""
        try:
            return self.from_wire(Layout(self).decode(data, f"CONFIG key {self.name}")[self.name])
        except FrameError as exc:  # bytes left after the value name no field
            raise FrameError(str(exc), field=self.name) from None


def _enum_key(kid: int, key: str, names: tuple[str, ...], doc: str) -> ConfigKey:
    """A u8 key whose wire code is the index of its name in ``names`` (spec range text:
    ``0 truncate, 1 half_up, 2 convergent``)."""
    def to_wire(v: Any) -> int:  # a name, or its code as it is
        if isinstance(v, str) and v not in names:
            raise FieldError("one of " + ", ".join(names))
        return names.index(v) if isinstance(v, str) else v

    return ConfigKey(key, "u8", doc, "", 0, len(names) - 1,
                     ", ".join(f"{c} {n}" for c, n in enumerate(names)), id=kid,
                     to_wire=to_wire, from_wire=names.__getitem__)


CONFIG_KEYS: tuple[ConfigKey, ...] = (
    ConfigKey("poly_u", "u32", "first Gold polynomial: bit e - 1 set = x^e term (e = 1..32), "
              "x^0 implied (host: exponent tuple, highest first)",
              allowed="mask, degree 2..max_degree", id=1, to_wire=_poly_to_wire,
              from_wire=_wire_to_poly),
    ConfigKey("poly_v", "u32", "second Gold polynomial, same encoding",
              allowed="mask, same degree as poly_u", id=2, to_wire=_poly_to_wire,
              from_wire=_wire_to_poly),
    ConfigKey("code_index", "u16 x K", "Gold family member of each channel", "", 0, 65535,
              "0..2^m (N+1), K items", kind="array", fmt="H", id=3, to_wire=list,
              from_wire=tuple),
    ConfigKey("uid_bits", "u8", "UID length n", "code periods", 1, 8, "1..max_uid_bits", id=4),
    ConfigKey("uid", "u8", "this device's UID (bit p = polarity of period p)", "", 0, 255,
              "0..2^uid_bits-1", id=5),
    ConfigKey("samples_per_chip", "u16", "ADC samples per chip S", "samples/chip", 1, 65535,
              "spc_min..spc_max", id=6),
    ConfigKey("averages", "u32", "coherently summed code repetitions R", "repetitions", 1,
              2**32 - 1, "1..max_averages", id=7),
    ConfigKey("adc_bits", "u8", "ADC resolution", "bits", 8, 16, "8..16, read-only", id=8,
              read_only=True),
    ConfigKey("gate_start", "u32", "first lag of the gate", "samples", 0, 2**32 - 1,
              "0..N*S-1", id=9),
    ConfigKey("gate_len", "u32", "lags in the gate", "samples", 1, 2**32 - 1,
              "1..min(N*S, max_gate_len)", id=10),
    ConfigKey("peak_exclude", "u32", "W: peaks at least W+1 lags apart; noise excludes "
              "|j - j_peak| <= W", "samples", 0, 2**32 - 1, "0..N*S", id=11),
    ConfigKey("ghost_windows", "(u32 start, u32 len) x n", "absolute lags (start, "
              "start+len-1, mod N*S) ignored by peak search and noise floor", "samples",
              allowed="lags mod N*S", kind="array", fmt="II", names=("start", "length"),
              id=12, to_wire=_windows_to_wire,
              from_wire=lambda w: tuple((e["start"], e["length"]) for e in w)),
    ConfigKey("out_shift", "u8", "out = round(raw / 2^out_shift)", "bits", 0, 63, "0..63",
              id=13),
    _enum_key(14, "rounding", ROUNDING_MODES, "rounding of the output shift"),
    ConfigKey("out_bits", "u8", "outputs saturate to signed out_bits", "bits", 8, 32, "8..32",
              id=15),
    ConfigKey("peaks", "u8", "peaks reported per channel P", "", 1, 8, "1..max_peaks", id=16),
    ConfigKey("columns_per_frame", "u16", "columns in a default scan frame", "columns", 1,
              65535, "1..max_columns", id=17),
    _enum_key(18, "mode", MODES, "measurement mode (calibration = zeroth-order beam)"),
    ConfigKey("cancel_rounds", "u8", "rounds of parallel interference cancellation; 0: none",
              "rounds", 0, 4, "0..4", id=19),
    ConfigKey("cancel_snr_q8", "u32", "SNR_XC power ratio in Q8 at which a found echo is "
              "subtracted (10192 = 16 dB)", "Q8 power ratio", 0, 2**32 - 1, "0..2^32-1", id=20),
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
