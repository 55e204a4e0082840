"""The host trusts nothing: every field of INFO, CONFIG and every column checked.

What passed the wire checks (CRC, lengths, each field's wire range) is then checked
against the session: INFO against itself and its physical ranges (:data:`INFO_RANGES`),
the configuration against INFO, every COLUMN_RESULT against both (the list is
docs/protocol.md section 8). A violation raises :class:`DeviceLied` (a LinkError) whose
one-line message names the field, its value and what was allowed. Strings from the
device are escaped (:func:`escape`) before they can reach a terminal.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import replace
from typing import Any

import numpy as np

from cdma_lidar.column_record import NO_PEAK, RECORD
from cdma_lidar.errors import LinkError
from cdma_lidar.protocol.columns import ColumnResult
from cdma_lidar.protocol.config_keys import CONFIG_KEYS
from cdma_lidar.protocol.messages import TILT_AUTO, Info

__all__ = ["INFO_RANGES", "ColumnChecker", "DeviceLied", "check_config", "check_info", "escape"]


class DeviceLied(LinkError):
    """A reply or column that parsed but contradicts the session (INFO, configuration)."""

    def __init__(self, message: str, field: str | None = None) -> None:
        super().__init__(message)
        self.field = field


def escape(text: str) -> str:
    """``text`` safe for a terminal: a backslash doubled, and every character that is not
    printable (control characters, C0, DEL and C1: ESC starts terminal escape sequences;
    format characters: bidirectional overrides; separators but the space) as ``\\xNN``,
    ``\\uNNNN`` or ``\\UNNNNNNNN``."""
    def one(ch: str) -> str:
        if ch.isprintable():
            return "\\\\" if ch == "\\" else ch
        n = ord(ch)
        return f"\\x{n:02x}" if n < 0x100 else f"\\u{n:04x}" if n < 0x10000 else f"\\U{n:08x}"

    return "".join(map(one, text))


def _lie(what: str, field: str, value: object, allowed: str) -> DeviceLied:
    return DeviceLied(f"device sent an invalid {what}: {field} = {value}, allowed "
                      f"{allowed}", field)


#: Physical range of each INFO field with a unit (inclusive, wire units): a device that
#: announces a value outside it is broken or lying, whatever the wire type can hold.
#: Fields whose declared wire range is already their physical one (``max_degree``
#: 2..32, ``max_frame`` 256..65535) are checked once, by the decoder.
INFO_RANGES: dict[str, tuple[int, int, str]] = {
    "wavelengths_pm": (200_000, 20_000_000, "pm (0.2 to 20 um)"),
    "reference_wavelength_pm": (200_000, 20_000_000, "pm (0.2 to 20 um)"),
    "chip_rate_hz": (1_000, 4_294_967_295, "Hz (1 kHz up; the wire holds up to 4.3 GHz)"),
    "grooves_per_mm_milli": (1_000, 10_000_000, "0.001 lines/mm (1 to 10000 lines/mm)"),
    "incidence_udeg": (0, 90_000_000, "udeg (0 to 90 deg)"),
    "tilt_udeg": (-90_000_000, 90_000_000, "udeg (-90 to 90 deg, or TILT_AUTO)"),
    "column_start_udeg": (-180_000_000, 180_000_000, "udeg (-180 to 180 deg)"),
    "column_step_udeg": (-90_000_000, 90_000_000, "udeg (-90 to 90 deg)"),
}


def check_info(info: Info) -> Info:
    """Check INFO's fields against each other and their physical ranges (the decoder
    checked each wire range); returns it with its strings escaped."""
    k = len(info.wavelengths_pm)
    if not 1 <= k <= info.max_channels:
        raise _lie("INFO", "wavelengths_pm", f"{k} channels",
                   f"1 to max_channels = {info.max_channels}")
    if info.spc_min > info.spc_max:
        raise _lie("INFO", "spc_min", info.spc_min, f"at most spc_max = {info.spc_max}")
    for field, (lo, hi, unit) in INFO_RANGES.items():
        value = getattr(info, field)
        if field == "tilt_udeg" and value == TILT_AUTO:
            continue
        if not all(lo <= v <= hi for v in (value if isinstance(value, tuple) else (value,))):
            raise _lie("INFO", field, value, f"{lo} to {hi} {unit} (physical range)")
    if info.column_power_cap_uw != 0 and not info.pixel_power_max_uw > 0:
        raise _lie("INFO", "pixel_power_max_uw", info.pixel_power_max_uw,
                   "above 0 when a column power cap is announced")
    return replace(info, serial=escape(info.serial),
                   firmware_version=escape(info.firmware_version))


def check_config(config: dict[str, Any], info: Info) -> None:
    """Every key present and every value within what INFO announced.

    Each value's own range was checked where it was decoded
    (:meth:`~cdma_lidar.protocol.config_keys.ConfigKey.decode`); here only what INFO
    and the other keys bound (the lower bounds in the messages are the decoder's).
    """
    for key in CONFIG_KEYS:
        if key.name not in config:
            raise DeviceLied(f"device's CONFIG lacks key {key.name!r} (every key must be "
                             "present in a CONFIG of all keys)", key.name)
    c, i = config, info
    degree = int(c["poly_u"][0]) if len(c["poly_u"]) else 0
    ns = ((1 << degree) - 1) * int(c["samples_per_chip"])
    gate_max = min(ns, i.max_gate_len)
    for ok, field, allowed in (
            (2 <= degree <= i.max_degree, "poly_u", f"degree 2 to max_degree = {i.max_degree}"),
            (len(c["code_index"]) == i.channels, "code_index",
             f"{i.channels} items (one per channel)"),
            (c["uid_bits"] <= i.max_uid_bits, "uid_bits", f"1 to max_uid_bits = {i.max_uid_bits}"),
            (c["uid"] < 1 << c["uid_bits"], "uid",
             f"0 to 2^uid_bits - 1 = {(1 << c['uid_bits']) - 1}"),
            (i.spc_min <= c["samples_per_chip"] <= i.spc_max, "samples_per_chip",
             f"{i.spc_min} to {i.spc_max}"),
            (c["averages"] <= i.max_averages, "averages", f"1 to {i.max_averages}"),
            (c["gate_start"] < ns, "gate_start", f"0 to N*S - 1 = {ns - 1}"),
            (c["gate_len"] <= gate_max, "gate_len", f"1 to min(N*S, max_gate_len) = {gate_max}"),
            (c["peaks"] <= i.max_peaks, "peaks", f"1 to max_peaks = {i.max_peaks}"),
            (c["columns_per_frame"] <= i.column_count, "columns_per_frame",
             f"1 to column_count = {i.column_count}")):
        if not ok:
            raise _lie("CONFIG", field, c[field], allowed)


class ColumnChecker:
    """Checks every column of one stream (a ``calibration`` one: shots) against the
    session's ``info`` and ``config`` (all keys, during the stream). Its frame id and
    column range are the reassembler's: a column outside them is not the stream's."""

    def __init__(self, info: Info, config: dict[str, Any], calibration: bool) -> None:
        self.channels = info.channels
        self.peaks, self.uid_bits, self.gate_len, out_bits = (
            int(config[k]) for k in ("peaks", "uid_bits", "gate_len", "out_bits"))
        self.lags = ((1 << int(config["poly_u"][0])) - 1) * int(config["samples_per_chip"])
        self.out_max = 1 << (out_bits - 1)  # outputs lie in [-out_max, out_max)
        self.calibration = calibration

    def check(self, col: ColumnResult) -> None:
        """Raise DeviceLied naming the first field of ``col`` that cannot be true."""
        what = f"column (column {col.column} of frame {col.frame})"

        def none(field: str, values: np.ndarray, bad: np.ndarray, allowed: str) -> None:
            if np.any(bad):  # names the first bad element
                idx = np.argwhere(bad)[0]
                at = ", ".join(str(int(x)) for x in idx)
                raise _lie(what, f"{field}[{at}]", int(values[tuple(idx)]), allowed)

        for field, value, want in (
                ("channels", col.channels, self.channels), ("peaks", col.peaks, self.peaks),
                ("uid_bits", col.uid_bits, self.uid_bits),
                ("flags.calibration", int(col.calibration), int(self.calibration))):
            if value != want:
                raise _lie(what, field, value, f"{want} (this session)")
        rec, n_mask, out = col.records, 1 << self.uid_bits, self.out_max
        for f in RECORD:
            if f.encoding == "signs":
                neg, zero = (w.name for w in f.wire)
                for name in (neg, zero):
                    none(name, rec[name], rec[name] >= n_mask, f"below 2^n = {n_mask}")
                none(zero, rec[zero], (rec[neg] & rec[zero]) != 0,
                     f"disjoint from {neg} (a sign is -1 or 0, not both)")
                continue
            v = rec[f.name]
            if f.encoding == "lag":
                none(f.name, v, (v >= self.lags) & (v != NO_PEAK),
                     f"0 to N*S - 1 = {self.lags - 1} or {NO_PEAK:#x} (no peak)")
            elif f.encoding == "flag":
                none(f.name, v, v > 1, "0 or 1")
            if f.allowed == "signed out_bits":
                none(f.name, v, (v < -out) | (v >= out), f"signed out_bits: {-out} to {out - 1}")
        none("uid_observed", rec["uid_observed"], rec["uid_observed"] >= n_mask,
             f"below 2^n = {n_mask}")
        count, total, sumsq = rec["noise_count"], rec["noise_sum"], rec["noise_sumsq"]
        none("noise_count", count, count > self.gate_len, f"at most gate_len = {self.gate_len}")
        none("noise_count", count, (count == 0) & (rec["peak_lag"] != NO_PEAK),
             "at least 1 where a peak is reported (the SNR needs a noise floor)")
        # Each noise lag is an output: |sum| <= count * out, sumsq <= count * out^2; and
        # count * sumsq >= sum^2 for any real noise floor (Cauchy-Schwarz). Exact integers.
        noise = (count, total, sumsq)
        none("noise_sum", total, _above(lambda c, s, q: (abs(s), c * out), noise),
             f"at most noise_count * 2^(out_bits-1) = noise_count * {out} in magnitude")
        none("noise_sumsq", sumsq, _above(lambda c, s, q: (q, c * out ** 2), noise),
             f"at most noise_count * 2^(2 out_bits - 2) = noise_count * {out ** 2}")
        none("noise_sumsq", sumsq, _above(lambda c, s, q: (s * s, c * q), noise),
             "at least noise_sum^2 / noise_count")


def _above(sides: Callable[..., Any], arrays: tuple[np.ndarray, ...]) -> np.ndarray:
    """Where ``lhs > rhs``, ``sides(*arrays)`` of 1-D integer arrays (both >= 0): in floats
    where more than 1e-9 apart (they are good to 1e-15), in exact integers elsewhere."""
    lhs, rhs = sides(*(a.astype(np.float64) for a in arrays))
    bad = lhs > rhs * (1 + 1e-9)
    if (near := np.flatnonzero(~bad & (lhs > rhs * (1 - 1e-9)))).size:
        lhs, rhs = sides(*(a[near].astype(object) for a in arrays))
        bad[near] = lhs > rhs
    return bad
