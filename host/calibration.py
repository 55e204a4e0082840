"""System-delay calibration on the zeroth-order beam (Supplementary Note 6).

Fibres, electronics and the detector add a fixed delay that pure theory cannot
predict. The zeroth diffraction order does not move with wavelength or rotation, so
with the grating in calibration mode every channel sees the same flat target at a
known distance. Repeated shots give a histogram of uncalibrated ranges; its centre
minus the known distance is the system offset (m) that every later range loses.

The histogram must be one narrow mode. Values are sorted and split into clusters
wherever two neighbours are more than ``gap_m`` apart (default: one lag sample of
range); clusters holding less than ``min_fraction`` of the values are outliers. Two
or more real clusters mean something else is in the beam (multimodal: error); a
main cluster whose standard deviation exceeds ``max_spread_m`` means the target is
too weak or moving (too wide: error). Both raise :class:`CalibrationError` saying so.

The result is a TOML file (written atomically with tomli_w, read with tomllib)::

    offset_m = 3.2104          # subtract from every range
    spread_m = 0.012           # standard deviation of the main mode
    target_distance_m = 1.5
    shots = 100
    samples = 4000             # range values in the histogram (shots x channels)
    date = "2026-11-21T09:30:00+00:00"
    intensity_gain = 8.3       # optional: scan --calibrate-intensity R on a flat target
    [device]      ...          # identity reported by the device (INFO)
    [configuration] ...        # the configuration the calibration holds for
"""

from __future__ import annotations

import datetime as _dt
import logging
import math
import os
import tomllib
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import tomli_w
from numpy.typing import ArrayLike

from cdma_lidar.errors import CalibrationError, ConfigError, out_of_range
from cdma_lidar.fileio import atomic_write_text

# the target distances (m) a zeroth-order beam trap can sit at (the scene file's range)
from cdma_lidar.host.settings import TARGET_DISTANCE_M

__all__ = [
    "CALIBRATION_KEYS",
    "TARGET_DISTANCE_M",
    "Calibration",
    "HistogramResult",
    "analyse_histogram",
    "toml_safe",
]

log = logging.getLogger(__name__)


#: Configuration fields that change the system delay or the lag-to-range scale; a
#: calibration applies only where all of those present in the file are equal.
CALIBRATION_KEYS = (
    "chip_rate_hz", "samples_per_chip", "poly_u", "poly_v", "code_degree", "code_length",
    "code_index", "channels", "adc_bits", "uid_bits", "uid", "out_shift", "rounding",
)


@dataclass(frozen=True)
class HistogramResult:
    """Centre (m), spread (m, standard deviation), values kept and outliers dropped."""

    centre_m: float
    spread_m: float
    kept: int
    outliers: int
    modes_m: tuple[float, ...]


def analyse_histogram(ranges_m: ArrayLike, *, gap_m: float, max_spread_m: float,
                      min_fraction: float = 0.1, min_values: int = 5) -> HistogramResult:
    """Find the one mode of a calibration histogram, or raise CalibrationError.

    ``ranges_m`` are uncalibrated ranges (m); NaNs (no detection) are ignored.
    """
    if not (gap_m > 0 and max_spread_m > 0):
        raise out_of_range("gap_m/max_spread_m", "> 0 m", (gap_m, max_spread_m))
    if not 0 < min_fraction < 1:
        raise out_of_range("min_fraction", "in (0, 1)", min_fraction)
    r = np.sort(np.asarray(ranges_m, dtype=np.float64).ravel())
    r = r[np.isfinite(r)]
    if r.size < min_values:
        raise CalibrationError(
            f"only {r.size} usable returns from the calibration target (need {min_values}); "
            "check the target is in the zeroth-order beam and lower --snr-threshold if needed")
    cuts = np.flatnonzero(np.diff(r) > gap_m) + 1
    clusters = np.split(r, cuts)
    big = [c for c in clusters if c.size >= min_fraction * r.size]
    modes = tuple(float(np.median(c)) for c in big)
    if len(big) != 1:
        desc = ", ".join(f"{float(np.median(c)):.3f} m ({c.size} values)" for c in big)
        raise CalibrationError(
            f"calibration histogram is multimodal: {len(big)} modes at {desc}; "
            "make sure only the calibration target is in the beam"
            if big else "calibration histogram has no dominant mode; returns are scattered")
    main = big[0]
    spread = float(np.std(main))
    if spread > max_spread_m:
        raise CalibrationError(
            f"calibration histogram is too wide: spread {spread:.3f} m exceeds "
            f"{max_spread_m:.3f} m; use a brighter or closer target, or more averages")
    return HistogramResult(centre_m=float(np.mean(main)), spread_m=spread, kept=int(main.size),
                           outliers=int(r.size - main.size), modes_m=modes)


