"""Scene description: the instrument's true parameters and the objects in front of it.

A scene is a TOML file (or a built-in preset loaded by name) with two parts::

    name = "flat-wall"
    [instrument]                 # the simulated board, optics and photodiode (true values)
    wavelengths = { start_m = 1570e-9, spacing_m = 0.875e-9, count = 40 }
    azimuth_deg = [-5.0, 5.0]    # first and last column, or rotations_deg = [...]
    columns = 160
    ...
    [[objects]]                  # planes, boxes, spheres, extruded text
    kind = "plane"
    position_m = [5.0, 0.0, 0.0]
    ...

Every field is checked once at load time; a bad value raises ``ConfigError`` naming the
dotted field (``objects[3].radius_m``) and its allowed range. Units: metres, seconds,
watts, volts, degrees, hertz; lags in samples, codes in chips.

Frames: the sensor frame of :mod:`cdma_lidar.optics.grating` (x forward, y left, z up, origin at the
grating) is the scene's global frame. Object orientation is ``[yaw, pitch, roll]`` in
degrees, applied as R = Rz(yaw) @ Ry(pitch) @ Rx(roll) to the object's local axes.
"""

from __future__ import annotations

import math
import re
import tomllib
import urllib.parse
from dataclasses import dataclass, field, replace
from importlib import resources
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import NDArray

from cdma_lidar.errors import ConfigError, out_of_range

if TYPE_CHECKING:  # imported at call time in geometry(): scene does not load host at import
    from cdma_lidar.optics.grating import GratingGeometry

__all__ = [
    "PRESETS",
    "SPEED_OF_LIGHT_M_S",
    "Calibration",
    "Ghost",
    "InstrumentSpec",
    "ObjectSpec",
    "OtherUser",
    "Scene",
    "load_scene",
    "parse_scene",
    "rotation_matrix",
]

SPEED_OF_LIGHT_M_S = 299_792_458.0

#: Built-in scenes, loadable by name (files in ``scene/presets``).
PRESETS = ("paper-scene1", "paper-scene2", "near-far", "flat-wall", "multi-user", "calibration")

_OBJECT_KINDS = ("plane", "box", "sphere", "text")


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
        value = self.raw(key, default)
        if isinstance(value, bool) or not isinstance(value, int) or not lo <= value <= hi:
            raise out_of_range(self.name(key), f"an integer from {lo} to {hi}", value)
        return int(value)

    def str(self, key: str, choices: tuple[str, ...] | None = None,
            default: str | None = None) -> str:
        value = self.raw(key, default)
        if not isinstance(value, str) or (choices is not None and value not in choices):
            allowed = "a string" if choices is None else "one of " + ", ".join(choices)
            raise out_of_range(self.name(key), allowed, value)
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


def rotation_matrix(yaw_pitch_roll_deg: NDArray[np.float64]) -> NDArray[np.float64]:
    """R = Rz(yaw) @ Ry(pitch) @ Rx(roll) (deg); columns are the local axes in the scene frame."""
    y, p, r = np.deg2rad(np.asarray(yaw_pitch_roll_deg, dtype=np.float64))
    rz = np.array([[np.cos(y), -np.sin(y), 0.0], [np.sin(y), np.cos(y), 0.0], [0.0, 0.0, 1.0]])
    ry = np.array([[np.cos(p), 0.0, np.sin(p)], [0.0, 1.0, 0.0], [-np.sin(p), 0.0, np.cos(p)]])
    rx = np.array([[1.0, 0.0, 0.0], [0.0, np.cos(r), -np.sin(r)], [0.0, np.sin(r), np.cos(r)]])
    return rz @ ry @ rx


# ---------------------------------------------------------------------------------------
# the instrument

@dataclass(frozen=True)
class Ghost:
    """A grating ghost: a fixed-distance spurious echo with the channel's own code (Note 5).

    Present at every pixel (channel, column) with channel in ``channels`` and column in
    ``columns`` (empty tuple: every channel / every column). Its amplitude does not fall
    with the target's distance.
    """

    distance_m: float
    amplitude_v: float
    channels: tuple[int, ...] = ()
    columns: tuple[int, ...] = ()


