"""The scene file format: TOML (and ``?key=value`` options) read and validated into a Scene.

A scene file has up to four parts::

    name = "flat-wall"
    description = "..."
    [shortcuts]                  # option names for dotted fields ("distance" -> objects[0]...)
    distance = "objects[0].position_m[0]"
    [instrument]                 # the simulated board, optics and photodiode (true values)
    wavelengths = { start_m = 1570e-9, spacing_m = 0.875e-9, count = 40 }
                                 # or { start_m, stop_m, count }: the spacing follows
    total_power_cap_w = 0.2      # or total_power_cap_per_channel_w: the cap is K times it
    azimuth_deg = [-5.0, 5.0]    # first and last column, or rotations_deg = [...]
    columns = 160
    ...
    [calibration]                # the zeroth-order target
    [[objects]]                  # planes, boxes, spheres, extruded text
    kind = "plane"
    position_m = [5.0, 0.0, 0.0]
    ...

Every field is checked once, here; a bad value raises ``ConfigError`` naming the dotted
field (``objects[3].radius_m``) and its allowed range, and a key nobody reads is an error
(typos must not pass silently). Defaults are those of the model's dataclass fields
(:mod:`cdma_lidar.scene.model`); only the shorthands that expand to the model's arrays
(``DEFAULT_*`` below) have theirs here.

Options (``flat-wall?distance=7.5`` or a dict) replace fields of the parsed document
before validation: a file's own ``[shortcuts]`` or any dotted field such as
``instrument.snr_db`` or ``objects[0].reflectivity``; values are read as TOML values
(``7.5``, ``[1, 2]``), else kept as strings.
"""

from __future__ import annotations

import math
import re
import tomllib
import urllib.parse
from typing import Any

import numpy as np
from numpy.typing import NDArray

from cdma_lidar.checks import check_int
from cdma_lidar.errors import ConfigError, out_of_range
from cdma_lidar.firmware_model.pairs import pair_degrees, preferred_pairs
from cdma_lidar.firmware_model.receiver import MAX_CHANNELS
from cdma_lidar.firmware_model.receiver_config import MAX_CANCEL_ROUNDS
from cdma_lidar.optics.grating import GratingGeometry
from cdma_lidar.scene.model import (
    FIDELITY_LEVELS,
    OBJECT_KINDS,
    Calibration,
    Ghost,
    InstrumentSpec,
    ObjectSpec,
    OtherUser,
    Scene,
    field_default,
)
from cdma_lidar.units import SPEED_OF_LIGHT_M_S

__all__ = [
    "DEFAULT_AZIMUTH_DEG",
    "DEFAULT_COLUMNS",
    "DEFAULT_LASER_POWER_W",
    "DEFAULT_WAVELENGTHS",
    "apply_options",
    "parse_options",
    "parse_scene",
    "read_document",
]

# Defaults of the shorthands that expand to arrays of InstrumentSpec (which therefore
# has no default of its own for them):
#: ``instrument.wavelengths``: the comb start_m + spacing_m * k, k < count (the paper's L band)
DEFAULT_WAVELENGTHS: dict[str, Any] = {"start_m": 1570e-9, "spacing_m": 0.875e-9, "count": 40}
#: ``instrument.azimuth_deg``: azimuths (deg) of the last and the first column
DEFAULT_AZIMUTH_DEG = (-5.0, 5.0)
#: ``instrument.columns``: columns spread over the azimuth field
DEFAULT_COLUMNS = 160
#: ``instrument.laser_power_w`` given as one number: every channel's laser power (W)
DEFAULT_LASER_POWER_W = 2.5e-3


# ---------------------------------------------------------------------------------------
# field readers: one place that knows how to check a number, a vector, a list of ints

