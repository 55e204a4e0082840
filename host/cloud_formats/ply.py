"""PLY, binary little endian: one vertex per pixel that has a range (plus kept extra points).

Every field of :data:`cdma_lidar.host.pointcloud.POINT_FIELDS` is a vertex property of
the same name. Types use the PLY spec's sized names (``float32``, ``uint16``,
``int32``), the ones Open3D's tensor reader (``open3d.t.io.read_point_cloud``) keeps:
it skips ``ushort`` and ``short``. An empty cloud is a valid file with
``element vertex 0``.
"""

from __future__ import annotations

import os

from cdma_lidar.fileio import atomic_open
from cdma_lidar.host.pointcloud import FLAG_BITS, POINT_FIELDS, PointCloud

__all__ = ["EXTENSION", "PLY_TYPES", "write"]

#: File extension this module writes.
EXTENSION = ".ply"

#: numpy type -> PLY property type.
PLY_TYPES = {"<f4": "float32", "<i4": "int32", "<u2": "uint16"}


def write(cloud: PointCloud, path: str | os.PathLike[str],
          keep_rejected: bool = False) -> int:
    """Write a binary little-endian PLY; returns the number of vertices written."""
    rec = cloud.records(keep_rejected)
    flags = ", ".join(f"{v} {k}" for k, v in FLAG_BITS.items())
    header = ["ply", "format binary_little_endian 1.0",
              f"comment cdma-lidar point cloud; flags bits: {flags}",
              "comment x y z range in m (x forward, y left, z up); t in s from the frame's "
              "first column; snr_xc in dB",
              f"comment channels {cloud.shape[0]} columns {cloud.shape[1]}",
              f"element vertex {rec.size}"]
    header += [f"property {PLY_TYPES[t]} {name}" for name, t in POINT_FIELDS]
    header.append("end_header")
    with atomic_open(path, "wb") as fh:
        fh.write(("\n".join(header) + "\n").encode("ascii"))
        fh.write(rec.tobytes())
    return int(rec.size)