@dataclass(frozen=True)
class OtherUser:
    """Another LiDAR whose light reaches our photodiode (Note 11).

    It emits Gold member ``code_index`` of the same pair, polarity-modulated by its own
    ``uid`` over ``uid_bits`` code periods. ``delay_s`` is the start of its UID frame
    relative to ours as seen at our ADC (its asynchronous start plus the one-way flight:
    in the TOML, ``distance_m`` gives ``delay_s = distance_m / c``); ``amplitude_v`` is its
    amplitude at our detector. Present on every column in ``columns`` (empty: all).
    """

    uid: int
    code_index: int
    delay_s: float
    amplitude_v: float
    uid_bits: int = 3
    columns: tuple[int, ...] = ()


@dataclass(frozen=True)
class Calibration:
    """The zeroth-order beam-trap target (Note 6): all channels see it in calibration mode."""

    target_distance_m: float = 0.5
    reflectivity: float = 0.9
    #: fraction of each channel's power that goes to the zeroth order and back (two passes)
    zeroth_order_efficiency: float = 0.02


@dataclass(frozen=True)
class InstrumentSpec:
    """True parameters of the simulated instrument; ``nominal_*`` is what it announces.

    Signal chain per pixel: received modulated amplitude (V at the ADC input)
    ``A = link_gain_v_m2_per_w * P_tx * reflectivity * cos(incidence) / r**2``; the detector
    output is ``A * code(t - tau)`` (bipolar NRZ, AC coupled) filtered by the detector's
    transfer function; the ADC maps volts to codes with ``round(gain * v / lsb + offset)``,
    ``lsb = adc_full_scale_v / 2**(adc_bits - 1)``, clipped to ``adc_bits``.
    """

    wavelengths_m: NDArray[np.float64]
    rotations_deg: NDArray[np.float64]
    grooves_per_mm: float = 600.0
    incidence_deg: float = 60.0
    tilt_deg: float | None = None
    nominal_grooves_per_mm: float = 600.0
    nominal_incidence_deg: float = 60.0
    nominal_tilt_deg: float | None = None
    chip_rate_hz: float = 62.5e6
    samples_per_chip: int = 4
    averages: int = 10
    code_degree: int = 11
    poly_u: tuple[int, ...] = (11, 2)
    poly_v: tuple[int, ...] = (11, 8, 5, 2)
    code_index: tuple[int, ...] | None = None
    uid_bits: int = 1
    uid: int = 0
    adc_bits: int = 12
    adc_gain: float = 1.0
    adc_offset: float = 0.0
    adc_full_scale_v: float = 1.0
    laser_power_w: NDArray[np.float64] = field(default_factory=lambda: np.full(40, 2.5e-3))
    max_pixel_power_w: float = 10e-3
    total_power_cap_w: float = 0.2
    link_gain_v_m2_per_w: float = 500.0
    #: per-sample SNR (dB) of the median lit pixel's echo (at the scene's laser power)
    #: against the Gaussian noise; exclusive with noise_rms_v
    snr_db: float | None = None
    noise_rms_v: float | None = 0.0
    system_delay_s: float = 37.3e-9
    detector_bandwidth_hz: float = 200e6
    min_range_m: float | None = None
    max_range_m: float | None = None
    ghosts: tuple[Ghost, ...] = ()
    other_users: tuple[OtherUser, ...] = ()

    @property
    def channels(self) -> int:
        """Number of wavelength channels K."""
        return int(self.wavelengths_m.size)

    @property
    def columns(self) -> int:
        """Number of grating rotations (columns) C."""
        return int(self.rotations_deg.size)

    @property
    def code_length(self) -> int:
        """Code period N (chips)."""
        return (1 << self.code_degree) - 1

    @property
    def code_indices(self) -> tuple[int, ...]:
        """Gold member used by each channel (default: channel k uses member k)."""
        return self.code_index if self.code_index is not None else tuple(range(self.channels))

    def geometry(self, nominal: bool = False) -> GratingGeometry:
        """The grating geometry: true (what the light does) or nominal (what the host assumes)."""
        from cdma_lidar.optics.grating import GratingGeometry

        if nominal:
            return GratingGeometry(self.nominal_grooves_per_mm, self.nominal_incidence_deg,
                                   self.nominal_tilt_deg)
        return GratingGeometry(self.grooves_per_mm, self.incidence_deg, self.tilt_deg)


