"""MCAP with ROS 2 ``sensor_msgs/msg/PointCloud2`` messages (optional extra ``mcap``).

One message per frame on topic :data:`TOPIC`, CDR-encoded through ``mcap`` and
``mcap-ros2-support`` (no ROS installation needed); Foxglove Studio and ``ros2 bag``
open the file. Each message:

* ``header.frame_id`` = :data:`FRAME_ID` (``cdma_lidar``: the sensor frame of
  :mod:`cdma_lidar.host.pointcloud`, x forward, y left, z up, origin at the grating);
* ``header.stamp`` = the host's UTC clock when the frame's first column arrived
  (``PointCloud.stamp_unix_s``); the per-point ``t`` (s) counts from it, the
  convention of LIO-SAM and FAST-LIO's ``time`` field; log and publish times are the
  same instant in ns;
* organised, ``height`` = channels and ``width`` = columns (pixels without a range
  are NaN, ``is_dense`` false), or ``height`` 1 when extra points (kept foreign
  returns) are present;
* ``fields``: every entry of :data:`cdma_lidar.host.pointcloud.POINT_FIELDS` with its
  offset and PointField datatype, little endian.
"""

from __future__ import annotations

import os
from collections.abc import Sequence

import numpy as np

from cdma_lidar.errors import ConfigError
from cdma_lidar.fileio import atomic_open
from cdma_lidar.host.pointcloud import POINT_FIELDS, PointCloud

__all__ = ["EXTENSION", "FRAME_ID", "MULTI_FRAME", "POINTCLOUD2_MSGDEF", "TOPIC", "write",
           "write_frames"]

#: File extension this module writes.
EXTENSION = ".mcap"
#: The format holds a sequence of frames (the scan writes every frame, not only the last).
MULTI_FRAME = True
#: Topic and frame id of the messages.
TOPIC = "/cdma_lidar/points"
FRAME_ID = "cdma_lidar"

#: sensor_msgs/msg/PointCloud2 with its dependencies, in the ROS 2 msgdef text format.
POINTCLOUD2_MSGDEF = """std_msgs/Header header
uint32 height
uint32 width
sensor_msgs/PointField[] fields
bool is_bigendian
uint32 point_step
uint32 row_step
uint8[] data
bool is_dense
================================================================================
MSG: std_msgs/Header
builtin_interfaces/Time stamp
string frame_id
================================================================================
MSG: builtin_interfaces/Time
int32 sec
uint32 nanosec
================================================================================
MSG: sensor_msgs/PointField
uint8 INT8    = 1
uint8 UINT8   = 2
uint8 INT16   = 3
uint8 UINT16  = 4
uint8 INT32   = 5
uint8 UINT32  = 6
uint8 FLOAT32 = 7
uint8 FLOAT64 = 8
string name
uint32 offset
uint8  datatype
uint32 count
"""

_DATATYPE = {"<f4": 7, "<i4": 5, "<u2": 4}


def _message(cloud: PointCloud) -> dict:
    rec = cloud.records(keep_rejected=True)
    k, c = cloud.shape
    height, width = (k, c) if not cloud.extra.size and rec.size else (1, rec.size)
    dt = rec.dtype
    sec = int(np.floor(cloud.stamp_unix_s))
    nsec = min(round((cloud.stamp_unix_s - sec) * 1e9), 999_999_999)
    fields = [{"name": n, "offset": dt.fields[n][1], "datatype": _DATATYPE[t], "count": 1}
              for n, t in POINT_FIELDS]
    return {"header": {"stamp": {"sec": sec, "nanosec": nsec}, "frame_id": FRAME_ID},
            "height": height, "width": width, "fields": fields, "is_bigendian": False,
            "point_step": dt.itemsize, "row_step": dt.itemsize * width,
            "data": rec.tobytes(), "is_dense": bool(np.all(np.isfinite(rec["x"])))}


def write_frames(clouds: Sequence[PointCloud], path: str | os.PathLike[str]) -> int:
    """Write one PointCloud2 per cloud (frame order); returns the points written in all."""
    try:
        from mcap_ros2.writer import Writer  # optional extra `mcap`: only for .mcap output
    except ImportError as exc:
        raise ConfigError("writing .mcap needs mcap and mcap-ros2-support: pip install "
                          "'cdma-lidar[mcap]' (or write .ply, .pcd, .las or .npz)",
                          field="out") from exc
    total = 0
    with atomic_open(path, "wb") as fh:
        writer = Writer(fh)
        schema = writer.register_msgdef("sensor_msgs/msg/PointCloud2", POINTCLOUD2_MSGDEF)
        for seq, cloud in enumerate(clouds):
            msg = _message(cloud)
            t_ns = round(cloud.stamp_unix_s * 1e9)
            writer.write_message(topic=TOPIC, schema=schema, message=msg, log_time=t_ns,
                                 publish_time=t_ns, sequence=seq)
            total += msg["height"] * msg["width"]
        writer.finish()
    return total


def write(cloud: PointCloud, path: str | os.PathLike[str]) -> int:
    """Write one frame (one message); returns the number of points."""
    return write_frames([cloud], path)
