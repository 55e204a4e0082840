"""Device requests that need no session or stream logic: configuration, power, capture,
status.

A handler is ``(request, fields) -> Reply``: it acts on the decoded fields and
returns the reply. It refuses by returning a NAK
(:meth:`~cdma_lidar.protocol.transmit.Transmitter.nak`) or raising ``ConfigError`` /
``DeviceError`` (answered NAK by the endpoint). Sessions
and HELLO are in :mod:`~cdma_lidar.protocol.device_sessions`, streams and RESEND in
:mod:`~cdma_lidar.protocol.streams`.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from typing import Any

import numpy as np
from numpy.typing import NDArray

from cdma_lidar.errors import DeviceError, FieldError
from cdma_lidar.protocol.config_keys import CONFIG_KEYS, config_key, decode_config, encode_config
from cdma_lidar.protocol.framing import Frame, frame_size
from cdma_lidar.protocol.messages import CaptureKind, ErrorCode, MsgType, encode_payload, head_size
from cdma_lidar.protocol.streams import Streams
from cdma_lidar.protocol.transmit import Reply, Transmitter
from cdma_lidar.protocol.views import Status

__all__ = ["AppRequests"]

log = logging.getLogger(__name__)

_READ_ONLY = {k.name for k in CONFIG_KEYS if k.read_only}
_CAPTURE_HEADER = head_size(MsgType.CAPTURE_DATA)  # bytes before the data (14)


class AppRequests:
    """CONFIG_GET/SET, POWER_GET/SET, CAPTURE and STATUS_GET of one connection; owns the
    capture being read out.

    Args:
        app: the device application.
        tx: the connection's transmitter (its max frame and signing size the replies).
        streams: the connection's streams (no CONFIG_SET while one runs).
        status: the current status (as STATUS sends it).
    """

    def __init__(self, app: Any, tx: Transmitter, streams: Streams,
                 status: Callable[[], Status]) -> None:
        self.app, self.tx, self.streams, self.status = app, tx, streams, status
        #: The capture being read out: ((kind, column, channel), its data).
        self.capture: tuple[tuple[int, int, int], NDArray] | None = None

    def handlers(self) -> dict[MsgType, Callable[[Frame, dict], Reply]]:
        return {MsgType.CONFIG_GET: self._config_get, MsgType.CONFIG_SET: self._config_set,
                MsgType.POWER_SET: self._power_set, MsgType.POWER_GET: self._power_get,
                MsgType.CAPTURE: self._capture, MsgType.STATUS_GET: self._status_get}

    def _config_get(self, req: Frame, f: dict) -> Reply:
        if self.streams.stream is not None and self.streams.config is not None:
            values = dict(self.streams.config)  # no CONFIG_SET while streaming: still current
        else:
            values = self.app.get_config()
        if f["keys"]:
            want = []
            for kid in f["keys"]:
                try:
                    want.append(config_key(kid).name)
                except FieldError:
                    return self.tx.nak(req, ErrorCode.UNKNOWN_KEY, f"key {kid}")
            values = {n: values[n] for n in want if n in values}
        # The model checked its configuration: encoded as it is (the host checks it).
        payload = encode_payload(MsgType.CONFIG, {"items": encode_config(values, check=False)})
        if not self.tx.fits(len(payload)):
            return self.tx.nak(req, ErrorCode.TOO_LARGE, "keys",
                               "ask for fewer keys per CONFIG_GET")
        return self.tx.reply(req, MsgType.CONFIG, payload)

    def _config_set(self, req: Frame, f: dict) -> Reply:
        if self.streams.stream is not None:
            return self.tx.nak(req, ErrorCode.BUSY, "", "abort the running scan first")
        cfg = decode_config(f["items"])
        if cfg.unknown:
            return self.tx.nak(req, ErrorCode.UNKNOWN_KEY, f"key {cfg.unknown[0]}",
                       "key not known to this device")
        for name in cfg.values:
            if name in _READ_ONLY:
                return self.tx.nak(req, ErrorCode.READ_ONLY, name, f"{name} is read-only")
        self.app.set_config(cfg.values)
        return self.tx.ack(req)

    def _power_set(self, req: Frame, f: dict) -> Reply:
        power = np.asarray(f["power"], dtype=np.uint16).reshape(f["channels"], f["columns"])
        self.app.set_power(f["channel_start"], f["column_start"], power)
        return self.tx.ack(req)

    def _power_get(self, req: Frame, f: dict) -> Reply:
        m = np.asarray(self.app.get_power(), dtype=np.uint16)
        r0, c0, nr, nc = f["channel_start"], f["column_start"], f["channels"], f["columns"]
        for name, start, n, have in (("channels", r0, nr, m.shape[0]),
                                     ("columns", c0, nc, m.shape[1])):
            if start + n > have:
                return self.tx.nak(req, ErrorCode.OUT_OF_RANGE, name,
                           f"{name[:-1]}_start + {name} must be at most {have}")
        payload = encode_payload(MsgType.POWER, {
            "channel_start": r0, "column_start": c0, "channels": nr, "columns": nc,
            "power": m[r0:r0 + nr, c0:c0 + nc]})
        if not self.tx.fits(len(payload)):
            return self.tx.nak(req, ErrorCode.TOO_LARGE, "columns",
                       "ask for a smaller rectangle per POWER_GET")
        return self.tx.reply(req, MsgType.POWER, payload)

    def _capture(self, req: Frame, f: dict) -> Reply:
        key = (f["kind"], f["column"], f["channel"])
        if f["offset"] == 0 or self.capture is None or self.capture[0] != key:
            if f["offset"] != 0:
                return self.tx.nak(req, ErrorCode.NOT_AVAILABLE, "offset",
                           "read offset 0 first to take a capture")
            data = np.asarray(self.app.capture(CaptureKind(f["kind"]), f["column"],
                                             f["channel"])).ravel()
            if data.dtype.kind not in "iu":
                raise DeviceError("capture is not integer data", code=ErrorCode.INTERNAL)
            lo, hi = (int(data.min()), int(data.max())) if data.size else (0, 0)
            dt = next(t for t in (np.int16, np.int32, np.int64)
                      if np.iinfo(t).min <= lo and hi <= np.iinfo(t).max)
            self.capture = (key, data.astype(np.dtype(dt).newbyteorder("<")))
        arr = self.capture[1]
        total, off = arr.size, f["offset"]
        if off > total:
            return self.tx.nak(req, ErrorCode.OUT_OF_RANGE, "offset",
                       f"offset must be 0..{total}, not {off}")
        room = (self.tx.max_frame - frame_size(_CAPTURE_HEADER, self.tx.signer is not None)) \
            // arr.itemsize
        n = max(0, min(f["max_count"], room, total - off))
        payload = encode_payload(MsgType.CAPTURE_DATA, {
            "kind": f["kind"], "column": f["column"], "channel": f["channel"],
            "elem_bytes": arr.itemsize, "total": total, "offset": off,
            "data": arr[off:off + n].tobytes()})
        return self.tx.reply(req, MsgType.CAPTURE_DATA, payload)

    def _status_get(self, req: Frame, f: dict) -> Reply:
        return self.tx.reply(req, MsgType.STATUS,
                             encode_payload(MsgType.STATUS, self.status().to_fields()))