class _Reader:
    """Reads fields of one TOML table, remembering which keys were used."""

    def __init__(self, table: Any, path: str) -> None:
        if not isinstance(table, dict):
            raise out_of_range(path, "a table", table)
        self.table = table
        self.path = path
        self.used: set[str] = set()

    def name(self, key: str) -> str:
        return f"{self.path}.{key}" if self.path else key

    def has(self, key: str) -> bool:
        return key in self.table

    def raw(self, key: str, default: Any = None) -> Any:
        self.used.add(key)
        return self.table.get(key, default)

    def num(self, key: str, lo: float, hi: float, default: float | None = None, *,
            unit: str = "", open_lo: bool = False) -> float:
        value = self.raw(key, default)
        allowed = f"a number {'>' if open_lo else 'from'} {lo:g}{'' if open_lo else f' to {hi:g}'}"
        if open_lo:
            allowed += f" and at most {hi:g}"
        allowed += f" {unit}".rstrip()
        if value is None:
            raise out_of_range(self.name(key), allowed + " (required)", value)
        if isinstance(value, bool) or not isinstance(value, int | float):
            raise out_of_range(self.name(key), allowed, value)
        v = float(value)
        if not math.isfinite(v) or v > hi or (v <= lo if open_lo else v < lo):
            raise out_of_range(self.name(key), allowed, value)
        return v

    def int(self, key: str, lo: int, hi: int, default: int | None = None) -> int:
        return check_int(self.name(key), self.raw(key, default), lo, hi)

    def str(self, key: str, choices: tuple[str, ...] | None = None,
            default: str | None = None) -> str:
        value = self.raw(key, default)
        if not isinstance(value, str) or (choices is not None and value not in choices):
            allowed = "a string" if choices is None else "one of " + ", ".join(choices)
            raise out_of_range(self.name(key), allowed, value)
        return value

    def bool(self, key: str, default: bool) -> bool:
        value = self.raw(key, default)
        if not isinstance(value, bool):
            raise out_of_range(self.name(key), "true or false", value)
        return value

    def vec(self, key: str, n: int, lo: float, hi: float, default: Any = None,
            unit: str = "") -> NDArray[np.float64]:
        value = self.raw(key, default)
        allowed = f"a list of {n} numbers from {lo:g} to {hi:g} {unit}".rstrip()
        if not isinstance(value, list | tuple) or len(value) != n or any(
                isinstance(x, bool) or not isinstance(x, int | float) for x in value):
            raise out_of_range(self.name(key), allowed, value)
        arr = np.asarray(value, dtype=np.float64)
        if not (np.all(np.isfinite(arr)) and np.all(arr >= lo) and np.all(arr <= hi)):
            raise out_of_range(self.name(key), allowed, value)
        return arr

    def nums(self, key: str, lo: float, hi: float, *, min_len: int = 1, max_len: int = 1 << 20,
             integer: bool = False, unit: str = "") -> NDArray:
        value = self.raw(key)
        kind = "integers" if integer else "numbers"
        allowed = f"a list of {min_len} to {max_len} {kind} from {lo:g} to {hi:g} {unit}".rstrip()
        ok_type = (int,) if integer else (int, float)
        if not isinstance(value, list | tuple) or not min_len <= len(value) <= max_len or any(
                isinstance(x, bool) or not isinstance(x, ok_type) for x in value):
            raise out_of_range(self.name(key), allowed, value)
        arr = np.asarray(value, dtype=np.int64 if integer else np.float64)
        if not (np.all(np.isfinite(arr)) and np.all(arr >= lo) and np.all(arr <= hi)):
            raise out_of_range(self.name(key), allowed, value)
        return arr

    def ints(self, key: str, lo: int, hi: int, default: tuple[int, ...] | None, *,
             min_len: int = 0, max_len: int = 1 << 20) -> tuple[int, ...] | None:
        """A list of integers in lo..hi as a tuple, ``default`` if the key is absent."""
        if not self.has(key):
            return default
        arr = self.nums(key, lo, hi, min_len=min_len, max_len=max_len, integer=True)
        return tuple(int(x) for x in arr)

    def sub(self, key: str) -> _Reader | None:
        value = self.raw(key)
        return None if value is None else _Reader(value, self.name(key))

    def done(self) -> None:
        """Reject keys nobody read (typos must not pass silently)."""
        extra = sorted(set(self.table) - self.used)
        if extra:
            known = ", ".join(sorted(self.used))
            raise ConfigError(
                f"{self.name(extra[0])} is not a known field; known fields here: {known}",
                field=self.name(extra[0]))


