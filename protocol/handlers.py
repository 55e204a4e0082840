"""Device request handlers that need no session or stream logic, and the reply builders.

A handler is ``(endpoint, request, fields, after) -> Reply``: it acts on the decoded
fields, returns the reply, and appends to ``after`` what must happen once the reply
is queued. It refuses by returning :func:`nak` or raising ``ConfigError`` /
``DeviceError`` (answered NAK by the endpoint). Sessions and HELLO are in
:mod:`~cdma_lidar.protocol.device_sessions`, streams and RESEND in
:mod:`~cdma_lidar.protocol.streams`.
"""

from __future__ import annotations

import logging
from typing import TYPE_CHECKING

import numpy as np

from cdma_lidar.errors import DeviceError, FieldError
from cdma_lidar.protocol.config_keys import CONFIG_KEYS, config_key, decode_config, encode_config
from cdma_lidar.protocol.framing import Frame, frame_size
from cdma_lidar.protocol.messages import CaptureKind, ErrorCode, MsgType, encode_payload, head_size

if TYPE_CHECKING:
    from cdma_lidar.protocol.endpoint import DeviceEndpoint

__all__ = ["HANDLERS", "Reply", "ack", "nak", "reply"]

log = logging.getLogger(__name__)

#: A reply as cached for replay: (type, payload, signed); signed afresh each time sent.
Reply = tuple[MsgType, bytes, bool]
_READ_ONLY = {k.name for k in CONFIG_KEYS if k.read_only}
_CAPTURE_HEADER = head_size(MsgType.CAPTURE_DATA)  # bytes before the data (14)


def reply(ep: DeviceEndpoint, req: Frame, msg_type: MsgType, payload: bytes) -> Reply:
    """A reply, signed when the session and the request are."""
    return (msg_type, payload, ep.tx.signer is not None and (bool(req.sig) or req.joined))


def ack(ep: DeviceEndpoint, req: Frame) -> Reply:
    return reply(ep, req, MsgType.ACK, encode_payload(MsgType.ACK, {"request_type": req.msg_type}))


def nak(ep: DeviceEndpoint, req: Frame, code: ErrorCode, fld: str = "", detail: str = "",
        signed: bool | None = None) -> Reply:
    """NAK ``code`` naming field ``fld`` (both texts clipped to 255 UTF-8 bytes)."""
    ep.stats.naks += 1
    log.debug("NAK %s seq %d: %s %s %s", req.msg_type, req.seq, code.name, fld, detail)
    payload = encode_payload(MsgType.NAK, {"request_type": req.msg_type, "code": int(code),
                                           "field": clip(fld), "detail": clip(detail)})
    return reply(ep, req, MsgType.NAK, payload) if signed is None else \
        (MsgType.NAK, payload, signed)


def clip(s: str, limit: int = 255) -> str:
    """``s`` cut to at most ``limit`` UTF-8 bytes, on a character boundary."""
    return s.encode("utf-8")[:limit].decode("utf-8", errors="ignore")


def _config_get(ep: DeviceEndpoint, req: Frame, f: dict, after: list) -> Reply:
    if ep.stream is not None and ep.config is not None:
        values = dict(ep.config)  # no CONFIG_SET while streaming: still current
    else:
        values = ep.app.get_config()
        ep.config = dict(values)
    if f["keys"]:
        want = []
        for kid in f["keys"]:
            try:
                want.append(config_key(kid).name)
            except FieldError:
                return nak(ep, req, ErrorCode.UNKNOWN_KEY, f"key {kid}")
        values = {n: values[n] for n in want if n in values}
    payload = encode_payload(MsgType.CONFIG, {"items": encode_config(values)})
    if not ep.tx.fits(len(payload)):
        return nak(ep, req, ErrorCode.TOO_LARGE, "keys", "ask for fewer keys per CONFIG_GET")
    return reply(ep, req, MsgType.CONFIG, payload)