@dataclass(frozen=True)
class ObjectSpec:
    """One object: ``kind`` plane, box, sphere or text, posed by position and orientation.

    Local frames: a plane is the local y-z plane through ``position_m`` facing local -x
    (towards the sensor when unrotated), limited to ``size_m`` = (width along y, height along
    z) if given; a box is centred at ``position_m`` with edge lengths ``size_m`` along its
    local x, y, z; a sphere has ``radius_m``; text is drawn in the local y-z plane (reading
    along -y, i.e. left to right as the sensor sees it, up along z), its front face at
    ``position_m`` facing -x, centred there, ``height_m`` tall (ink box), extruded
    ``depth_m`` along +x.
    """

    kind: str
    position_m: NDArray[np.float64]
    orientation_deg: NDArray[np.float64]
    reflectivity: float
    name: str = ""
    size_m: NDArray[np.float64] | None = None
    radius_m: float = 0.0
    text: str = ""
    height_m: float = 0.0
    depth_m: float = 0.0
    font: str = "DejaVu Sans"

    @property
    def rotation(self) -> NDArray[np.float64]:
        """Local-to-scene rotation matrix."""
        return rotation_matrix(self.orientation_deg)


@dataclass(frozen=True)
class Scene:
    """A validated scene: the instrument, the objects, the calibration target."""

    name: str
    instrument: InstrumentSpec
    objects: tuple[ObjectSpec, ...]
    calibration: Calibration = Calibration()
    description: str = ""

    def with_instrument(self, **changes: Any) -> Scene:
        """A copy with instrument fields replaced (no re-validation: callers pass valid values)."""
        return replace(self, instrument=replace(self.instrument, **changes))


# ---------------------------------------------------------------------------------------
# parsing

def _parse_wavelengths(r: _Reader) -> NDArray[np.float64]:
    if r.has("wavelengths_m"):
        return r.nums("wavelengths_m", 100e-9, 20e-6, max_len=1024, unit="m")
    w = r.sub("wavelengths")
    if w is None:
        w = _Reader({}, r.name("wavelengths"))
    start = w.num("start_m", 100e-9, 20e-6, 1570e-9, unit="m")
    spacing = w.num("spacing_m", -1e-6, 1e-6, 0.875e-9, unit="m")
    count = w.int("count", 1, 1024, 40)
    w.done()
    return start + spacing * np.arange(count, dtype=np.float64)


def _parse_rotations(r: _Reader, geometry_kw: dict[str, Any]) -> NDArray[np.float64]:
    if r.has("rotations_deg"):
        return r.nums("rotations_deg", -60.0, 60.0, max_len=100_000, unit="deg")
    from cdma_lidar.optics.grating import GratingGeometry

    az = r.vec("azimuth_deg", 2, -60.0, 60.0, [-5.0, 5.0], unit="deg")
    cols = r.int("columns", 1, 100_000, 160)
    geom = GratingGeometry(**geometry_kw)
    # column 0 is the leftmost as the sensor sees it (largest azimuth, +y); the stage steps
    # the rotation uniformly between the rotations that aim the reference wavelength at the
    # two ends of the field (so a column's angle is start + step * column)
    ends = np.array([az[1], az[0]]) if cols > 1 else np.array([az.mean()])
    try:
        rot_ends = geom.rotations_for_azimuths(ends)
    except ConfigError as exc:
        raise ConfigError(f"{r.name('azimuth_deg')}: {exc}", field=r.name("azimuth_deg")) from exc
    return np.linspace(rot_ends[0], rot_ends[-1], cols)