# ---------------------------------------------------------------------------------------
# parsing

def _parse_wavelengths(r: _Reader) -> NDArray[np.float64]:
    if r.has("wavelengths_m"):
        return r.nums("wavelengths_m", 100e-9, 20e-6, max_len=MAX_CHANNELS, unit="m")
    w = r.sub("wavelengths")
    if w is None:
        w = _Reader({}, r.name("wavelengths"))
    d = DEFAULT_WAVELENGTHS
    start = w.num("start_m", 100e-9, 20e-6, d["start_m"], unit="m")
    count = w.int("count", 1, MAX_CHANNELS, d["count"])
    if w.has("stop_m"):
        # a band instead of a spacing: the spacing follows the count
        if w.has("spacing_m"):
            raise out_of_range(w.name("spacing_m"), "absent when stop_m is given",
                               w.raw("spacing_m"))
        stop = w.num("stop_m", 100e-9, 20e-6, unit="m")
        w.done()
        return np.linspace(start, stop, count) if count > 1 else np.array([start])
    spacing = w.num("spacing_m", -1e-6, 1e-6, d["spacing_m"], unit="m")
    w.done()
    return start + spacing * np.arange(count, dtype=np.float64)


def _parse_rotations(r: _Reader, grooves_per_mm: float, incidence_deg: float,
                     tilt_deg: float | None) -> NDArray[np.float64]:
    if r.has("rotations_deg"):
        return r.nums("rotations_deg", -60.0, 60.0, max_len=100_000, unit="deg")
    az = r.vec("azimuth_deg", 2, -60.0, 60.0, list(DEFAULT_AZIMUTH_DEG), unit="deg")
    cols = r.int("columns", 1, 100_000, DEFAULT_COLUMNS)
    geom = GratingGeometry(grooves_per_mm, incidence_deg, tilt_deg)
    # column 0 is the leftmost as the sensor sees it (largest azimuth, +y); the stage steps
    # the rotation uniformly between the rotations that aim the reference wavelength at the
    # two ends of the field (so a column's angle is start + step * column)
    ends = np.array([az[1], az[0]]) if cols > 1 else np.array([az.mean()])
    try:
        rot_ends = geom.rotations_for_azimuths(ends)
    except ConfigError as exc:
        raise ConfigError(f"{r.name('azimuth_deg')}: {exc}", field=r.name("azimuth_deg")) from exc
    return np.linspace(rot_ends[0], rot_ends[-1], cols)


def _array_of_tables(value: Any, path: str) -> list[Any]:
    if value is None:
        return []
    if not isinstance(value, list):
        raise out_of_range(path, "an array of tables", value)
    return value


def _parse_ghosts(value: Any, path: str, k: int, c: int) -> tuple[Ghost, ...]:
    out = []
    for i, item in enumerate(_array_of_tables(value, path)):
        g = _Reader(item, f"{path}[{i}]")
        chans = g.ints("channels", 0, k - 1, field_default(Ghost, "channels"))
        cols = g.ints("columns", 0, c - 1, field_default(Ghost, "columns"))
        out.append(Ghost(distance_m=g.num("distance_m", 0.0, 1e4, unit="m"),
                         amplitude_v=g.num("amplitude_v", 0.0, 1e3, unit="V"),
                         channels=chans, columns=cols))
        g.done()
    return tuple(out)


def _parse_users(value: Any, path: str, n_codes: int, c: int) -> tuple[OtherUser, ...]:
    out = []
    for i, item in enumerate(_array_of_tables(value, path)):
        u = _Reader(item, f"{path}[{i}]")
        bits = u.int("uid_bits", 1, 16, field_default(OtherUser, "uid_bits"))
        uid = u.int("uid", 0, (1 << bits) - 1)
        if u.has("delay_s"):
            delay = u.num("delay_s", 0.0, 1.0, unit="s")
        else:
            delay = u.num("distance_m", 0.0, 1e5, unit="m") / SPEED_OF_LIGHT_M_S
        cols = u.ints("columns", 0, c - 1, field_default(OtherUser, "columns"))
        out.append(OtherUser(
            uid=uid,
            code_index=u.int("code_index", 0, n_codes - 1, field_default(OtherUser, "code_index")),
            delay_s=delay, amplitude_v=u.num("amplitude_v", 0.0, 1e3, unit="V"),
            uid_bits=bits, columns=cols))
        u.done()
    return tuple(out)