def _config_set(ep: DeviceEndpoint, req: Frame, f: dict, after: list) -> Reply:
    if ep.stream is not None:
        return nak(ep, req, ErrorCode.BUSY, "", "abort the running scan first")
    cfg = decode_config(f["items"])
    if cfg.unknown:
        return nak(ep, req, ErrorCode.UNKNOWN_KEY, f"key {cfg.unknown[0]}",
                   "key not known to this device")
    for name in cfg.values:
        if name in _READ_ONLY:
            return nak(ep, req, ErrorCode.READ_ONLY, name, f"{name} is read-only")
    ep.app.set_config(cfg.values)
    ep.config = ep.app.get_config()
    return ack(ep, req)


def _power_set(ep: DeviceEndpoint, req: Frame, f: dict, after: list) -> Reply:
    power = np.asarray(f["power"], dtype=np.uint16).reshape(f["channels"], f["columns"])
    ep.app.set_power(f["channel_start"], f["column_start"], power)
    return ack(ep, req)


def _power_get(ep: DeviceEndpoint, req: Frame, f: dict, after: list) -> Reply:
    m = np.asarray(ep.app.get_power(), dtype=np.uint16)
    r0, c0, nr, nc = f["channel_start"], f["column_start"], f["channels"], f["columns"]
    for name, start, n, have in (("channels", r0, nr, m.shape[0]), ("columns", c0, nc, m.shape[1])):
        if start + n > have:
            return nak(ep, req, ErrorCode.OUT_OF_RANGE, name,
                       f"{name[:-1]}_start + {name} must be at most {have}")
    payload = encode_payload(MsgType.POWER, {
        "channel_start": r0, "column_start": c0, "channels": nr, "columns": nc,
        "power": m[r0:r0 + nr, c0:c0 + nc]})
    if not ep.tx.fits(len(payload)):
        return nak(ep, req, ErrorCode.TOO_LARGE, "columns",
                   "ask for a smaller rectangle per POWER_GET")
    return reply(ep, req, MsgType.POWER, payload)


def _capture(ep: DeviceEndpoint, req: Frame, f: dict, after: list) -> Reply:
    key = (f["kind"], f["column"], f["channel"])
    if f["offset"] == 0 or ep.capture is None or ep.capture[0] != key:
        if f["offset"] != 0:
            return nak(ep, req, ErrorCode.NOT_AVAILABLE, "offset",
                       "read offset 0 first to take a capture")
        data = np.asarray(ep.app.capture(CaptureKind(f["kind"]), f["column"],
                                         f["channel"])).ravel()
        if data.dtype.kind not in "iu":
            raise DeviceError("capture is not integer data", code=ErrorCode.INTERNAL)
        lo, hi = (int(data.min()), int(data.max())) if data.size else (0, 0)
        dt = next(t for t in (np.int16, np.int32, np.int64)
                  if np.iinfo(t).min <= lo and hi <= np.iinfo(t).max)
        ep.capture = (key, data.astype(np.dtype(dt).newbyteorder("<")))
    arr = ep.capture[1]
    total, off = arr.size, f["offset"]
    if off > total:
        return nak(ep, req, ErrorCode.OUT_OF_RANGE, "offset",
                   f"offset must be 0..{total}, not {off}")
    room = (ep.tx.max_frame - frame_size(_CAPTURE_HEADER, ep.tx.signer is not None)) // arr.itemsize
    n = max(0, min(f["max_count"], room, total - off))
    payload = encode_payload(MsgType.CAPTURE_DATA, {
        "kind": f["kind"], "column": f["column"], "channel": f["channel"],
        "elem_bytes": arr.itemsize, "total": total, "offset": off,
        "data": arr[off:off + n].tobytes()})
    return reply(ep, req, MsgType.CAPTURE_DATA, payload)


def _status_get(ep: DeviceEndpoint, req: Frame, f: dict, after: list) -> Reply:
    return reply(ep, req, MsgType.STATUS, encode_payload(MsgType.STATUS, ep.status().to_fields()))


HANDLERS = {MsgType.CONFIG_GET: _config_get,
            MsgType.CONFIG_SET: _config_set, MsgType.POWER_SET: _power_set,
            MsgType.POWER_GET: _power_get, MsgType.CAPTURE: _capture,
            MsgType.STATUS_GET: _status_get}