def toml_safe(value: Any) -> Any:
    """Convert numpy scalars/arrays, tuples and None into TOML-writable values."""
    if isinstance(value, Mapping):
        return {str(k): toml_safe(v) for k, v in value.items() if v is not None}
    if isinstance(value, np.ndarray):
        return [toml_safe(v) for v in value.tolist()]
    if isinstance(value, list | tuple):
        return [toml_safe(v) for v in value if v is not None]
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, bytes):
        return value.hex()
    if isinstance(value, float) and not math.isfinite(value):
        return str(value)
    return value


def _norm(value: Any) -> Any:
    """Normalise for comparison: lists and tuples alike, ints and floats alike."""
    v = toml_safe(value)
    if isinstance(v, list):
        return [_norm(x) for x in v]
    if isinstance(v, bool | str) or v is None:
        return v
    if isinstance(v, int | float):
        return float(v)
    if isinstance(v, Mapping):
        return {k: _norm(x) for k, x in v.items()}
    return v


@dataclass
class Calibration:
    """A system-delay calibration: offset (m) for one device and configuration.

    ``intensity_gain`` (optional) makes the per-point intensity a reflectance estimate
    (:mod:`cdma_lidar.host.intensity`); ``scan --calibrate-intensity R`` measures it on a
    flat target of reflectivity R and adds it to the file.
    """

    offset_m: float
    spread_m: float
    target_distance_m: float
    shots: int
    samples: int
    device: dict[str, Any] = field(default_factory=dict)
    configuration: dict[str, Any] = field(default_factory=dict)
    date: str = ""
    intensity_gain: float | None = None

    @classmethod
    def from_ranges(cls, ranges_m: ArrayLike, target_distance_m: float, *, shots: int,
                    gap_m: float, max_spread_m: float, device: Mapping[str, Any] | None = None,
                    configuration: Mapping[str, Any] | None = None) -> Calibration:
        """Calibrate from uncalibrated ranges (m) of the zeroth-order target."""
        if not (math.isfinite(target_distance_m)
                and TARGET_DISTANCE_M[0] <= target_distance_m <= TARGET_DISTANCE_M[1]):
            raise out_of_range("target_distance", f"from {TARGET_DISTANCE_M[0]:g} to "
                               f"{TARGET_DISTANCE_M[1]:g} m", target_distance_m)
        hist = analyse_histogram(ranges_m, gap_m=gap_m, max_spread_m=max_spread_m)
        offset = hist.centre_m - target_distance_m
        if offset < 0:  # the system delay only adds range: the target is nearer than said
            raise CalibrationError(
                f"--target-distance {target_distance_m:g} m disagrees with the target "
                f"measured at {hist.centre_m:.4f} m (uncalibrated, system delay included): "
                f"the offset would be negative ({offset:.4f} m); give the target's distance")
        log.info("calibration: centre %.4f m, spread %.4f m, offset %.4f m (%d values, %d "
                 "outliers)", hist.centre_m, hist.spread_m, offset, hist.kept, hist.outliers)
        return cls(offset_m=offset, spread_m=hist.spread_m,
                   target_distance_m=float(target_distance_m), shots=int(shots),
                   samples=hist.kept, device=toml_safe(dict(device or {})),
                   configuration=toml_safe(dict(configuration or {})),
                   date=_dt.datetime.now(_dt.UTC).isoformat(timespec="seconds"))

    def to_dict(self) -> dict[str, Any]:
        """The TOML document as a dict."""
        return {
            "offset_m": float(self.offset_m), "spread_m": float(self.spread_m),
            "target_distance_m": float(self.target_distance_m), "shots": int(self.shots),
            "samples": int(self.samples), "date": self.date,
            "device": toml_safe(self.device), "configuration": toml_safe(self.configuration),
        } | ({} if self.intensity_gain is None
             else {"intensity_gain": float(self.intensity_gain)})

    def save(self, path: str | os.PathLike[str]) -> None:
        """Write the calibration as TOML, atomically."""
        atomic_write_text(path, tomli_w.dumps(self.to_dict()))

    @classmethod
    def load(cls, path: str | os.PathLike[str]) -> Calibration:
        """Read a calibration file; a missing or malformed file is a ConfigError."""
        p = Path(path)
        try:
            doc = tomllib.loads(p.read_text(encoding="utf-8"))
        except FileNotFoundError as exc:
            raise ConfigError(f"calibration file {str(p)!r} does not exist; run "
                              "'cdma-lidar calibrate' first", field="calibration") from exc
        except (tomllib.TOMLDecodeError, UnicodeDecodeError) as exc:
            raise ConfigError(f"calibration file {str(p)!r} is not valid TOML ({exc}); make "
                              "a new one with 'cdma-lidar calibrate'", field="calibration"
                              ) from exc
        except OSError as exc:  # a folder, a symlink loop, no permission
            raise ConfigError(f"calibration file {str(p)!r} cannot be read ({exc.strerror}); "
                              "give the TOML file 'cdma-lidar calibrate' wrote",
                              field="calibration") from None
        try:
            cal = cls(offset_m=float(doc["offset_m"]), spread_m=float(doc["spread_m"]),
                       target_distance_m=float(doc["target_distance_m"]),
                       shots=int(doc["shots"]), samples=int(doc.get("samples", 0)),
                       device=dict(doc.get("device", {})),
                       configuration=dict(doc.get("configuration", {})),
                       date=str(doc.get("date", "")),
                       intensity_gain=(float(doc["intensity_gain"])
                                       if "intensity_gain" in doc else None))
        except KeyError as exc:
            raise ConfigError(f"calibration file {str(p)!r} lacks the field {exc}; make a new "
                              "one with 'cdma-lidar calibrate'", field="calibration") from exc
        except (TypeError, ValueError) as exc:
            raise ConfigError(f"calibration file {str(p)!r} has a field of the wrong type "
                              f"({exc}); make a new one with 'cdma-lidar calibrate'",
                              field="calibration") from exc
        for name, ok, allowed in (
                ("offset_m", math.isfinite(cal.offset_m), "a finite number of m"),
                ("spread_m", math.isfinite(cal.spread_m) and cal.spread_m >= 0, ">= 0 m"),
                ("shots", cal.shots >= 1, "at least 1")):
            if not ok:
                raise ConfigError(f"calibration file {str(p)!r}: {name} must be {allowed}, "
                                  f"not {getattr(cal, name)!r}; make a new one with "
                                  "'cdma-lidar calibrate'", field="calibration")
        return cal

    def check_applies(self, device: Mapping[str, Any],
                      configuration: Mapping[str, Any]) -> None:
        """Raise CalibrationError unless this calibration was made on ``device`` and config.

        Every identity field recorded in the file must match the device's; of the
        configuration, the fields in :data:`CALIBRATION_KEYS` recorded in the file must match.
        """
        for key, want in self.device.items():
            have = device.get(key)
            if _norm(have) != _norm(want):
                raise CalibrationError(
                    f"calibration was made on another device ({key} {want!r}, this device has "
                    f"{have!r}); run 'cdma-lidar calibrate' on this device")
        for key in CALIBRATION_KEYS:
            if key not in self.configuration:
                continue
            want, have = self.configuration[key], configuration.get(key)
            if _norm(have) != _norm(want):
                raise CalibrationError(
                    f"calibration was made with another configuration ({key} {want!r}, now "
                    f"{have!r}); calibrate again with this configuration")