def _parse_poly(r: _Reader, key: str) -> tuple[int, ...] | None:
    r.used.add(key)  # a known field even when absent (listed as such in the error of a typo)
    poly = r.ints(key, 1, 32, field_default(InstrumentSpec, key), min_len=2, max_len=33)
    if list(poly) != sorted(set(poly), reverse=True):
        raise out_of_range(r.name(key), "exponents in strictly decreasing order", list(poly))
    return poly


def _speckle_cells(r: _Reader) -> float:
    """0 (no speckle) or at least 1 speckle cell averaged over the aperture."""
    cells = r.num("speckle_cells", 0.0, 1e6, field_default(InstrumentSpec, "speckle_cells"))
    if 0 < cells < 1:
        raise out_of_range("instrument.speckle_cells", "0 (off) or a number from 1 to 1e+06",
                           cells)
    return cells


def _parse_instrument(table: Any) -> InstrumentSpec:
    r = _Reader(table if table is not None else {}, "instrument")

    def d(key: str) -> Any:
        return field_default(InstrumentSpec, key)

    def optional_num(key: str, lo: float, hi: float, unit: str) -> float | None:
        return r.num(key, lo, hi, unit=unit) if r.has(key) else d(key)

    wl = _parse_wavelengths(r)
    k = wl.size
    tilt = optional_num("tilt_deg", -180.0, 180.0, "deg")
    grooves = r.num("grooves_per_mm", 1.0, 1e4, d("grooves_per_mm"), unit="lines/mm")
    incidence = r.num("incidence_deg", -89.0, 89.0, d("incidence_deg"), unit="deg")
    nominal_tilt = optional_num("nominal_tilt_deg", -180.0, 180.0, "deg")
    rot = _parse_rotations(r, grooves, incidence, tilt)
    c = rot.size
    if r.has("code_degree"):
        # shorthand for the code pair: the first preferred pair of that degree
        degree = r.int("code_degree", min(pair_degrees()), max(pair_degrees()))
        if r.has("poly_u") or r.has("poly_v"):
            raise out_of_range("instrument.code_degree", "absent when poly_u/poly_v are given",
                               degree)
        if degree not in pair_degrees():
            raise out_of_range("instrument.code_degree", "one of " + ", ".join(
                str(m) for m in pair_degrees()) + " (degrees with preferred pairs)", degree)
        poly_u, poly_v = preferred_pairs(degree)[0]
        r.used.update(("poly_u", "poly_v"))
    else:
        r.used.add("code_degree")
        poly_u = _parse_poly(r, "poly_u")
        poly_v = _parse_poly(r, "poly_v")
    if poly_u[0] != poly_v[0]:
        raise out_of_range("instrument.poly_v", f"of the same degree as poly_u ({poly_u[0]})",
                           list(poly_v))
    degree = poly_u[0]
    if not 3 <= degree <= 20:
        raise out_of_range("instrument.poly_u", "a polynomial of degree 3 to 20", list(poly_u))
    n_codes = (1 << degree) + 1
    code_index = r.ints("code_index", 0, n_codes - 1, d("code_index"), min_len=k, max_len=k)
    uid_bits = r.int("uid_bits", 1, 16, d("uid_bits"))
    uid = r.int("uid", 0, (1 << uid_bits) - 1, d("uid"))
    adc_bits = r.int("adc_bits", 8, 16, d("adc_bits"))
    max_pixel = r.num("max_pixel_power_w", 0.0, 10.0, d("max_pixel_power_w"), unit="W",
                      open_lo=True)
    if r.has("laser_power_w") and isinstance(r.table["laser_power_w"], list):
        power = r.nums("laser_power_w", 0.0, max_pixel, min_len=k, max_len=k, unit="W")
    else:
        power = np.full(k, r.num("laser_power_w", 0.0, max_pixel, DEFAULT_LASER_POWER_W,
                                 unit="W"))
    if r.has("total_power_cap_per_channel_w"):
        # the column cap stated per channel, so that it scales with K
        if r.has("total_power_cap_w"):
            raise out_of_range("instrument.total_power_cap_w",
                               "absent when total_power_cap_per_channel_w is given",
                               r.raw("total_power_cap_w"))
        cap = k * r.num("total_power_cap_per_channel_w", 0.0, 100.0 / k, unit="W",
                        open_lo=True)
    else:
        cap = r.num("total_power_cap_w", 0.0, 100.0, d("total_power_cap_w"), unit="W",
                    open_lo=True)
    if power.sum() > cap:
        raise out_of_range("instrument.laser_power_w", f"summing to at most the total cap {cap} W",
                           float(power.sum()))
    snr_db = optional_num("snr_db", -80.0, 120.0, "dB")
    noise_rms = optional_num("noise_rms_v", 0.0, 1e3, "V")
    if snr_db is not None and noise_rms is not None:
        raise out_of_range("instrument.noise_rms_v", "absent when instrument.snr_db is given",
                           noise_rms)
    min_r = optional_num("min_range_m", 0.0, 1e5, "m")
    max_r = optional_num("max_range_m", 0.0, 1e5, "m")
    if min_r is not None and max_r is not None and max_r < min_r:
        raise out_of_range("instrument.max_range_m", f"at least min_range_m ({min_r})", max_r)
    spec = InstrumentSpec(
        wavelengths_m=wl, rotations_deg=rot,
        grooves_per_mm=grooves, incidence_deg=incidence, tilt_deg=tilt,
        # the announced grating defaults to the true one
        nominal_grooves_per_mm=r.num("nominal_grooves_per_mm", 1.0, 1e4, grooves,
                                     unit="lines/mm"),
        nominal_incidence_deg=r.num("nominal_incidence_deg", -89.0, 89.0, incidence, unit="deg"),
        nominal_tilt_deg=nominal_tilt,
        chip_rate_hz=r.num("chip_rate_hz", 1e3, 100e9, d("chip_rate_hz"), unit="Hz"),
        samples_per_chip=r.int("samples_per_chip", 1, 64, d("samples_per_chip")),
        averages=r.int("averages", 1, 1024, d("averages")),
        poly_u=poly_u, poly_v=poly_v, code_index=code_index,
        uid_bits=uid_bits, uid=uid, adc_bits=adc_bits,
        adc_gain=r.num("adc_gain", 0.0, 1e6, d("adc_gain"), open_lo=True),
        adc_offset=r.num("adc_offset", -(2.0 ** 15), 2.0 ** 15, d("adc_offset"), unit="codes"),
        adc_full_scale_v=r.num("adc_full_scale_v", 0.0, 1e3, d("adc_full_scale_v"), unit="V",
                               open_lo=True),
        laser_power_w=power, max_pixel_power_w=max_pixel, total_power_cap_w=cap,
        beam_waist_m=r.num("beam_waist_m", 0.0, 1.0, d("beam_waist_m"), unit="m"),
        beam_divergence_rad=r.num("beam_divergence_rad", 0.0, 1.0, d("beam_divergence_rad"),
                                  unit="rad"),
        rx_aperture_m=r.num("rx_aperture_m", 0.0, 10.0, d("rx_aperture_m"), unit="m",
                            open_lo=True),
        rx_efficiency=r.num("rx_efficiency", 0.0, 1.0, d("rx_efficiency"), open_lo=True),
        responsivity_a_per_w=r.num("responsivity_a_per_w", 0.0, 10.0, d("responsivity_a_per_w"),
                                   unit="A/W", open_lo=True),
        apd_gain=r.num("apd_gain", 1.0, 1e4, d("apd_gain")),
        apd_k_ratio=r.num("apd_k_ratio", 0.0, 1.0, d("apd_k_ratio")),
        dark_current_a=r.num("dark_current_a", 0.0, 1.0, d("dark_current_a"), unit="A"),
        tia_gain_ohm=r.num("tia_gain_ohm", 0.0, 1e12, d("tia_gain_ohm"), unit="ohm",
                           open_lo=True),
        tia_noise_a_per_rthz=r.num("tia_noise_a_per_rthz", 0.0, 1e-3, d("tia_noise_a_per_rthz"),
                                   unit="A/sqrt(Hz)"),
        edfa_gain_db=r.num("edfa_gain_db", 0.0, 60.0, d("edfa_gain_db"), unit="dB"),
        edfa_noise_figure_db=r.num("edfa_noise_figure_db", 3.0, 30.0, d("edfa_noise_figure_db"),
                                   unit="dB"),
        ambient_power_w=r.num("ambient_power_w", 0.0, 1.0, d("ambient_power_w"), unit="W"),
        speckle_cells=_speckle_cells(r),
        sequential_mixing=r.bool("sequential_mixing", d("sequential_mixing")),
        link_gain_v_m2_per_w=optional_num("link_gain_v_m2_per_w", 0.0, 1e12, "V m^2/W"),
        snr_db=snr_db, noise_rms_v=noise_rms,
        system_delay_s=r.num("system_delay_s", 0.0, 1e-3, d("system_delay_s"), unit="s"),
        detector_bandwidth_hz=r.num("detector_bandwidth_hz", 0.0, 1e12,
                                    d("detector_bandwidth_hz"), unit="Hz", open_lo=True),
        cancel_rounds=r.int("cancel_rounds", 0, MAX_CANCEL_ROUNDS, d("cancel_rounds")),
        # 0..72 dB: what the chain's u32 Q8 register holds (firmware_model.snr.snr_q8)
        cancel_snr_db=r.num("cancel_snr_db", 0.0, 72.0, d("cancel_snr_db"), unit="dB"),
        min_range_m=min_r, max_range_m=max_r,
        ghosts=_parse_ghosts(r.raw("ghosts"), "instrument.ghosts", k, c),
        other_users=_parse_users(r.raw("other_users"), "instrument.other_users", n_codes, c),
    )
    r.done()
    return spec


