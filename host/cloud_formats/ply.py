"""PLY, binary little endian: one vertex per pixel that has a range.

Properties x y z range snr_xc (float32), peak (int32), channel column (uint16), flags
(uint8); coordinates in m, sensor frame (x forward, y left, z up).
"""

from __future__ import annotations

import os

from cdma_lidar.fileio import atomic_open
from cdma_lidar.host.pointcloud import POINT_FIELDS, PointCloud

__all__ = ["EXTENSION", "write"]

#: File extension this module writes.
EXTENSION = ".ply"


def write(cloud: PointCloud, path: str | os.PathLike[str],
              keep_rejected: bool = False) -> int:
    """Write a binary little-endian PLY; returns the number of vertices written."""
    rec = cloud.records(keep_rejected)
    ply_type = {"<f4": "float", "<i4": "int", "<u2": "ushort", "u1": "uchar"}
    header = ["ply", "format binary_little_endian 1.0",
              "comment cdma-lidar point cloud; flags: 0 valid, 1 interpolated, 2 rejected, "
              "4 foreign UID, 8 ghost",
              f"comment channels {cloud.shape[0]} columns {cloud.shape[1]}",
              f"element vertex {rec.size}"]
    header += [f"property {ply_type[t]} {name}" for name, t in POINT_FIELDS]
    header.append("end_header")
    with atomic_open(path, "wb") as fh:
        fh.write(("\n".join(header) + "\n").encode("ascii"))
        fh.write(rec.tobytes())
    return int(rec.size)
