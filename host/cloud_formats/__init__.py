"""Point-cloud file formats, chosen by the output file's extension (all written atomically).

======  =========================================================================
.ply    binary little endian, one vertex per pixel that has a range (:mod:`.ply`)
.pcd    PCD v0.7 binary, organised: WIDTH = columns, HEIGHT = channels (:mod:`.pcd`)
.npz    every (K, C) array plus wavelengths (m) and angles (deg) (:mod:`.npz`)
.las    LAS 1.4 point format 6 through laspy, optional extra ``las`` (:mod:`.las`)
.mcap   ROS 2 sensor_msgs/PointCloud2, one message per frame, optional extra
        ``mcap`` (:mod:`.mcap`)
======  =========================================================================

Every format carries the same per-point fields under the same names
(:data:`cdma_lidar.host.pointcloud.POINT_FIELDS`). A format module with
``MULTI_FRAME = True`` also has ``write_frames(clouds, path)`` and gets every frame of
a scan (:func:`write_frames`); the others get the last frame.

Every module also reads back what it wrote, ``read_frames(path) -> [PointCloud, ...]``
(:data:`READERS`, :func:`read_frames`; the records land in their pixels by ``ring`` and
``column``, :mod:`.grid`), so ``cdma-lidar convert IN OUT`` goes between every pair and
``replay://FILE`` (:mod:`cdma_lidar.host.replay`) feeds a recording back through the host.
What a format cannot hold is lost on the way: PCD keeps no wavelengths or column
rotations, PLY and PCD no stamp (their bytes depend only on the scan), LAS quantises
intensity to 1/4096. Every file opens in the reader people use (Open3D for .ply and
.pcd, laspy for .las, the mcap ROS 2 reader for .mcap: tests/host/test_readers.py); a
list too long for one header line is split over several (.ply) or goes in a VLR (.las)
or a metadata record (.mcap), never on a line a reader rejects. Each reader checks the
header's point count against the bytes that follow: a file cut short is refused.

Adding a format is one new module here with ``EXTENSION``,
``write(cloud, path) -> int`` (points written) and ``read_frames``, listed in
:data:`FORMATS`. A module whose library is optional imports it inside ``write`` and says so.
"""

from __future__ import annotations

import importlib.util
import logging
import os
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path

from cdma_lidar.errors import ConfigError
from cdma_lidar.fileio import check_writable
from cdma_lidar.host.cloud_formats import las, mcap, npz, pcd, ply
from cdma_lidar.host.pointcloud import PointCloud

__all__ = ["FORMATS", "METADATA_FORMATS", "MULTI_FRAME_FORMATS", "OPTIONAL_LIBRARIES",
           "READERS", "check_output", "read_frames", "write", "write_frames"]

log = logging.getLogger(__name__)

#: Extension (lower case, with the dot) -> writer ``(cloud, path) -> points written``.
FORMATS: dict[str, Callable[[PointCloud, str | os.PathLike[str]], int]] = {
    m.EXTENSION: m.write for m in (ply, pcd, npz, las, mcap)
}

#: Extension -> writer of a sequence of frames, for the formats that hold several.
MULTI_FRAME_FORMATS: dict[str, Callable[..., int]] = {
    m.EXTENSION: m.write_frames for m in (mcap,) if getattr(m, "MULTI_FRAME", False)
}

#: Extension -> reader ``path -> [PointCloud, ...]`` (one per frame; one for single-frame
#: formats). Each reads what its writer wrote: :func:`read_frames` and ``convert``.
READERS: dict[str, Callable[[str | os.PathLike[str]], list[PointCloud]]] = {
    m.EXTENSION: m.read_frames for m in (ply, pcd, npz, las, mcap)
}

#: Extensions whose writer also takes the scan's ``metadata`` (string keys to JSON text).
METADATA_FORMATS = (".las", ".mcap")

#: Extension -> (import name, extra) of the optional library a format needs.
OPTIONAL_LIBRARIES: dict[str, tuple[str, str]] = {".las": ("laspy", "las"),
                                                  ".mcap": ("mcap_ros2", "mcap")}


def check_output(path: str | os.PathLike[str], option: str = "--out") -> Path:
    """The one check of a cloud file to write: a known extension whose library is
    installed, in a folder that takes new files. Returns ``path`` as a Path."""
    p = Path(path)
    ext = p.suffix.lower()
    if ext not in FORMATS:
        raise ConfigError(f"{option} must end in one of {', '.join(FORMATS)}, not "
                          f"{p.suffix or '(no extension)'!r}", field=option.lstrip("-"))
    lib = OPTIONAL_LIBRARIES.get(ext)
    if lib is not None and importlib.util.find_spec(lib[0]) is None:
        raise ConfigError(f"{option} {ext} needs {lib[0]}: pip install 'cdma-lidar[{lib[1]}]' "
                          "(or write .ply, .pcd or .npz)", field=option.lstrip("-"))
    return check_writable(p, option)


def write(cloud: PointCloud, path: str | os.PathLike[str],
          metadata: Mapping[str, str] | None = None) -> int:
    """Write ``cloud`` in the format its extension names (.ply, .pcd, .npz, .las, .mcap);
    ``metadata`` goes into the formats that keep it (:data:`METADATA_FORMATS`)."""
    p = check_output(path)
    ext = p.suffix.lower()
    n = (FORMATS[ext](cloud, p, metadata) if ext in METADATA_FORMATS  # type: ignore[call-arg]
         else FORMATS[ext](cloud, p))
    log.info("wrote %d points to %s", n, p)
    return n


def write_frames(clouds: Sequence[PointCloud], path: str | os.PathLike[str],
                 metadata: Mapping[str, str] | None = None) -> int:
    """Write every frame where the format holds several (.mcap), else the last one.

    ``metadata`` (string keys to JSON text: beam angles, wavelengths, configuration, the
    threshold, units and version) goes into the formats that keep it (.mcap, .las); the
    others have their fixed header fields.
    """
    if not clouds:
        raise ConfigError("no frame to write", field="out")
    p = Path(path)
    writer = MULTI_FRAME_FORMATS.get(p.suffix.lower())
    if writer is None:
        return write(clouds[-1], p, metadata)
    check_output(p)
    n = writer(clouds, p, metadata)
    log.info("wrote %d frames, %d points to %s", len(clouds), n, p)
    return n


def read_frames(path: str | os.PathLike[str]) -> list[PointCloud]:
    """Every frame of a cloud file cdma-lidar wrote, by extension; ConfigError otherwise."""
    p = Path(path)
    reader = READERS.get(p.suffix.lower())
    if reader is None:
        raise ConfigError(f"input must end in one of {', '.join(READERS)}, not "
                          f"{p.suffix or '(no extension)'!r}", field="in")
    if not p.is_file():
        raise ConfigError(f"{str(p)!r} does not exist or is not a file", field="in")
    try:
        return reader(p)
    except ConfigError:
        raise
    except Exception as exc:  # laspy, mcap and struct raise their own kinds
        raise ConfigError(f"{str(p)!r} cannot be read as {p.suffix.lower()} "
                          f"({type(exc).__name__}: {str(exc)[:120]}); is it a file "
                          "cdma-lidar wrote?", field="in") from None
