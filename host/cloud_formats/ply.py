"""PLY, binary little endian: one vertex per pixel that has a range (plus kept extra points).

Every field of :data:`cdma_lidar.host.pointcloud.POINT_FIELDS` is a vertex property of
the same name. Types use the PLY spec's sized names (``float32``, ``uint16``,
``int32``), the ones Open3D's tensor reader (``open3d.t.io.read_point_cloud``) keeps:
it skips ``ushort`` and ``short``. An empty cloud is a valid file with
``element vertex 0``.

The grid's size, the channel wavelengths (m) and the column rotations (deg) are header
comments. A list too long for one line is split over several comments of the same key,
:data:`VALUES_PER_LINE` values each, read back in order: readers cap a header line
(Open3D's RPly at 1,024 characters, and it aborts the process on a longer one), and a
160-column scan's rotations alone take about 2,100.

The vertex count in the header is checked against the bytes that follow it: a file cut
short (at a record boundary or not) is refused, not read as a smaller cloud.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from cdma_lidar.errors import ConfigError
from cdma_lidar.fileio import atomic_open
from cdma_lidar.host.cloud_formats.grid import cloud_from_records
from cdma_lidar.host.pointcloud import FLAG_BITS, POINT_FIELDS, PointCloud

__all__ = ["EXTENSION", "PLY_TYPES", "VALUES_PER_LINE", "read_frames", "write"]

#: File extension this module writes.
EXTENSION = ".ply"

#: numpy type -> PLY property type.
PLY_TYPES = {"<f4": "float32", "<i4": "int32", "<u2": "uint16"}

#: Values per comment line of a long list: 16 reprs of float64 take at most ~400
#: characters, well under RPly's 1,024.
VALUES_PER_LINE = 16


def _list_comments(key: str, values: np.ndarray) -> list[str]:
    """``comment KEY v v ...`` lines, :data:`VALUES_PER_LINE` values each (one if empty)."""
    vals = [repr(float(v)) for v in values]
    return [f"comment {key} " + " ".join(vals[i:i + VALUES_PER_LINE])
            for i in range(0, max(len(vals), 1), VALUES_PER_LINE)]


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
              *_list_comments("wavelengths_m", cloud.wavelengths_m),
              *_list_comments("angles_deg", cloud.angles_deg),
              f"element vertex {rec.size}"]
    header += [f"property {PLY_TYPES[t]} {name}" for name, t in POINT_FIELDS]
    header.append("end_header")
    with atomic_open(path, "wb") as fh:
        fh.write(("\n".join(header) + "\n").encode("ascii"))
        fh.write(rec.tobytes())
    return int(rec.size)


def read_frames(path: str | os.PathLike[str]) -> list[PointCloud]:
    """Read a PLY this module wrote (binary little endian, our properties) as one frame."""
    raw = Path(path).read_bytes()
    end = raw.find(b"end_header\n")
    if not raw.startswith(b"ply\n") or end < 0:
        raise ConfigError(f"{str(path)!r} is not a PLY file", field="in")
    header = raw[:end].decode("ascii", "replace").splitlines()
    if "format binary_little_endian 1.0" not in header:
        raise ConfigError(f"{str(path)!r}: only binary little-endian PLY is read", field="in")
    types = {v: k for k, v in PLY_TYPES.items()}
    props = [ln.split()[1:] for ln in header if ln.startswith("property ")]
    try:
        dt = np.dtype([(name, types[t]) for t, name in props])
    except KeyError as exc:
        raise ConfigError(f"{str(path)!r}: property type {exc} is not one cdma-lidar writes",
                          field="in") from None
    comments: dict[str, list[str]] = {}
    for ln in header:  # a key over several lines: its values in order
        words = ln.split()
        if len(words) > 1 and words[0] == "comment":
            comments.setdefault(words[1], []).extend(words[2:])
    shape = None
    if "channels" in comments:
        shape = (int(comments["channels"][0]), int(comments["channels"][2]))
    counts = [ln.split() for ln in header if ln.startswith("element vertex ")]
    body = raw[end + len(b"end_header\n"):]
    want = int(counts[0][2]) if counts else -1
    if want * dt.itemsize != len(body):
        raise ConfigError(f"{str(path)!r} is cut short or padded: its header says {want} "
                          f"vertices ({want * dt.itemsize} bytes), the file holds {len(body)} "
                          "bytes of them", field="in")
    rec = np.frombuffer(body, dtype=dt)
    return [cloud_from_records(
        rec, shape=shape,
        wavelengths_m=[float(v) for v in comments["wavelengths_m"]]
        if "wavelengths_m" in comments else None,
        angles_deg=[float(v) for v in comments["angles_deg"]]
        if "angles_deg" in comments else None)]
