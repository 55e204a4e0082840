"""PCD v0.7 binary. Organised (WIDTH = columns, HEIGHT = channels, row-major by channel)
unless extra points (kept foreign returns) are present, then unorganised (HEIGHT 1).

Every field of :data:`cdma_lidar.host.pointcloud.POINT_FIELDS` under its own name;
pixels without a range have NaN x y z. An empty cloud (no pixels) is WIDTH 0,
HEIGHT 1, POINTS 0. ``POINTS`` is checked against the bytes after the header: a file
cut short is refused, not read as a smaller cloud.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from cdma_lidar.errors import ConfigError
from cdma_lidar.fileio import atomic_open
from cdma_lidar.host.cloud_formats.grid import cloud_from_records
from cdma_lidar.host.pointcloud import POINT_FIELDS, PointCloud

__all__ = ["EXTENSION", "PCD_TYPES", "read_frames", "write"]

#: File extension this module writes.
EXTENSION = ".pcd"

#: numpy type -> (SIZE, TYPE) of a PCD field.
PCD_TYPES = {"<f4": ("4", "F"), "<i4": ("4", "I"), "<u2": ("2", "U")}


def write(cloud: PointCloud, path: str | os.PathLike[str]) -> int:
    """Write a binary PCD v0.7; returns the number of points written."""
    rec = cloud.records(keep_rejected=True)
    k, c = cloud.shape
    width, height = (c, k) if not cloud.extra.size and rec.size else (rec.size, 1)
    header = [
        "# .PCD v0.7 - Point Cloud Data file format (cdma-lidar; rows are channels)",
        "VERSION 0.7",
        "FIELDS " + " ".join(n for n, _ in POINT_FIELDS),
        "SIZE " + " ".join(PCD_TYPES[t][0] for _, t in POINT_FIELDS),
        "TYPE " + " ".join(PCD_TYPES[t][1] for _, t in POINT_FIELDS),
        "COUNT " + " ".join("1" for _ in POINT_FIELDS),
        f"WIDTH {width}",
        f"HEIGHT {height}",
        "VIEWPOINT 0 0 0 1 0 0 0",
        f"POINTS {rec.size}",
        "DATA binary",
    ]
    with atomic_open(path, "wb") as fh:
        fh.write(("\n".join(header) + "\n").encode("ascii"))
        fh.write(rec.tobytes())
    return int(rec.size)


def read_frames(path: str | os.PathLike[str]) -> list[PointCloud]:
    """Read a binary PCD this module wrote as one frame (organised: HEIGHT x WIDTH)."""
    raw = Path(path).read_bytes()
    end = raw.find(b"DATA binary\n")
    if end < 0:
        raise ConfigError(f"{str(path)!r} is not a binary PCD file", field="in")
    head = {ln.split()[0]: ln.split()[1:] for ln in
            raw[:end].decode("ascii", "replace").splitlines() if ln and ln[0] != "#"}
    types = {v: k for k, v in PCD_TYPES.items()}
    try:
        dt = np.dtype([(n, types[(s, t)]) for n, s, t in
                       zip(head["FIELDS"], head["SIZE"], head["TYPE"], strict=True)])
        width, height = int(head["WIDTH"][0]), int(head["HEIGHT"][0])
        points = int(head["POINTS"][0])
    except (KeyError, ValueError) as exc:
        raise ConfigError(f"{str(path)!r}: a PCD header cdma-lidar did not write ({exc})",
                          field="in") from None
    body = raw[end + len(b"DATA binary\n"):]
    if points != width * height or points * dt.itemsize != len(body):
        raise ConfigError(f"{str(path)!r} is cut short or padded: its header says {points} "
                          f"points of {width} x {height} ({points * dt.itemsize} bytes), the "
                          f"file holds {len(body)} bytes of them", field="in")
    rec = np.frombuffer(body, dtype=dt)
    return [cloud_from_records(rec, shape=(height, width) if height > 1 else None)]
