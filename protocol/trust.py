"""The host trusts nothing: every field of INFO, CONFIG and every column checked.

A device may be buggy, half-updated or hostile. What passed the wire checks (CRC,
lengths, each field's wire range) is then checked against the session: INFO against
itself, the configuration against INFO, every COLUMN_RESULT against both. A
violation raises :class:`DeviceLied` (a LinkError) whose one-line message names the
field, its value and what was allowed, never a traceback, never a valid-looking
point. Strings from the device are escaped (:func:`escape`) before they can reach a
terminal: control characters, escape sequences and bidirectional overrides become
``\\xNN`` / ``\\uNNNN``.

The checks on a column (K channels, P peaks, n UID bits, N*S lags per period)::

    channels == INFO channels         peaks == config peaks     uid_bits == config uid_bits
    calibration flag == the stream's  column inside the scan   frame == the scan's
    lag fields: 0 <= lag < N*S or NO_PEAK
    sign masks: < 2^n, the -1 and 0 masks disjoint;  uid_observed < 2^n
    flags: 0 or 1;  noise_count <= gate_len, and >= 1 where a peak is reported;
    noise_count * noise_sumsq >= noise_sum^2
    peak, neighbours, extra_peak: signed out_bits, -2^(out_bits-1) <= v < 2^(out_bits-1)
    |noise_sum| <= noise_count * 2^(out_bits-1);  noise_sumsq <= noise_count * 4^(out_bits-1)

INFO's fields with a unit are checked against their physical ranges
(:data:`INFO_RANGES`: wavelengths 0.2 to 20 um, chip rate 1 kHz to 100 GHz, ...).
"""

from __future__ import annotations

import unicodedata
from dataclasses import replace
from typing import Any

import numpy as np

from cdma_lidar.column_record import NO_PEAK, RECORD
from cdma_lidar.errors import LinkError
from cdma_lidar.protocol.columns import ColumnResult
from cdma_lidar.protocol.config_keys import CONFIG_KEYS
from cdma_lidar.protocol.views import TILT_AUTO, Info

__all__ = ["INFO_RANGES", "ColumnChecker", "DeviceLied", "check_config", "check_info", "escape"]


class DeviceLied(LinkError):
    """A reply or column that parsed but contradicts the session (INFO, configuration)."""

    def __init__(self, message: str, field: str | None = None) -> None:
        super().__init__(message)
        self.field = field


def escape(text: str) -> str:
    """``text`` safe for a terminal: every non-printable character as an escape.

    Printable characters (letters, digits, punctuation, spaces) pass; control
    characters (C0, DEL, C1: ESC starts terminal escape sequences), format characters
    (bidirectional overrides) and separators other than the space become ``\\xNN`` or
    ``\\uNNNN``; a backslash is doubled so the result is unambiguous.
    """
    out = []
    for ch in text:
        if ch == "\\":
            out.append("\\\\")
        elif ch == " " or (ch.isprintable() and unicodedata.category(ch) not in ("Cf", "Zl",
                                                                                 "Zp")):
            out.append(ch)
        elif ord(ch) < 0x100:
            out.append(f"\\x{ord(ch):02x}")
        else:
            out.append(f"\\u{ord(ch):04x}" if ord(ch) < 0x10000 else f"\\U{ord(ch):08x}")
    return "".join(out)


def _lie(what: str, field: str, value: object, allowed: str) -> DeviceLied:
    return DeviceLied(f"device sent an invalid {what}: {field} = {value}, allowed "
                      f"{allowed}", field)


