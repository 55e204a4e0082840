r"""Grating scanner geometry: channel wavelength and grating rotation to a ray direction.

Supplementary Note 10, eqs. 45 to 49. One collimated beam of wavelength
:math:`\lambda` hits a reflective grating (groove period :math:`\Lambda`, groove
density ``grooves_per_mm``) at incidence angle :math:`\theta_i` in the grating's
YZ plane. The first diffracted order leaves along :math:`\mathbf{K}_d`::

    grating frame (X along the grooves, Z the grating normal)

           Z (normal)
           |      first order, direction d = K_d / |K_d|
           |    /
           |  /   theta_d
           |/___________ Y  (in the grating plane, across the grooves)
          /
         X  (along the grooves; the grating rotates about Z by -theta_r)

    K_d / (2 pi / lambda) = [ -G sin(theta_r),
                              sin(theta_i) - G cos(theta_r),
                              sqrt(1 - G^2 - sin^2(theta_i) + 2 G sin(theta_i) cos(theta_r)) ]
    with G = lambda / Lambda                                              (eq. 47)

At ``theta_r = 0`` this is the grating equation ``sin(theta_i) + sin(theta_d) = G``
(eq. 45) with ``d = (0, -sin(theta_d), cos(theta_d))``. Wavelength moves the beam
in Y (vertical: one channel per elevation); rotation moves it in X (horizontal:
one column per rotation angle), along a bow-shaped curve.

The mounting tilt rotates the grating frame about X by ``gamma`` (eq. 49) into
the global frame X'Y'Z' (Z' up). By default ``gamma`` makes the mean channel at
``theta_r = 0`` horizontal, so it travels along -Y'. Points are then reported in
the sensor frame used everywhere in cdma-lidar (REP 103)::

    x_s = -Y'   forward (range direction)
    y_s =  X'   left
    z_s =  Z'   up

Units: wavelengths in metres, angles in degrees at the API, radians inside.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from cdma_lidar.errors import ConfigError, out_of_range

__all__ = [
    "DEFAULT_INCIDENCE_DEG",
    "GratingGeometry",
    "azimuth_elevation_deg",
    "paper_wavelengths_m",
]

#: Default incidence angle (deg): with 600 grooves/mm and the L band it sends the first
#: order about 4 to 6 degrees off the normal, giving about 0.03 deg per 0.875 nm channel.
DEFAULT_INCIDENCE_DEG = 60.0

# Grating frame (X, Y, Z) after the tilt, to sensor frame (x forward, y left, z up).
_GLOBAL_TO_SENSOR = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])


def paper_wavelengths_m(channels: int = 40, start_m: float = 1570.0e-9,
                        spacing_m: float = 0.875e-9) -> NDArray[np.float64]:
    """Channel wavelengths (m) on the paper's L-band grid: ``start + k * spacing``."""
    if not 1 <= channels <= 1024:
        raise out_of_range("channels", "an integer from 1 to 1024", channels)
    return start_m + spacing_m * np.arange(channels, dtype=np.float64)