def _parse_ghosts(value: Any, path: str, k: int, c: int) -> tuple[Ghost, ...]:
    if value is None:
        return ()
    if not isinstance(value, list):
        raise out_of_range(path, "an array of tables", value)
    out = []
    for i, item in enumerate(value):
        g = _Reader(item, f"{path}[{i}]")
        chans = tuple(int(x) for x in g.nums("channels", 0, k - 1, min_len=0, integer=True)) \
            if g.has("channels") else ()
        cols = tuple(int(x) for x in g.nums("columns", 0, c - 1, min_len=0, integer=True)) \
            if g.has("columns") else ()
        out.append(Ghost(distance_m=g.num("distance_m", 0.0, 1e4, unit="m"),
                         amplitude_v=g.num("amplitude_v", 0.0, 1e3, unit="V"),
                         channels=chans, columns=cols))
        g.done()
    return tuple(out)


def _parse_users(value: Any, path: str, n_codes: int, c: int) -> tuple[OtherUser, ...]:
    if value is None:
        return ()
    if not isinstance(value, list):
        raise out_of_range(path, "an array of tables", value)
    out = []
    for i, item in enumerate(value):
        u = _Reader(item, f"{path}[{i}]")
        bits = u.int("uid_bits", 1, 16, 3)
        uid = u.int("uid", 0, (1 << bits) - 1)
        if u.has("delay_s"):
            delay = u.num("delay_s", 0.0, 1.0, unit="s")
        else:
            delay = u.num("distance_m", 0.0, 1e5, unit="m") / SPEED_OF_LIGHT_M_S
        cols = tuple(int(x) for x in u.nums("columns", 0, c - 1, min_len=0, integer=True)) \
            if u.has("columns") else ()
        out.append(OtherUser(uid=uid, code_index=u.int("code_index", 0, n_codes - 1, 0),
                             delay_s=delay, amplitude_v=u.num("amplitude_v", 0.0, 1e3, unit="V"),
                             uid_bits=bits, columns=cols))
        u.done()
    return tuple(out)


def _parse_poly(r: _Reader, key: str, default: tuple[int, ...]) -> tuple[int, ...]:
    if not r.has(key):
        r.used.add(key)
        return default
    arr = r.nums(key, 1, 32, min_len=2, max_len=33, integer=True)
    poly = tuple(int(x) for x in arr)
    if list(poly) != sorted(set(poly), reverse=True):
        raise out_of_range(r.name(key), "exponents in strictly decreasing order", list(poly))
    return poly


