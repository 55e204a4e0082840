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
  offset and PointField datatype, little endian, each at an offset that is a multiple of
  its size (:data:`ALIGNED`, ``point_step`` 44: numpy's C alignment, two pad bytes after
  ``ring``), so a reader can view the buffer as float32 without copying.

The file also holds, for tools that show a cloud in a scene:

* one ``tf2_msgs/msg/TFMessage`` on :data:`TF_TOPIC` (``/tf_static``) at the first
  frame's stamp: the identity transform from :data:`PARENT_FRAME` (``base_link``) to
  ``cdma_lidar``, so Foxglove and RViz have a fixed frame to draw in;
* a metadata record :data:`METADATA_NAME` (``cdma_lidar``): string keys to JSON text,
  given by the caller (the scan writes the beam elevation and azimuth of every pixel from
  the grating, the channel wavelengths, the column rotations, the device identity and
  configuration, the scan options and the intensity unit).
"""

from __future__ import annotations

import json
import os
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

from cdma_lidar.errors import ConfigError
from cdma_lidar.fileio import atomic_open
from cdma_lidar.host.cloud_formats.grid import cloud_from_records
from cdma_lidar.host.pointcloud import POINT_FIELDS, PointCloud

__all__ = [
    "ALIGNED",
    "EXTENSION",
    "FRAME_ID",
    "METADATA_NAME",
    "MULTI_FRAME",
    "PARENT_FRAME",
    "POINTCLOUD2_MSGDEF",
    "TFMESSAGE_MSGDEF",
    "TF_TOPIC",
    "TOPIC",
    "read_frames",
    "read_metadata",
    "write",
    "write_frames",
]

#: File extension this module writes.
EXTENSION = ".mcap"
#: The format holds a sequence of frames (the scan writes every frame, not only the last).
MULTI_FRAME = True
#: Topic and frame id of the messages.
TOPIC = "/cdma_lidar/points"
FRAME_ID = "cdma_lidar"
#: The static transform's topic and parent frame, and the metadata record's name.
TF_TOPIC = "/tf_static"
PARENT_FRAME = "base_link"
METADATA_NAME = "cdma_lidar"

#: The point record with every field aligned to its size (point_step 44).
ALIGNED = np.dtype([(n, t) for n, t in POINT_FIELDS], align=True)

#: tf2_msgs/msg/TFMessage with its dependencies, in the ROS 2 msgdef text format.
TFMESSAGE_MSGDEF = """geometry_msgs/TransformStamped[] transforms
================================================================================
MSG: geometry_msgs/TransformStamped
std_msgs/Header header
string child_frame_id
geometry_msgs/Transform transform
================================================================================
MSG: std_msgs/Header
builtin_interfaces/Time stamp
string frame_id
================================================================================
MSG: builtin_interfaces/Time
int32 sec
uint32 nanosec
================================================================================
MSG: geometry_msgs/Transform
geometry_msgs/Vector3 translation
geometry_msgs/Quaternion rotation
================================================================================
MSG: geometry_msgs/Vector3
float64 x
float64 y
float64 z
================================================================================
MSG: geometry_msgs/Quaternion
float64 x
float64 y
float64 z
float64 w
"""

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


def _stamp(unix_s: float) -> dict:
    sec = int(np.floor(unix_s))
    return {"sec": sec, "nanosec": min(round((unix_s - sec) * 1e9), 999_999_999)}


def _message(cloud: PointCloud) -> dict:
    packed = cloud.records(keep_rejected=True)
    rec = np.zeros(packed.shape, ALIGNED)
    for name, _ in POINT_FIELDS:
        rec[name] = packed[name]
    k, c = cloud.shape
    height, width = (k, c) if not cloud.extra.size and rec.size else (1, rec.size)
    dt = rec.dtype
    fields = [{"name": n, "offset": dt.fields[n][1], "datatype": _DATATYPE[t], "count": 1}
              for n, t in POINT_FIELDS]
    return {"header": {"stamp": _stamp(cloud.stamp_unix_s), "frame_id": FRAME_ID},
            "height": height, "width": width, "fields": fields, "is_bigendian": False,
            "point_step": dt.itemsize, "row_step": dt.itemsize * width,
            "data": rec.tobytes(), "is_dense": bool(np.all(np.isfinite(rec["x"])))}


def write_frames(clouds: Sequence[PointCloud], path: str | os.PathLike[str],
                 metadata: Mapping[str, str] | None = None) -> int:
    """Write one PointCloud2 per cloud (frame order), the static transform and
    ``metadata`` (string to string); returns the points written in all."""
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
        tf = writer.register_msgdef("tf2_msgs/msg/TFMessage", TFMESSAGE_MSGDEF)
        t0 = clouds[0].stamp_unix_s if clouds else 0.0
        identity = {"translation": {"x": 0.0, "y": 0.0, "z": 0.0},
                    "rotation": {"x": 0.0, "y": 0.0, "z": 0.0, "w": 1.0}}
        writer.write_message(topic=TF_TOPIC, schema=tf, message={"transforms": [
            {"header": {"stamp": _stamp(t0), "frame_id": PARENT_FRAME},
             "child_frame_id": FRAME_ID, "transform": identity}]},
            log_time=round(t0 * 1e9), publish_time=round(t0 * 1e9))
        # mcap_ros2's Writer has no metadata call: the mcap Writer it wraps has one
        writer._writer.add_metadata(METADATA_NAME, dict(metadata or {}))
        for seq, cloud in enumerate(clouds):
            msg = _message(cloud)
            t_ns = round(cloud.stamp_unix_s * 1e9)
            writer.write_message(topic=TOPIC, schema=schema, message=msg, log_time=t_ns,
                                 publish_time=t_ns, sequence=seq)
            total += msg["height"] * msg["width"]
        writer.finish()
    return total


def write(cloud: PointCloud, path: str | os.PathLike[str],
          metadata: Mapping[str, str] | None = None) -> int:
    """Write one frame (one message); returns the number of points."""
    return write_frames([cloud], path, metadata)


def _reader(fh: Any) -> Any:
    try:
        from mcap.reader import make_reader  # optional extra `mcap`
        from mcap_ros2.decoder import DecoderFactory  # optional extra `mcap` too
    except ImportError as exc:
        raise ConfigError("reading .mcap needs mcap and mcap-ros2-support: pip install "
                          "'cdma-lidar[mcap]'", field="in") from exc
    return make_reader(fh, decoder_factories=[DecoderFactory()])


def read_metadata(path: str | os.PathLike[str]) -> dict[str, str]:
    """The :data:`METADATA_NAME` record (empty when the file has none)."""
    with open(path, "rb") as fh:
        for rec in _reader(fh).iter_metadata():
            if rec.name == METADATA_NAME:
                return dict(rec.metadata)
    return {}


def read_frames(path: str | os.PathLike[str]) -> list[PointCloud]:
    """Every PointCloud2 on :data:`TOPIC`, in order, as clouds (any field offsets)."""
    meta = read_metadata(path)
    wl = json.loads(meta["wavelengths_m"]) if "wavelengths_m" in meta else None
    ang = json.loads(meta["angles_deg"]) if "angles_deg" in meta else None
    types = {v: k for k, v in _DATATYPE.items()}
    clouds = []
    with open(path, "rb") as fh:
        for _, _, _, msg in _reader(fh).iter_decoded_messages(topics=[TOPIC]):
            dt = np.dtype({"names": [f.name for f in msg.fields],
                           "formats": [types[f.datatype] for f in msg.fields],
                           "offsets": [f.offset for f in msg.fields],
                           "itemsize": msg.point_step})
            rec = np.frombuffer(bytes(msg.data), dtype=dt)
            organised = msg.height > 1
            clouds.append(cloud_from_records(
                rec, shape=(msg.height, msg.width) if organised else None,
                wavelengths_m=wl if organised else None, angles_deg=ang if organised else None,
                stamp_unix_s=msg.header.stamp.sec + msg.header.stamp.nanosec * 1e-9))
    return clouds