def _parse_object(table: Any, i: int) -> ObjectSpec:
    path = f"objects[{i}]"
    r = _Reader(table, path)

    def d(key: str) -> Any:
        return field_default(ObjectSpec, key)

    kind = r.str("kind", OBJECT_KINDS)
    common = dict(
        kind=kind,
        name=r.str("name", default=f"{kind}{i}"),
        position_m=r.vec("position_m", 3, -1e5, 1e5, unit="m"),
        orientation_deg=r.vec("orientation_deg", 3, -360.0, 360.0,
                              d("orientation_deg").tolist(), unit="deg"),
        reflectivity=r.num("reflectivity", 0.0, 1.0, d("reflectivity")),
    )
    if kind == "plane":
        size = r.vec("size_m", 2, 0.0, 1e5, unit="m") if r.has("size_m") else d("size_m")
        obj = ObjectSpec(**common, size_m=size)
    elif kind == "box":
        obj = ObjectSpec(**common, size_m=r.vec("size_m", 3, 1e-6, 1e5, unit="m"))
    elif kind == "sphere":
        obj = ObjectSpec(**common, radius_m=r.num("radius_m", 1e-6, 1e5, unit="m"))
    else:
        text = r.str("text")
        if not text.strip():
            raise out_of_range(f"{path}.text", "a non-blank string", text)
        obj = ObjectSpec(**common, text=text,
                         height_m=r.num("height_m", 1e-4, 100.0, unit="m"),
                         depth_m=r.num("depth_m", 0.0, 100.0, d("depth_m"), unit="m"),
                         font=r.str("font", default=d("font")))
    r.done()
    return obj


