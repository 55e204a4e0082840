"""NumPy ``.npz``: every (K, C) array of the cloud plus wavelengths (m) and angles (deg).

The one format that reads back into a :class:`~cdma_lidar.host.pointcloud.PointCloud`.
"""

from __future__ import annotations

import os
from dataclasses import fields

import numpy as np

from cdma_lidar.fileio import atomic_open
from cdma_lidar.host.pointcloud import PointCloud

__all__ = ["EXTENSION", "read", "read_frames", "write"]

#: File extension this module writes.
EXTENSION = ".npz"


def write(cloud: PointCloud, path: str | os.PathLike[str]) -> int:
    """Write every array of the cloud to a compressed ``.npz``; returns K*C."""
    arrays = {f.name: np.asarray(getattr(cloud, f.name)) for f in fields(cloud)}
    with atomic_open(path, "wb") as fh:
        np.savez_compressed(fh, **arrays)
    return cloud.range.size


def read(path: str | os.PathLike[str]) -> PointCloud:
    """Read a cloud written by :func:`write`."""
    with np.load(path) as data:
        kw = {f.name: data[f.name] for f in fields(PointCloud) if f.name in data.files}
    kw["stamp_unix_s"] = float(kw.get("stamp_unix_s", 0.0))
    return PointCloud(**kw)


def read_frames(path: str | os.PathLike[str]) -> list[PointCloud]:
    """:func:`read` as a list of one frame (the readers' common shape)."""
    return [read(path)]
