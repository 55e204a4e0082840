"""Point clouds: ranges plus grating geometry to 3D points.

A :class:`PointCloud` is organised like the scan: ``(K channels, C columns)`` arrays
of x, y, z (m, sensor frame: x forward, y left, z up, origin at the grating), range
(m), SNR_XC (dB), peak (correlator units), channel, column and flags (see
:mod:`cdma_lidar.host.ranging`: 0 valid, 1 interpolated, 2 rejected, 4 foreign UID, 8 ghost).
Pixels without a range have NaN coordinates.

The file formats are in :mod:`cdma_lidar.host.cloud_formats`, one module each.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from cdma_lidar.errors import ConfigError
from cdma_lidar.host.ranging import FLAG_REJECTED, RangeImage
from cdma_lidar.optics.grating import GratingGeometry

__all__ = ["POINT_FIELDS", "PointCloud", "assemble"]

log = logging.getLogger(__name__)

#: Per-point fields in file order with their numpy type (every format writes these).
POINT_FIELDS = (
    ("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("range", "<f4"), ("snr_xc", "<f4"),
    ("peak", "<i4"), ("channel", "<u2"), ("column", "<u2"), ("flags", "u1"),
)


@dataclass
class PointCloud:
    """An organised point cloud, every array (K, C) except wavelengths (K,) and angles (C,)."""

    x: NDArray[np.float64]
    y: NDArray[np.float64]
    z: NDArray[np.float64]
    range: NDArray[np.float64]
    snr_xc: NDArray[np.float64]
    peak: NDArray[np.int64]
    channel: NDArray[np.int64]
    column: NDArray[np.int64]
    flags: NDArray[np.uint8]
    wavelengths_m: NDArray[np.float64]
    angles_deg: NDArray[np.float64]

    @property
    def shape(self) -> tuple[int, int]:
        """(K channels, C columns)."""
        return self.range.shape  # type: ignore[return-value]

    @property
    def has_range(self) -> NDArray[np.bool_]:
        """Pixels with finite coordinates (valid or interpolated)."""
        return np.isfinite(self.range) & np.isfinite(self.x)

    def records(self, keep_rejected: bool = False) -> NDArray:
        """Structured array of points (row-major: channel, then column).

        Pixels without a range are left out unless ``keep_rejected`` (then x y z are NaN).
        """
        rec = np.empty(self.range.size, dtype=list(POINT_FIELDS))
        for name, _ in POINT_FIELDS:
            rec[name] = getattr(self, name).ravel()
        if not keep_rejected:
            rec = rec[self.has_range.ravel()]
        return rec


def assemble(image: RangeImage, geometry: GratingGeometry, wavelengths_m: ArrayLike,
             angles_deg: ArrayLike) -> PointCloud:
    """Place every ranged pixel in 3D: ``range * direction(wavelength, rotation)`` (eqs. 45-49)."""
    wl = np.asarray(wavelengths_m, dtype=np.float64)
    ang = np.asarray(angles_deg, dtype=np.float64)
    k, c = image.range_m.shape
    if wl.shape != (k,):
        raise ConfigError(f"wavelengths_m must have {k} entries (one per channel), not {wl.size}",
                          field="wavelengths_m")
    if ang.shape != (c,):
        raise ConfigError(f"angles_deg must have {c} entries (one per column), not {ang.size}",
                          field="angles_deg")
    rng = image.range_m
    known = np.isfinite(ang)
    pts = np.full((k, c, 3), np.nan)
    if np.any(known):
        dirs = geometry.directions(wl[:, None], ang[None, known])
        pts[:, known] = dirs * rng[:, known, None]
    chan, col = np.meshgrid(np.arange(k), np.arange(c), indexing="ij")
    flags = image.flags.copy()
    flags[~np.isfinite(rng)] |= FLAG_REJECTED
    return PointCloud(x=pts[..., 0], y=pts[..., 1], z=pts[..., 2], range=rng.copy(),
                      snr_xc=image.snr_xc_db.copy(), peak=image.peak.copy(), channel=chan,
                      column=col, flags=flags, wavelengths_m=wl, angles_deg=ang)
