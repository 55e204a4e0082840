"""Point records back into an organised :class:`~cdma_lidar.host.pointcloud.PointCloud`.

The readers of every format end here: each record lands in its pixel by its ``ring``
(channel) and ``column`` fields; pixels no record names have NaN coordinates and ranges,
flag ``rejected``, ``user_id`` -1 and peak 0; records flagged ``foreign`` (other users'
returns kept with ``--keep-foreign``) become the cloud's extra points. Where a format does
not store the grid's size, wavelengths or column rotations, the size comes from the largest
ring and column and the others are NaN.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

from cdma_lidar.host.pointcloud import POINT_FIELDS, PointCloud, empty_records
from cdma_lidar.host.ranging import FLAG_FOREIGN, FLAG_REJECTED

__all__ = ["cloud_from_records"]


def cloud_from_records(rec: NDArray, *, shape: tuple[int, int] | None = None,
                       wavelengths_m: ArrayLike | None = None,
                       angles_deg: ArrayLike | None = None,
                       stamp_unix_s: float = 0.0) -> PointCloud:
    """An organised cloud from records with :data:`POINT_FIELDS` (any field order)."""
    names = [n for n, _ in POINT_FIELDS]
    packed = empty_records(rec.size)
    for n in names:
        packed[n] = rec[n]
    foreign = (packed["flags"] & FLAG_FOREIGN) != 0
    own, extra = packed[~foreign], packed[foreign]
    if shape is None:
        shape = (int(own["ring"].max()) + 1 if own.size else 0,
                 int(own["column"].max()) + 1 if own.size else 0)
    k, c = shape
    grid = {n: np.full((k, c), np.nan) for n in ("x", "y", "z", "intensity", "range",
                                                 "snr_xc")}
    grid["t"] = np.zeros((k, c))
    grid["ring"], grid["column"] = np.meshgrid(np.arange(k), np.arange(c), indexing="ij")
    grid["flags"] = np.full((k, c), FLAG_REJECTED, np.uint16)
    grid["user_id"] = np.full((k, c), -1, np.int64)
    grid["peak"] = np.zeros((k, c), np.int64)
    r, col = own["ring"].astype(np.int64), own["column"].astype(np.int64)
    for n in names:
        if n not in ("ring", "column"):
            grid[n][r, col] = own[n]
    wl = np.full(k, np.nan) if wavelengths_m is None else np.asarray(wavelengths_m, float)
    ang = np.full(c, np.nan) if angles_deg is None else np.asarray(angles_deg, float)
    return PointCloud(**{n: grid[n] for n in names}, wavelengths_m=wl, angles_deg=ang,
                      stamp_unix_s=float(stamp_unix_s), extra=extra)
