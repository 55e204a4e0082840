"""LAS 1.4 point format 6 through laspy (the optional extra ``las``).

Coordinates with a 0.1 mm scale. ``gps_time`` is the point's time: the frame's host
stamp plus ``t``, as *adjusted standard GPS time* (GPS seconds minus 1e9; global
encoding bit 0 set), or just ``t`` when the cloud has no stamp (global encoding bit 0
clear). The standard ``intensity`` (uint16) holds the intensity times
:data:`INTENSITY_SCALE` = 4096: a calibrated reflectance of 1.0 reads 4096, an
uncalibrated intensity (:data:`cdma_lidar.host.intensity.RAW_UNIT`) of 1.0 reads 4096 as
well; values above 16 saturate at 65535 with a warning naming how many (the float
``intensity`` of the other formats never saturates). Every other field of
:data:`cdma_lidar.host.pointcloud.POINT_FIELDS` (``t`` too) is an extra-bytes
dimension of the same name and type. laspy is imported only when a .las is written.

Point format 6 requires the coordinate system as WKT: global encoding bit 4 (WKT) is
set and an OGC WKT VLR names the sensor frame, :data:`SENSOR_WKT`: a local engineering
system in metres (x forward, y left, z up, origin at the grating), not a map projection.
An empty cloud is a valid file with no points.
"""

from __future__ import annotations

import logging
import os

import numpy as np

from cdma_lidar.errors import ConfigError
from cdma_lidar.fileio import atomic_open
from cdma_lidar.host.cloud_formats.grid import cloud_from_records
from cdma_lidar.host.pointcloud import POINT_FIELDS, PointCloud, empty_records

__all__ = ["EXTENSION", "INTENSITY_SCALE", "SENSOR_WKT", "gps_time", "read_frames", "write"]

log = logging.getLogger(__name__)

#: File extension this module writes.
EXTENSION = ".las"

#: LAS intensity counts per unit of intensity (65535 = 16 units).
INTENSITY_SCALE = 4096.0

#: The sensor frame as OGC WKT (LAS 1.4 asks for WKT with point formats 6-10).
SENSOR_WKT = ('LOCAL_CS["cdma_lidar sensor frame (x forward, y left, z up, origin at the '
              'grating)",LOCAL_DATUM["cdma_lidar grating",0],UNIT["metre",1],'
              'AXIS["X",NORTH],AXIS["Y",WEST],AXIS["Z",UP]]')

_GPS_EPOCH_UNIX_S = 315_964_800.0   # 1980-01-06T00:00:00Z
_GPS_MINUS_UTC_S = 18.0             # leap seconds since 1980 (unchanged since 2017)
_NATIVE = ("x", "y", "z", "intensity")


def gps_time(unix_s: float | np.ndarray) -> float | np.ndarray:
    """Adjusted standard GPS time (s): GPS seconds since 1980-01-06 minus 1e9."""
    return unix_s - _GPS_EPOCH_UNIX_S + _GPS_MINUS_UTC_S - 1e9


def write(cloud: PointCloud, path: str | os.PathLike[str]) -> int:
    """Write LAS 1.4 (point format 6) through laspy; returns the number of points.

    Needs the optional extra ``las`` (``pip install cdma-lidar[las]``).
    """
    try:
        import laspy  # optional extra `las`: loaded only when a .las is written
    except ImportError as exc:  # pragma: no cover - depends on the environment
        raise ConfigError("writing .las needs laspy: pip install 'cdma-lidar[las]'",
                          field="out") from exc
    rec = cloud.records()
    header = laspy.LasHeader(point_format=6, version="1.4")
    header.scales = np.array([1e-4, 1e-4, 1e-4])
    header.offsets = np.zeros(3)
    stamped = cloud.stamp_unix_s > 0
    header.global_encoding.gps_time_type = (laspy.header.GpsTimeType.STANDARD if stamped
                                            else laspy.header.GpsTimeType.WEEK_TIME)
    header.global_encoding.wkt = True
    header.vlrs.append(laspy.vlrs.known.WktCoordinateSystemVlr(SENSOR_WKT))
    extras = [(n, np.dtype(t).type) for n, t in POINT_FIELDS if n not in _NATIVE]
    header.add_extra_dims([laspy.ExtraBytesParams(name=n, type=t) for n, t in extras])
    las = laspy.LasData(header)
    las.x, las.y, las.z = rec["x"], rec["y"], rec["z"]
    for name, _ in extras:
        setattr(las, name, rec[name])
    base = gps_time(cloud.stamp_unix_s) if stamped else 0.0
    las.gps_time = base + rec["t"].astype(np.float64)
    inten = np.nan_to_num(rec["intensity"].astype(np.float64), nan=0.0) * INTENSITY_SCALE
    over = int(np.count_nonzero(inten > 65535))
    if over:
        log.warning("%d of %d points have an intensity above %g: LAS intensity saturates "
                    "at 65535 for them (the float intensity of .ply/.pcd/.npz/.mcap does not)",
                    over, inten.size, 65535 / INTENSITY_SCALE)
    las.intensity = np.clip(np.rint(inten), 0, 65535).astype(np.uint16)
    with atomic_open(path, "wb") as fh:
        las.write(fh)
    return int(rec.size)


def read_frames(path: str | os.PathLike[str]) -> list[PointCloud]:
    """Read a LAS this module wrote as one frame (intensity back in units, not counts)."""
    try:
        import laspy  # optional extra `las`
    except ImportError as exc:  # pragma: no cover - depends on the environment
        raise ConfigError("reading .las needs laspy: pip install 'cdma-lidar[las]'",
                          field="in") from exc
    las = laspy.read(str(path))
    rec = empty_records(len(las.points))
    for name, _ in POINT_FIELDS:
        rec[name] = np.asarray(getattr(las, name))
    rec["intensity"] = np.asarray(las.intensity, np.float64) / INTENSITY_SCALE
    t0 = float(np.min(np.asarray(las.gps_time) - rec["t"])) if rec.size else 0.0
    stamped = las.header.global_encoding.gps_time_type == laspy.header.GpsTimeType.STANDARD
    stamp = t0 + _GPS_EPOCH_UNIX_S - _GPS_MINUS_UTC_S + 1e9 if stamped and rec.size else 0.0
    return [cloud_from_records(rec, stamp_unix_s=stamp)]