#: Physical range of each INFO field with a unit (inclusive, wire units): a device that
#: announces a value outside it is broken or lying, whatever the wire type can hold.
INFO_RANGES: dict[str, tuple[int, int, str]] = {
    "wavelengths_pm": (200_000, 20_000_000, "pm (0.2 to 20 um)"),
    "reference_wavelength_pm": (200_000, 20_000_000, "pm (0.2 to 20 um)"),
    "chip_rate_hz": (1_000, 4_294_967_295, "Hz (1 kHz up; the wire holds up to 4.3 GHz)"),
    "grooves_per_mm_milli": (1_000, 10_000_000, "0.001 lines/mm (1 to 10000 lines/mm)"),
    "incidence_udeg": (0, 90_000_000, "udeg (0 to 90 deg)"),
    "tilt_udeg": (-90_000_000, 90_000_000, "udeg (-90 to 90 deg, or TILT_AUTO)"),
    "column_start_udeg": (-180_000_000, 180_000_000, "udeg (-180 to 180 deg)"),
    "column_step_udeg": (-90_000_000, 90_000_000, "udeg (-90 to 90 deg)"),
    "max_degree": (2, 32, "(LFSR degree)"),
    "max_frame": (256, 65535, "bytes"),
}


def check_info(info: Info) -> Info:
    """Check INFO's fields against each other; returns it with its strings escaped."""
    def need(ok: bool, field: str, allowed: str) -> None:
        if not ok:
            raise _lie("INFO", field, getattr(info, field, "?"), allowed)

    k = len(info.wavelengths_pm)
    if not 1 <= k <= info.max_channels:
        raise _lie("INFO", "wavelengths_pm", f"{k} channels",
                   f"1 to max_channels = {info.max_channels}")
    need(info.spc_min <= info.spc_max, "spc_min", f"at most spc_max = {info.spc_max}")
    need(info.column_count >= 1, "column_count", "at least 1")
    need(info.max_columns >= 1, "max_columns", "at least 1")
    need(info.heartbeat_ms >= 1, "heartbeat_ms", "at least 1")
    for field, (lo, hi, unit) in INFO_RANGES.items():
        value = getattr(info, field)
        if field == "tilt_udeg" and value == TILT_AUTO:
            continue
        values = value if isinstance(value, tuple) else (value,)
        if not all(lo <= v <= hi for v in values):
            raise _lie("INFO", field, value, f"{lo} to {hi} {unit} (physical range)")
    need(info.column_power_cap_uw == 0 or info.pixel_power_max_uw > 0, "pixel_power_max_uw",
         "above 0 when a column power cap is announced")
    return replace(info, serial=escape(info.serial),
                   firmware_version=escape(info.firmware_version))


def check_config(config: dict[str, Any], info: Info) -> None:
    """Every key present and every value within what INFO announced."""
    for key in CONFIG_KEYS:
        if key.name not in config:
            raise DeviceLied(f"device's CONFIG lacks key {key.name!r} (every key must be "
                             "present in a CONFIG of all keys)", key.name)
    c = config

    def need(ok: bool, field: str, allowed: str) -> None:
        if not ok:
            raise _lie("CONFIG", field, c[field], allowed)

    degree = int(c["poly_u"][0]) if len(c["poly_u"]) else 0
    need(2 <= degree <= info.max_degree, "poly_u", f"degree 2 to max_degree = {info.max_degree}")
    ns = ((1 << degree) - 1) * int(c["samples_per_chip"])
    need(len(c["code_index"]) == info.channels, "code_index",
         f"{info.channels} items (one per channel)")
    need(1 <= c["uid_bits"] <= info.max_uid_bits, "uid_bits",
         f"1 to max_uid_bits = {info.max_uid_bits}")
    need(0 <= c["uid"] < 1 << c["uid_bits"], "uid", f"0 to 2^uid_bits - 1 = "
         f"{(1 << c['uid_bits']) - 1}")
    need(info.spc_min <= c["samples_per_chip"] <= info.spc_max, "samples_per_chip",
         f"{info.spc_min} to {info.spc_max}")
    need(1 <= c["averages"] <= info.max_averages, "averages", f"1 to {info.max_averages}")
    need(0 <= c["gate_start"] < ns, "gate_start", f"0 to N*S - 1 = {ns - 1}")
    need(1 <= c["gate_len"] <= min(ns, info.max_gate_len), "gate_len",
         f"1 to min(N*S, max_gate_len) = {min(ns, info.max_gate_len)}")
    need(1 <= c["peaks"] <= info.max_peaks, "peaks", f"1 to max_peaks = {info.max_peaks}")
    need(1 <= c["columns_per_frame"] <= info.column_count, "columns_per_frame",
         f"1 to column_count = {info.column_count}")