def _parse_instrument(table: Any) -> InstrumentSpec:
    r = _Reader(table if table is not None else {}, "instrument")
    wl = _parse_wavelengths(r)
    k = wl.size
    tilt = r.num("tilt_deg", -180.0, 180.0, unit="deg") if r.has("tilt_deg") else None
    geometry_kw = dict(grooves_per_mm=r.num("grooves_per_mm", 1.0, 1e4, 600.0, unit="lines/mm"),
                       incidence_deg=r.num("incidence_deg", -89.0, 89.0, 60.0, unit="deg"),
                       tilt_deg=tilt)
    nominal_tilt = r.num("nominal_tilt_deg", -180.0, 180.0, unit="deg") \
        if r.has("nominal_tilt_deg") else None
    rot = _parse_rotations(r, geometry_kw)
    c = rot.size
    poly_u = _parse_poly(r, "poly_u", (11, 2))
    poly_v = _parse_poly(r, "poly_v", (11, 8, 5, 2))
    if poly_u[0] != poly_v[0]:
        raise out_of_range("instrument.poly_v", f"of the same degree as poly_u ({poly_u[0]})",
                           list(poly_v))
    degree = poly_u[0]
    if not 3 <= degree <= 20:
        raise out_of_range("instrument.poly_u", "a polynomial of degree 3 to 20", list(poly_u))
    n_codes = (1 << degree) + 1
    code_index = None
    if r.has("code_index"):
        code_index = tuple(int(x) for x in r.nums("code_index", 0, n_codes - 1, min_len=k,
                                                   max_len=k, integer=True))
    uid_bits = r.int("uid_bits", 1, 16, 1)
    uid = r.int("uid", 0, (1 << uid_bits) - 1, 0)
    adc_bits = r.int("adc_bits", 8, 16, 12)
    max_pixel = r.num("max_pixel_power_w", 0.0, 10.0, 10e-3, unit="W", open_lo=True)
    if r.has("laser_power_w") and isinstance(r.table["laser_power_w"], list):
        power = r.nums("laser_power_w", 0.0, max_pixel, min_len=k, max_len=k, unit="W")
    else:
        power = np.full(k, r.num("laser_power_w", 0.0, max_pixel, 2.5e-3, unit="W"))
    cap = r.num("total_power_cap_w", 0.0, 100.0, 0.2, unit="W", open_lo=True)
    if power.sum() > cap:
        raise out_of_range("instrument.laser_power_w", f"summing to at most the total cap {cap} W",
                           float(power.sum()))
    snr_db = r.num("snr_db", -80.0, 120.0, unit="dB") if r.has("snr_db") else None
    noise_rms = None
    if snr_db is None:
        noise_rms = r.num("noise_rms_v", 0.0, 1e3, 0.0, unit="V")
    elif r.has("noise_rms_v"):
        raise out_of_range("instrument.noise_rms_v", "absent when instrument.snr_db is given",
                           r.raw("noise_rms_v"))
    min_r = r.num("min_range_m", 0.0, 1e5, unit="m") if r.has("min_range_m") else None
    max_r = r.num("max_range_m", 0.0, 1e5, unit="m") if r.has("max_range_m") else None
    if min_r is not None and max_r is not None and max_r < min_r:
        raise out_of_range("instrument.max_range_m", f"at least min_range_m ({min_r})", max_r)
    spec = InstrumentSpec(
        wavelengths_m=wl, rotations_deg=rot,
        grooves_per_mm=geometry_kw["grooves_per_mm"], incidence_deg=geometry_kw["incidence_deg"],
        tilt_deg=tilt,
        nominal_grooves_per_mm=r.num("nominal_grooves_per_mm", 1.0, 1e4,
                                     geometry_kw["grooves_per_mm"], unit="lines/mm"),
        nominal_incidence_deg=r.num("nominal_incidence_deg", -89.0, 89.0,
                                    geometry_kw["incidence_deg"], unit="deg"),
        nominal_tilt_deg=nominal_tilt,
        chip_rate_hz=r.num("chip_rate_hz", 1e3, 100e9, 62.5e6, unit="Hz"),
        samples_per_chip=r.int("samples_per_chip", 1, 64, 4),
        averages=r.int("averages", 1, 1024, 10),
        code_degree=degree, poly_u=poly_u, poly_v=poly_v, code_index=code_index,
        uid_bits=uid_bits, uid=uid, adc_bits=adc_bits,
        adc_gain=r.num("adc_gain", 0.0, 1e6, 1.0, open_lo=True),
        adc_offset=r.num("adc_offset", -(2.0 ** 15), 2.0 ** 15, 0.0, unit="codes"),
        adc_full_scale_v=r.num("adc_full_scale_v", 0.0, 1e3, 1.0, unit="V", open_lo=True),
        laser_power_w=power, max_pixel_power_w=max_pixel, total_power_cap_w=cap,
        link_gain_v_m2_per_w=r.num("link_gain_v_m2_per_w", 0.0, 1e12, 500.0, unit="V m^2/W"),
        snr_db=snr_db, noise_rms_v=noise_rms,
        system_delay_s=r.num("system_delay_s", 0.0, 1e-3, 37.3e-9, unit="s"),
        detector_bandwidth_hz=r.num("detector_bandwidth_hz", 0.0, 1e12, 200e6, unit="Hz",
                                    open_lo=True),
        min_range_m=min_r, max_range_m=max_r,
        ghosts=_parse_ghosts(r.raw("ghosts"), "instrument.ghosts", k, c),
        other_users=_parse_users(r.raw("other_users"), "instrument.other_users", n_codes, c),
    )
    r.done()
    return spec