def _parse_calibration(table: Any) -> Calibration:
    r = _Reader(table, "calibration")

    def d(key: str) -> Any:
        return field_default(Calibration, key)

    cal = Calibration(
        target_distance_m=r.num("target_distance_m", 0.01, 1e3, d("target_distance_m"),
                                unit="m"),
        reflectivity=r.num("reflectivity", 0.0, 1.0, d("reflectivity")),
        zeroth_order_efficiency=r.num("zeroth_order_efficiency", 0.0, 1.0,
                                      d("zeroth_order_efficiency")))
    r.done()
    return cal


def parse_scene(doc: dict[str, Any], name: str = "scene") -> Scene:
    """Validate a parsed TOML document into a :class:`Scene` (``name`` if it names none)."""
    r = _Reader(doc, "")
    inst = _parse_instrument(r.raw("instrument"))
    objs_raw = r.raw("objects", [])
    if not isinstance(objs_raw, list):
        raise out_of_range("objects", "an array of tables ([[objects]])", objs_raw)
    objects = tuple(_parse_object(o, i) for i, o in enumerate(objs_raw))
    cal = _parse_calibration(r.raw("calibration", {}))
    scene = Scene(name=r.str("name", default=name), instrument=inst, objects=objects,
                  calibration=cal,
                  description=r.str("description", default=field_default(Scene, "description")),
                  fidelity=r.str("fidelity", FIDELITY_LEVELS, field_default(Scene, "fidelity")))
    r.done()
    return scene


