"""Point-cloud file formats, chosen by the output file's extension (all written atomically).

======  =========================================================================
.ply    binary little endian, one vertex per pixel that has a range (:mod:`.ply`)
.pcd    PCD v0.7 binary, organised: WIDTH = columns, HEIGHT = channels (:mod:`.pcd`)
.npz    every (K, C) array plus wavelengths (m) and angles (deg) (:mod:`.npz`)
.las    LAS 1.4 point format 6 through laspy, optional extra ``las`` (:mod:`.las`)
======  =========================================================================

Adding a format is one new module here with ``EXTENSION`` and
``write(cloud, path) -> int`` (points written), listed in :data:`FORMATS`. A module
whose library is optional imports it inside ``write`` and says so.
"""

from __future__ import annotations

import logging
import os
from collections.abc import Callable
from pathlib import Path

from cdma_lidar.errors import ConfigError
from cdma_lidar.fileio import check_writable
from cdma_lidar.host.cloud_formats import las, npz, pcd, ply
from cdma_lidar.host.pointcloud import PointCloud

__all__ = ["FORMATS", "write"]

log = logging.getLogger(__name__)

#: Extension (lower case, with the dot) -> writer ``(cloud, path) -> points written``.
FORMATS: dict[str, Callable[[PointCloud, str | os.PathLike[str]], int]] = {
    m.EXTENSION: m.write for m in (ply, pcd, npz, las)
}


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