def _parse_object(table: Any, i: int) -> ObjectSpec:
    path = f"objects[{i}]"
    r = _Reader(table, path)
    kind = r.str("kind", _OBJECT_KINDS)
    common = dict(
        kind=kind,
        name=r.str("name", default=f"{kind}{i}"),
        position_m=r.vec("position_m", 3, -1e5, 1e5, unit="m"),
        orientation_deg=r.vec("orientation_deg", 3, -360.0, 360.0, [0.0, 0.0, 0.0], unit="deg"),
        reflectivity=r.num("reflectivity", 0.0, 1.0, 0.5),
    )
    if kind == "plane":
        size = r.vec("size_m", 2, 0.0, 1e5, unit="m") if r.has("size_m") else None
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
                         depth_m=r.num("depth_m", 0.0, 100.0, 0.02, unit="m"),
                         font=r.str("font", default="DejaVu Sans"))
    r.done()
    return obj


def parse_scene(doc: dict[str, Any], name: str = "scene") -> Scene:
    """Validate a parsed TOML document into a :class:`Scene`."""
    r = _Reader(doc, "")
    inst = _parse_instrument(r.raw("instrument"))
    objs_raw = r.raw("objects", [])
    if not isinstance(objs_raw, list):
        raise out_of_range("objects", "an array of tables ([[objects]])", objs_raw)
    objects = tuple(_parse_object(o, i) for i, o in enumerate(objs_raw))
    cal_r = _Reader(r.raw("calibration", {}), "calibration")
    cal = Calibration(target_distance_m=cal_r.num("target_distance_m", 0.01, 1e3, 0.5, unit="m"),
                      reflectivity=cal_r.num("reflectivity", 0.0, 1.0, 0.9),
                      zeroth_order_efficiency=cal_r.num("zeroth_order_efficiency", 0.0, 1.0,
                                                        0.02))
    cal_r.done()
    scene = Scene(name=r.str("name", default=name), instrument=inst, objects=objects,
                  calibration=cal, description=r.str("description", default=""))
    r.done()
    return scene


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


def _coerce(text: str) -> Any:
    try:
        return tomllib.loads(f"v = {text}")["v"]
    except tomllib.TOMLDecodeError:
        return text


def load_scene(name_or_path: str | Path, overrides: dict[str, Any] | None = None) -> Scene:
    """Load a preset by name (``flat-wall``, optionally ``flat-wall?distance=7.5``) or a TOML file.

    Query options after ``?`` (and ``overrides``) replace fields before validation: a preset's
    own shortcuts (``distance`` for ``flat-wall``) or any dotted field such as
    ``instrument.snr_db=-10`` or ``objects[0].reflectivity=0.2``.
    """
    text = str(name_or_path)
    base, _, query = text.partition("?")
    opts: dict[str, Any] = {k: _coerce(v[-1]) for k, v in urllib.parse.parse_qs(query).items()}
    opts.update(overrides or {})
    path = Path(base)
    if base in PRESETS:
        raw = resources.files("cdma_lidar.scene").joinpath("presets", f"{base}.toml").read_text("utf-8")
    elif path.suffix == ".toml" or path.exists():
        try:
            raw = path.read_text("utf-8")
        except OSError as exc:
            raise ConfigError(f"scene file {base!r} cannot be read ({exc.strerror})",
                              field="scene") from exc
    else:
        raise out_of_range("scene", "a preset (" + ", ".join(PRESETS) + ") or a .toml file", base)
    try:
        doc = tomllib.loads(raw)
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"scene {base!r} is not valid TOML: {exc}", field="scene") from exc
    shortcuts = doc.pop("shortcuts", {})
    for key, value in opts.items():
        target = shortcuts.get(key, key)
        targets = target if isinstance(target, list) else [target]
        for t in targets:
            try:
                _set_dotted(doc, t, value)
            except (KeyError, IndexError, ValueError, TypeError) as exc:
                raise out_of_range("scene option", "a known field (e.g. instrument.snr_db)",
                                   key) from exc
    return parse_scene(doc, name=path.stem if base not in PRESETS else base)