@dataclass(frozen=True)
class GratingGeometry:
    """Geometry of the rotating-grating scanner.

    Attributes:
        grooves_per_mm: groove density (lines/mm); the period is ``1e-3 / grooves_per_mm`` m.
        incidence_deg: incidence angle theta_i (deg), from the grating normal.
        tilt_deg: mounting tilt gamma about the grooves (deg, eq. 49). ``None`` picks the
            tilt that makes ``reference_wavelength_m`` horizontal at zero rotation.
        reference_wavelength_m: wavelength (m) used to pick the default tilt.
    """

    grooves_per_mm: float = 600.0
    incidence_deg: float = DEFAULT_INCIDENCE_DEG
    tilt_deg: float | None = None
    reference_wavelength_m: float = 1587.0e-9

    def __post_init__(self) -> None:
        if not (np.isfinite(self.grooves_per_mm) and 1.0 <= self.grooves_per_mm <= 1e4):
            raise out_of_range("grooves_per_mm", "from 1 to 10000 lines/mm", self.grooves_per_mm)
        if not (np.isfinite(self.incidence_deg) and -89.0 <= self.incidence_deg <= 89.0):
            raise out_of_range("incidence_deg", "from -89 to 89 degrees", self.incidence_deg)
        if self.tilt_deg is not None and not (np.isfinite(self.tilt_deg)
                                              and -180 <= self.tilt_deg <= 180):
            raise out_of_range("tilt_deg", "from -180 to 180 degrees or None", self.tilt_deg)
        if not (np.isfinite(self.reference_wavelength_m)
                and 100e-9 <= self.reference_wavelength_m <= 20e-6):
            raise out_of_range("reference_wavelength_m", "from 100e-9 to 20e-6 m",
                               self.reference_wavelength_m)

    @property
    def period_m(self) -> float:
        """Groove period Lambda (m)."""
        return 1e-3 / self.grooves_per_mm

    @property
    def gamma_rad(self) -> float:
        """Mounting tilt gamma (rad): given, or the one that levels the reference beam."""
        if self.tilt_deg is not None:
            return float(np.deg2rad(self.tilt_deg))
        d = self.grating_directions(self.reference_wavelength_m, 0.0)
        theta_d = np.arctan2(-d[..., 1], d[..., 2])  # d = (0, -sin theta_d, cos theta_d)
        return float(np.pi / 2 - theta_d)

    def wavevectors(self, wavelengths_m: ArrayLike, rotations_deg: ArrayLike) -> NDArray:
        """Diffracted wave vectors K_d (rad/m) in the grating frame, eq. 47.

        Broadcasts ``wavelengths_m`` against ``rotations_deg``; pass a (K, 1) and a (C,)
        array to get (K, C, 3). Raises ConfigError, not NaN, where the first order does
        not propagate (evanescent) for some wavelength and rotation.
        """
        lam = np.asarray(wavelengths_m, dtype=np.float64)
        rot = np.deg2rad(np.asarray(rotations_deg, dtype=np.float64))
        if lam.size and not (np.all(np.isfinite(lam)) and np.all(lam > 0)):
            raise out_of_range("wavelengths_m", "finite and positive (m)", lam)
        if rot.size and not np.all(np.isfinite(rot)):
            raise out_of_range("rotations_deg", "finite (deg)", rotations_deg)
        lam, rot = np.broadcast_arrays(lam, rot)
        g = lam / self.period_m
        s_i = np.sin(np.deg2rad(self.incidence_deg))
        kx = -g * np.sin(rot)
        ky = s_i - g * np.cos(rot)
        radicand = 1.0 - kx * kx - ky * ky
        bad = radicand < 0.0
        if np.any(bad):
            idx = np.argwhere(bad)[0]
            raise ConfigError(
                f"no propagating first order at wavelength {lam[tuple(idx)] * 1e9:.3f} nm and "
                f"rotation {np.rad2deg(rot[tuple(idx)]):.3f} deg (|K_d| parallel exceeds "
                f"2*pi/lambda); use a smaller rotation or a shorter wavelength",
                field="rotations_deg",
            )
        k = 2.0 * np.pi / lam
        return np.stack([kx, ky, np.sqrt(radicand)], axis=-1) * k[..., None]

    def grating_directions(self, wavelengths_m: ArrayLike, rotations_deg: ArrayLike) -> NDArray:
        """Unit ray directions in the grating frame (eq. 47 divided by 2*pi/lambda)."""
        kd = self.wavevectors(wavelengths_m, rotations_deg)
        return kd / np.linalg.norm(kd, axis=-1, keepdims=True)

    def directions(self, wavelengths_m: ArrayLike, rotations_deg: ArrayLike) -> NDArray:
        """Unit ray directions in the sensor frame (x forward, y left, z up), eq. 49.

        ``directions(wl[:, None], rot[None, :])`` gives the (K, C, 3) grid of a frame.
        """
        d = self.grating_directions(wavelengths_m, rotations_deg)
        c, s = np.cos(self.gamma_rad), np.sin(self.gamma_rad)
        r_x = np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])  # eq. 49
        return d @ (_GLOBAL_TO_SENSOR @ r_x).T

    def points(self, wavelengths_m: ArrayLike, rotations_deg: ArrayLike,
               ranges_m: ArrayLike) -> NDArray:
        """3D points (m) in the sensor frame: ``range * direction`` (origin at the grating)."""
        r = np.asarray(ranges_m, dtype=np.float64)
        return self.directions(wavelengths_m, rotations_deg) * r[..., None]

    def rotations_for_azimuths(self, azimuths_deg: ArrayLike,
                               wavelength_m: float | None = None) -> NDArray:
        """Grating rotations (deg) that point ``wavelength_m`` at the given azimuths (deg).

        Azimuth is measured in the sensor frame, positive to the left (towards +y).
        The map is monotonic over |rotation| < 60 deg and is inverted by interpolation
        on a 0.001-deg table, good to about 1e-6 deg.
        """
        lam = self.reference_wavelength_m if wavelength_m is None else wavelength_m
        az = np.asarray(azimuths_deg, dtype=np.float64)
        table_rot = np.linspace(-60.0, 60.0, 120001)
        try:
            table_az, _ = azimuth_elevation_deg(self.directions(lam, table_rot))
        except ConfigError:  # evanescent at large rotations: restrict the table
            ok = np.array([self._propagates(lam, r) for r in (-60.0, 60.0)])
            if not ok.any():
                raise
            table_rot = np.linspace(-20.0, 20.0, 40001)
            table_az, _ = azimuth_elevation_deg(self.directions(lam, table_rot))
        order = np.argsort(table_az)
        lo, hi = table_az[order[0]], table_az[order[-1]]
        if az.size and (np.min(az) < lo or np.max(az) > hi):
            raise out_of_range("azimuths_deg", f"within [{lo:.3f}, {hi:.3f}] degrees", az)
        return np.interp(az, table_az[order], table_rot[order])

    def _propagates(self, wavelength_m: float, rotation_deg: float) -> bool:
        try:
            self.wavevectors(wavelength_m, rotation_deg)
        except ConfigError:
            return False
        return True


def azimuth_elevation_deg(directions: ArrayLike) -> tuple[NDArray, NDArray]:
    """Azimuth (deg, positive left) and elevation (deg, positive up) of sensor-frame vectors."""
    d = np.asarray(directions, dtype=np.float64)
    az = np.degrees(np.arctan2(d[..., 1], d[..., 0]))
    el = np.degrees(np.arctan2(d[..., 2], np.hypot(d[..., 0], d[..., 1])))
    return az, el
