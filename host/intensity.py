r"""Per-point intensity: a reflectance estimate from the peak, the range and the power.

The echo of a pixel (scene model, paper eq. 3 and docs/scene.md) has the amplitude::

    A = G * P * rho * cos(theta) / r^2          (V at the detector)

with ``G`` the link gain of the instrument (optics, detector, ADC: one number per
device and configuration), ``P`` the pixel's laser power, ``rho`` the target's
reflectivity, ``theta`` its incidence angle and ``r`` the range. The correlation peak
is proportional to ``A`` (the processing gain of the configured code, averages and UID
periods, divided by ``2^out_shift``); dividing by that processing gain and by the
ADC's full scale::

    intensity = |peak| * 2^out_shift * r^2 / (P * N * S * M * B * 2^(adc_bits-1) * g)

with ``N`` the code length (chips), ``S`` samples per chip, ``M`` averages and ``B`` the
UID bits (code periods per symbol). ``P`` is the fraction of the per-pixel maximum the
pixel was scanned with (the near-far power matrix, or the uniform start power).

Without a gain (``g = 1``) the unit is :data:`RAW_UNIT`: the echo amplitude in ADC full
scales that the target would give at 1 m and full pixel power. It does not depend on
the code, samples per chip, averages, UID bits or ``out_shift``, only on the optics and
the target: flat-wall's 0.5-reflectance wall reads about 4.2 x 0.5 = 2.1. A device does
not announce its optical link gain (INFO carries powers, not responsivity or aperture),
so a reflectance needs ``g`` measured once on a flat target of known reflectivity
(``scan --calibrate-intensity R`` stores it in the calibration file,
:func:`intensity_gain`); then a flat target reads about ``rho cos(theta)`` (flat-wall:
0.5). The gain holds for the optics it was measured with.
"""

from __future__ import annotations

import logging
from collections.abc import Mapping
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from cdma_lidar.errors import ConfigError, out_of_range

__all__ = ["RAW_UNIT", "intensity", "intensity_gain", "processing_gain"]

log = logging.getLogger(__name__)


#: The unit of an uncalibrated intensity (module docstring).
RAW_UNIT = "ADC full scales at 1 m and full pixel power"


def processing_gain(config: Mapping[str, Any]) -> float:
    """Correlation peak (LSB) of a full-scale echo: ``N * S * M * B * 2^(adc_bits-1)``.

    ``N = 2^degree - 1`` chips (``poly_u[0]``), ``S`` samples per chip, ``M`` averages,
    ``B`` UID bits (one code period per UID bit), ``adc_bits`` signed ADC bits.
    """
    chips = (1 << int(config["poly_u"][0])) - 1
    return float(chips * int(config["samples_per_chip"]) * int(config.get("averages", 1))
                 * max(1, int(config.get("uid_bits", 1)))
                 * (1 << (int(config.get("adc_bits", 12)) - 1)))


def _raw(peak: ArrayLike, range_m: ArrayLike, power: ArrayLike,
         config: Mapping[str, Any]) -> NDArray[np.float64]:
    shift = int(config.get("out_shift", 0))
    a = (np.abs(np.asarray(peak, dtype=np.float64)) * float(2**shift)
         / processing_gain(config))
    r = np.asarray(range_m, dtype=np.float64)
    p = np.asarray(power, dtype=np.float64)
    with np.errstate(divide="ignore", invalid="ignore"):
        out = a * r * r / p
    return np.where(np.isfinite(out) & (p > 0), out, np.nan)


def intensity(peak: ArrayLike, range_m: ArrayLike, power: ArrayLike,
              config: Mapping[str, Any], gain: float | None = None) -> NDArray[np.float64]:
    """Reflectance estimate per pixel (module docstring); NaN where there is no range.

    ``peak`` in correlator units, ``range_m`` in m, ``power`` as a fraction of the
    per-pixel maximum (all broadcastable), ``config`` the device configuration.
    """
    if gain is not None and not (np.isfinite(gain) and gain > 0):
        raise out_of_range("intensity_gain", "finite and > 0", gain)
    return _raw(peak, range_m, power, config) / (1.0 if gain is None else gain)


def intensity_gain(peak: ArrayLike, range_m: ArrayLike, power: ArrayLike,
                   config: Mapping[str, Any], reflectivity: float,
                   valid: ArrayLike) -> float:
    """The gain ``g`` that makes the ``valid`` pixels of a flat target read ``reflectivity``.

    The median over the pixels is used (edges and partial pixels do not pull it).
    """
    if not (np.isfinite(reflectivity) and 0 < reflectivity <= 1):
        raise out_of_range("reflectivity", "in (0, 1]", reflectivity)
    raw = _raw(peak, range_m, power, config)[np.asarray(valid, bool)]
    raw = raw[np.isfinite(raw)]
    if raw.size < 10:
        raise ConfigError(f"the intensity calibration needs at least 10 valid pixels on the "
                          f"target, not {raw.size}", field="calibrate_intensity")
    gain = float(np.median(raw)) / reflectivity
    log.info("intensity gain %.6g from %d pixels (spread %.1f %%)", gain, raw.size,
             100 * float(np.std(raw) / np.median(raw)))
    return gain
