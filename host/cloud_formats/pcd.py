"""PCD v0.7 binary, organised: WIDTH = columns, HEIGHT = channels, row-major by channel.

Pixels without a range have NaN x y z; the fields are those of the PLY writer.
"""

from __future__ import annotations

import os

from cdma_lidar.fileio import atomic_open
from cdma_lidar.host.pointcloud import POINT_FIELDS, PointCloud

__all__ = ["EXTENSION", "write"]

#: File extension this module writes.
EXTENSION = ".pcd"


def write(cloud: PointCloud, path: str | os.PathLike[str]) -> int:
    """Write an organised binary PCD v0.7 (WIDTH columns, HEIGHT channels); returns K*C."""
    rec = cloud.records(keep_rejected=True)
    pcd_type = {"<f4": ("4", "F"), "<i4": ("4", "I"), "<u2": ("2", "U"), "u1": ("1", "U")}
    k, c = cloud.shape
    names = [n for n, _ in POINT_FIELDS]
    header = [
        "# .PCD v0.7 - Point Cloud Data file format (cdma-lidar; rows are channels)",
        "VERSION 0.7",
        "FIELDS " + " ".join(names),
        "SIZE " + " ".join(pcd_type[t][0] for _, t in POINT_FIELDS),
        "TYPE " + " ".join(pcd_type[t][1] for _, t in POINT_FIELDS),
        "COUNT " + " ".join("1" for _ in POINT_FIELDS),
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
