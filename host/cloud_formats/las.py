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

What the points mean is in the file too: every extra-bytes dimension has a description
(:data:`cdma_lidar.host.pointcloud.FIELD_UNITS`, unit first), the header's generating
software names the toolkit and its version, and a VLR :data:`METADATA_VLR` (user
``cdma_lidar``, record 1) holds JSON: ``intensity_scale`` (4096), the grid's size, the
channel wavelengths and column rotations and what the scan says about its points (the
threshold, the units, the version: :func:`cdma_lidar.host.pointcloud.file_metadata`).
The caller's metadata beyond that (per-pixel beam angles: K x C values, more than a VLR's
65,535 bytes) goes in an extended VLR, record 2. The header's point count is checked
against the file's size when it is read: a file cut short is refused, not read as a
smaller cloud.
"""

from __future__ import annotations

import importlib.metadata
import json
import logging
import os
from collections.abc import Mapping
from pathlib import Path

import numpy as np

from cdma_lidar.errors import ConfigError
from cdma_lidar.fileio import atomic_open
from cdma_lidar.host.cloud_formats.grid import cloud_from_records
from cdma_lidar.host.pointcloud import FIELD_UNITS, POINT_FIELDS, PointCloud, empty_records

__all__ = ["EXTENSION", "INTENSITY_SCALE", "METADATA_VLR", "SENSOR_WKT", "gps_time",
           "read_frames", "write"]

log = logging.getLogger(__name__)

#: File extension this module writes.
EXTENSION = ".las"

#: LAS intensity counts per unit of intensity (65535 = 16 units).
INTENSITY_SCALE = 4096.0

#: The sensor frame as OGC WKT (LAS 1.4 asks for WKT with point formats 6-10).
SENSOR_WKT = ('LOCAL_CS["cdma_lidar sensor frame (x forward, y left, z up, origin at the '
              'grating)",LOCAL_DATUM["cdma_lidar grating",0],UNIT["metre",1],'
              'AXIS["X",NORTH],AXIS["Y",WEST],AXIS["Z",UP]]')

#: User id of the VLR (record 1) and extended VLR (record 2) of the scan's metadata.
METADATA_VLR = "cdma_lidar"
#: Metadata keys small enough for the VLR (the rest go in the extended VLR).
_SMALL = ("cdma_lidar_version", "snr_threshold_db", "intensity_unit", "field_units",
          "device", "configuration", "scan_options")

_GPS_EPOCH_UNIX_S = 315_964_800.0   # 1980-01-06T00:00:00Z
_GPS_MINUS_UTC_S = 18.0             # leap seconds since 1980 (unchanged since 2017)
_NATIVE = ("x", "y", "z", "intensity")


def gps_time(unix_s: float | np.ndarray) -> float | np.ndarray:
    """Adjusted standard GPS time (s): GPS seconds since 1980-01-06 minus 1e9."""
    return unix_s - _GPS_EPOCH_UNIX_S + _GPS_MINUS_UTC_S - 1e9


def write(cloud: PointCloud, path: str | os.PathLike[str],
          metadata: Mapping[str, str] | None = None) -> int:
    """Write LAS 1.4 (point format 6) through laspy; returns the number of points.

    ``metadata``: string keys to JSON text (:func:`cdma_lidar.host.scan.scan_metadata`).
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
    header.generating_software = f"cdma-lidar {importlib.metadata.version('cdma-lidar')}"
    meta = {k: json.loads(v) for k, v in (metadata or {}).items()}
    small = {k: meta.pop(k) for k in _SMALL if k in meta}
    small |= {"intensity_scale": INTENSITY_SCALE, "channels": cloud.shape[0],
              "columns": cloud.shape[1], "wavelengths_m": _finite(cloud.wavelengths_m),
              "angles_deg": _finite(cloud.angles_deg)}
    for k in ("wavelengths_m", "angles_deg"):
        meta.pop(k, None)
    header.vlrs.append(laspy.vlrs.VLR(METADATA_VLR, 1, "scan metadata (JSON)",
                                      json.dumps(small).encode()))
    if meta:
        header.evlrs = laspy.vlrs.vlrlist.VLRList([laspy.vlrs.VLR(
            METADATA_VLR, 2, "more scan metadata (JSON)", json.dumps(meta).encode())])
    extras = [(n, np.dtype(t).type) for n, t in POINT_FIELDS if n not in _NATIVE]
    header.add_extra_dims([laspy.ExtraBytesParams(
        name=n, type=t, description=f"{FIELD_UNITS[n][0]}: {FIELD_UNITS[n][1]}"[:32])
        for n, t in extras])
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
    with laspy.open(str(path)) as fh:
        h = fh.header
        want = h.offset_to_point_data + h.point_count * h.point_format.size
    have = Path(path).stat().st_size
    if have < want:
        raise ConfigError(f"{str(path)!r} is cut short: its header says {h.point_count} "
                          f"points ({want} bytes with the header), the file holds {have} "
                          "bytes", field="in")
    las = laspy.read(str(path))
    meta = next((json.loads(v.record_data) for v in las.header.vlrs
                 if v.user_id == METADATA_VLR and v.record_id == 1), {})
    rec = empty_records(len(las.points))
    for name, _ in POINT_FIELDS:
        rec[name] = np.asarray(getattr(las, name))
    rec["intensity"] = np.asarray(las.intensity, np.float64) / INTENSITY_SCALE
    t0 = float(np.min(np.asarray(las.gps_time) - rec["t"])) if rec.size else 0.0
    stamped = las.header.global_encoding.gps_time_type == laspy.header.GpsTimeType.STANDARD
    stamp = t0 + _GPS_EPOCH_UNIX_S - _GPS_MINUS_UTC_S + 1e9 if stamped and rec.size else 0.0
    return [cloud_from_records(
        rec, stamp_unix_s=stamp,
        shape=(meta["channels"], meta["columns"]) if "channels" in meta else None,
        wavelengths_m=_nan(meta.get("wavelengths_m")), angles_deg=_nan(meta.get("angles_deg")))]


def _finite(values: np.ndarray) -> list[float | None]:
    """JSON-safe list: NaN (unknown) as null."""
    return [float(v) if np.isfinite(v) else None for v in np.asarray(values, float)]


def _nan(values: list[float | None] | None) -> np.ndarray | None:
    """:func:`_finite` undone (None stays None)."""
    return None if values is None else np.array([np.nan if v is None else v for v in values])
