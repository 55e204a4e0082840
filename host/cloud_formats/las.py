"""LAS 1.4 point format 6 through laspy (the optional extra ``las``).

Coordinates with a 0.1 mm scale; range, snr_xc, peak, channel, column and flags as extra
dimensions. laspy is imported only when a .las is written.
"""

from __future__ import annotations

import os

import numpy as np

from cdma_lidar.errors import ConfigError
from cdma_lidar.fileio import atomic_open
from cdma_lidar.host.pointcloud import PointCloud

__all__ = ["EXTENSION", "write"]

#: File extension this module writes.
EXTENSION = ".las"


def write(cloud: PointCloud, path: str | os.PathLike[str]) -> int:
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