# ---------------------------------------------------------------------------------------
# documents and options

def read_document(text: str, origin: str) -> dict[str, Any]:
    """Parse scene-file TOML ``text`` (``origin`` names it in the error message)."""
    try:
        return tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"scene {origin!r} is not valid TOML: {exc}", field="scene") from exc


def _coerce(text: str) -> Any:
    try:
        return tomllib.loads(f"v = {text}")["v"]
    except tomllib.TOMLDecodeError:
        return text


def parse_options(query: str) -> dict[str, Any]:
    """``a=1&b.c=x`` (the part of a scene name after ``?``) as {key: TOML value or string}.

    A key given twice keeps its last value.
    """
    return {k: _coerce(v[-1]) for k, v in urllib.parse.parse_qs(query).items()}


def _set_dotted(doc: dict[str, Any], key: str, value: Any) -> None:
    """Set ``a.b[2].c`` or ``objects[0].position_m[0]`` in a nested TOML document."""
    parts = key.split(".")
    node: Any = doc
    for i, part in enumerate(parts):
        m = re.fullmatch(r"([A-Za-z_][A-Za-z0-9_]*)((?:\[\d+\])*)", part)
        if m is None:
            raise KeyError(part)
        name, idx = m.group(1), [int(x) for x in re.findall(r"\d+", m.group(2))]
        last = i == len(parts) - 1
        if not idx:
            if last:
                node[name] = value
            else:
                node = node.setdefault(name, {})
            continue
        node = node[name]
        for j, ix in enumerate(idx):
            if last and j == len(idx) - 1:
                node[ix] = value
            else:
                node = node[ix]


def _shortcut_targets(key: str, target: Any, value: Any) -> list[str]:
    """The dotted fields a shortcut stands for, after checking ``value`` against its bounds.

    A shortcut is a dotted field, a list of them, or a table ``{ field = "...", min = 0.1,
    max = 1e4, unit = "m" }`` whose value must be a number in [min, max] (a distance of
    -3 m or 0 m names no physical scene).
    """
    if isinstance(target, dict):
        lo, hi = float(target.get("min", -math.inf)), float(target.get("max", math.inf))
        unit = str(target.get("unit", ""))
        allowed = f"a number from {lo:g} to {hi:g} {unit}".rstrip()
        if isinstance(value, bool) or not isinstance(value, int | float) \
                or not math.isfinite(value) or not lo <= value <= hi:
            raise out_of_range(f"scene option {key}", allowed, value)
        target = target["field"]
    return target if isinstance(target, list) else [target]


def apply_options(doc: dict[str, Any], options: dict[str, Any]) -> None:
    """Replace fields of ``doc`` in place; removes its ``[shortcuts]`` table.

    A key is one of the document's shortcuts (which may stand for a list of dotted fields,
    and may bound the value) or a dotted field itself.
    """
    shortcuts = doc.pop("shortcuts", {})
    for key, value in options.items():
        for t in _shortcut_targets(key, shortcuts.get(key, key), value):
            try:
                _set_dotted(doc, t, value)
            except (KeyError, IndexError, ValueError, TypeError) as exc:
                raise out_of_range("scene option", "a known field (e.g. instrument.snr_db)",
                                   key) from exc
