"""Point clouds: ranges plus grating geometry to 3D points, and the file writers.

A :class:`PointCloud` is organised like the scan: ``(K channels, C columns)`` arrays
of x, y, z (m, sensor frame: x forward, y left, z up, origin at the grating), range
(m), SNR_XC (dB), peak (correlator units), channel, column and flags (see
:mod:`cdma_lidar.host.ranging`: 0 valid, 1 interpolated, 2 rejected, 4 foreign UID, 8 ghost).
Pixels without a range have NaN coordinates.

Writers, chosen by the output file's extension (all written atomically):

======  ==================================================================
.ply    binary little endian, one vertex per pixel that has a range; properties
        x y z range snr_xc (float32), peak (int32), channel column (uint16), flags (uint8)
.pcd    PCD v0.7 binary, organised: WIDTH = columns, HEIGHT = channels, row-major by
        channel; pixels without a range have NaN x y z
.npz    every (K, C) array plus wavelengths (m) and angles (deg)
.las    LAS 1.4 point format 6 through laspy (optional extra ``las``); range,
        snr_xc, peak, channel, column and flags as extra dimensions
======  ==================================================================
"""

from __future__ import annotations

import logging
import os
from dataclasses import dataclass, fields
from pathlib import Path

import numpy as np
from numpy.typing import ArrayLike, NDArray

from cdma_lidar.errors import ConfigError
from cdma_lidar.fileio import atomic_open, check_writable
from cdma_lidar.host.ranging import FLAG_REJECTED, RangeImage
from cdma_lidar.optics.grating import GratingGeometry

__all__ = [
    "FORMATS",
    "PointCloud",
    "assemble",
    "read_npz",
    "write",
    "write_las",
    "write_npz",
    "write_pcd",
    "write_ply",
]

log = logging.getLogger(__name__)

#: Per-point fields in file order with their numpy type.
_POINT_FIELDS = (
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
        rec = np.empty(self.range.size, dtype=list(_POINT_FIELDS))
        for name, _ in _POINT_FIELDS:
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


def write_ply(cloud: PointCloud, path: str | os.PathLike[str],
              keep_rejected: bool = False) -> int:
    """Write a binary little-endian PLY; returns the number of vertices written."""
    rec = cloud.records(keep_rejected)
    ply_type = {"<f4": "float", "<i4": "int", "<u2": "ushort", "u1": "uchar"}
    header = ["ply", "format binary_little_endian 1.0",
              "comment cdma-lidar point cloud; flags: 0 valid, 1 interpolated, 2 rejected, "
              "4 foreign UID, 8 ghost",
              f"comment channels {cloud.shape[0]} columns {cloud.shape[1]}",
              f"element vertex {rec.size}"]
    header += [f"property {ply_type[t]} {name}" for name, t in _POINT_FIELDS]
    header.append("end_header")
    with atomic_open(path, "wb") as fh:
        fh.write(("\n".join(header) + "\n").encode("ascii"))
        fh.write(rec.tobytes())
    return int(rec.size)


def write_pcd(cloud: PointCloud, path: str | os.PathLike[str]) -> int:
    """Write an organised binary PCD v0.7 (WIDTH columns, HEIGHT channels); returns K*C."""
    rec = cloud.records(keep_rejected=True)
    pcd_type = {"<f4": ("4", "F"), "<i4": ("4", "I"), "<u2": ("2", "U"), "u1": ("1", "U")}
    k, c = cloud.shape
    names = [n for n, _ in _POINT_FIELDS]
    header = [
        "# .PCD v0.7 - Point Cloud Data file format (cdma-lidar; rows are channels)",
        "VERSION 0.7",
        "FIELDS " + " ".join(names),
        "SIZE " + " ".join(pcd_type[t][0] for _, t in _POINT_FIELDS),
        "TYPE " + " ".join(pcd_type[t][1] for _, t in _POINT_FIELDS),
        "COUNT " + " ".join("1" for _ in _POINT_FIELDS),
        f"WIDTH {c}",
        f"HEIGHT {k}",
        "VIEWPOINT 0 0 0 1 0 0 0",
        f"POINTS {k * c}",
        "DATA binary",
    ]
    with atomic_open(path, "wb") as fh:
        fh.write(("\n".join(header) + "\n").encode("ascii"))
        fh.write(rec.tobytes())
    return k * c


def write_npz(cloud: PointCloud, path: str | os.PathLike[str]) -> int:
    """Write every array of the cloud to a compressed ``.npz``; returns K*C."""
    arrays = {f.name: np.asarray(getattr(cloud, f.name)) for f in fields(cloud)}
    with atomic_open(path, "wb") as fh:
        np.savez_compressed(fh, **arrays)
    return cloud.range.size


def read_npz(path: str | os.PathLike[str]) -> PointCloud:
    """Read a cloud written by :func:`write_npz`."""
    with np.load(path) as data:
        return PointCloud(**{f.name: data[f.name] for f in fields(PointCloud)})


def write_las(cloud: PointCloud, path: str | os.PathLike[str]) -> int:
    """Write LAS 1.4 (point format 6) through laspy; returns the number of points.

    Coordinates are stored with a 0.1 mm scale; the per-pixel fields go in extra
    dimensions. Needs the optional extra ``las`` (``pip install cdma-lidar[las]``).
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
    extras = [("range", np.float32), ("snr_xc", np.float32), ("peak", np.int32),
              ("channel", np.uint16), ("column", np.uint16), ("flags", np.uint8)]
    header.add_extra_dims([laspy.ExtraBytesParams(name=n, type=t) for n, t in extras])
    las = laspy.LasData(header)
    las.x, las.y, las.z = rec["x"], rec["y"], rec["z"]
    for name, _ in extras:
        setattr(las, name, rec[name])
    las.intensity = np.clip(rec["snr_xc"] * 100.0, 0, 65535).astype(np.uint16)
    with atomic_open(path, "wb") as fh:
        las.write(fh)
    return int(rec.size)


FORMATS = {".ply": write_ply, ".pcd": write_pcd, ".npz": write_npz, ".las": write_las}


def write(cloud: PointCloud, path: str | os.PathLike[str]) -> int:
    """Write ``cloud`` in the format its extension names (.ply, .pcd, .npz, .las)."""
    p = Path(path)
    writer = FORMATS.get(p.suffix.lower())
    if writer is None:
        raise ConfigError(f"output file extension must be one of {', '.join(FORMATS)}, "
                          f"not {p.suffix or '(none)'!r}", field="out")
    check_writable(p)
    n = writer(cloud, p)
    log.info("wrote %d points to %s", n, p)
    return n