def _field_groups(extra: bool) -> tuple[list[str], list[str], list[tuple[str, str]],
                                        list[str]]:
    """(lag fields, flag fields, sign mask pairs, signed out_bits fields) of the record,
    with or without extra peaks."""
    fs = [f for f in RECORD if extra or not f.per_extra_peak]
    return ([f.name for f in fs if f.encoding == "lag"],
            [f.name for f in fs if f.encoding == "flag"],
            [(f.wire[0].name, f.wire[1].name) for f in fs if f.encoding == "signs"],
            [f.name for f in fs if f.allowed == "signed out_bits"])


_FIXED = _field_groups(False)
_ALL = _field_groups(True)


class ColumnChecker:
    """Checks every column of one stream against the session's INFO and configuration.

    Args:
        info: the session's INFO.
        config: the device configuration during the stream (all keys).
        frame: the stream's frame id.
        first, end: columns (or shots) first..end-1 are expected.
        calibration: True for a calibration stream.
    """

    def __init__(self, info: Info, config: dict[str, Any], frame: int, first: int, end: int,
                 calibration: bool) -> None:
        self.channels = info.channels
        self.peaks = int(config["peaks"])
        self.uid_bits = int(config["uid_bits"])
        self.lags = ((1 << int(config["poly_u"][0])) - 1) * int(config["samples_per_chip"])
        self.gate_len = int(config["gate_len"])
        self.out_max = 1 << (int(config["out_bits"]) - 1)  # outputs lie in [-out_max, out_max)
        self.frame, self.first, self.end = frame, first, end
        self.calibration = calibration

    def check(self, col: ColumnResult) -> None:
        """Raise DeviceLied naming the first field of ``col`` that cannot be true."""
        where = f"column {col.column} of frame {col.frame}"

        def lie(field: str, value: object, allowed: str) -> DeviceLied:
            return _lie(f"column ({where})", field, value, allowed)

        for field, value, want in (("channels", col.channels, self.channels),
                                   ("peaks", col.peaks, self.peaks),
                                   ("uid_bits", col.uid_bits, self.uid_bits),
                                   ("frame", col.frame, self.frame),
                                   ("flags.calibration", int(col.calibration),
                                    int(self.calibration))):
            if value != want:
                raise lie(field, value, f"{want} (this session)")
        if not self.first <= col.column < self.end:
            raise lie("column", col.column, f"{self.first} to {self.end - 1}")
        rec = col.records
        if self._plausible(rec):
            return  # the common case, in a few vectorised comparisons
        # Something is wrong: find the first field that says so, for the message.
        n_mask = 1 << self.uid_bits
        for f in RECORD:
            names = [w.name for w in f.wire]
            if f.encoding == "lag":
                bad = (rec[f.name] != NO_PEAK) & (rec[f.name] >= self.lags)
                self._none(lie, f.name, rec[f.name], bad, f"0 to N*S - 1 = {self.lags - 1} "
                           f"or {NO_PEAK:#x} (no peak)")
            elif f.encoding == "flag":
                self._none(lie, f.name, rec[f.name], rec[f.name] > 1, "0 or 1")
            elif f.encoding == "signs":
                neg, zero = rec[names[0]], rec[names[1]]
                self._none(lie, names[0], neg, neg >= n_mask, f"below 2^n = {n_mask}")
                self._none(lie, names[1], zero, zero >= n_mask, f"below 2^n = {n_mask}")
                self._none(lie, names[1], zero, (neg & zero) != 0,
                           f"disjoint from {names[0]} (a sign is -1 or 0, not both)")
        self._none(lie, "uid_observed", rec["uid_observed"], rec["uid_observed"] >= n_mask,
                   f"below 2^n = {n_mask}")
        for f in RECORD:
            if f.allowed == "signed out_bits":
                v = rec[f.name]
                self._none(lie, f.name, v, (v < -self.out_max) | (v >= self.out_max),
                           f"signed out_bits: {-self.out_max} to {self.out_max - 1}")
        count = rec["noise_count"]
        self._none(lie, "noise_count", count, count > self.gate_len,
                   f"at most gate_len = {self.gate_len}")
        self._none(lie, "noise_count", count, (count == 0) & (rec["peak_lag"] != NO_PEAK),
                   "at least 1 where a peak is reported (the SNR needs a noise floor)")
        # Each noise lag is an output: |sum| <= count * out_max, sumsq <= count * out_max^2.
        c_obj = count.astype(object)
        self._none(lie, "noise_sum", rec["noise_sum"], np.asarray(
            abs(rec["noise_sum"].astype(object)) > c_obj * self.out_max, dtype=bool),
            f"at most noise_count * 2^(out_bits-1) = noise_count * {self.out_max} in magnitude")
        self._none(lie, "noise_sumsq", rec["noise_sumsq"], np.asarray(
            rec["noise_sumsq"].astype(object) > c_obj * self.out_max ** 2, dtype=bool),
            f"at most noise_count * 2^(2 out_bits - 2) = noise_count * {self.out_max ** 2}")
        # Cauchy-Schwarz: count * sumsq >= sum^2 for any real noise floor (exact integers).
        lhs = count.astype(object) * rec["noise_sumsq"].astype(object)
        rhs = rec["noise_sum"].astype(object) ** 2
        self._none(lie, "noise_sumsq", rec["noise_sumsq"], np.asarray(lhs < rhs, dtype=bool),
                   "at least noise_sum^2 / noise_count")

    def _plausible(self, rec: np.ndarray) -> bool:
        """True when every record field is within the session (fast path of check)."""
        n_mask = 1 << self.uid_bits
        if self.peaks == 1:  # the per-extra-peak fields are empty
            lags, flags, signs, outs = _FIXED
        else:
            lags, flags, signs, outs = _ALL
        for name in outs:
            v = rec[name]
            if v.size and (v.min() < -self.out_max or v.max() >= self.out_max):
                return False
        for name in lags:
            v = rec[name]
            if v.max() >= self.lags and bool(((v >= self.lags) & (v != NO_PEAK)).any()):
                return False
        for name in flags:
            if rec[name].max() > 1:
                return False
        for neg_name, zero_name in signs:
            neg, zero = rec[neg_name], rec[zero_name]
            if max(neg.max(), zero.max()) >= n_mask or (neg & zero).any():
                return False
        count = rec["noise_count"]
        if rec["uid_observed"].max() >= n_mask or count.max() > self.gate_len:
            return False
        if count.min() == 0 and bool(((count == 0) & (rec["peak_lag"] != NO_PEAK)).any()):
            return False
        cf = count.astype(np.float64)
        # Bounds from the output range; float is within 1e-15, so a margin of 1e-9 is safe
        # and a record near a bound is judged exactly by check().
        if (np.abs(rec["noise_sum"].astype(np.float64)) > cf * self.out_max * (1 - 1e-9)).any() \
                or (rec["noise_sumsq"].astype(np.float64) >
                    cf * float(self.out_max) ** 2 * (1 - 1e-9)).any():
            return False
        lhs = cf * rec["noise_sumsq"].astype(np.float64)
        rhs = np.square(rec["noise_sum"].astype(np.float64))
        close = lhs <= rhs * (1 + 1e-9)  # decided exactly below; float is good to 1e-15
        if close.any():
            idx = np.flatnonzero(close)
            exact = [int(count[i]) * int(rec["noise_sumsq"][i]) >= int(rec["noise_sum"][i]) ** 2
                     for i in idx]
            return all(exact)
        return True

    @staticmethod
    def _none(lie: Any, field: str, values: np.ndarray, bad: np.ndarray, allowed: str) -> None:
        if np.any(bad):
            idx = np.argwhere(bad)[0]
            at = ", ".join(str(int(x)) for x in idx)
            raise lie(f"{field}[{at}]", int(values[tuple(idx)]), allowed)
