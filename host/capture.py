"""Debug captures: one column's raw ADC codes or one channel's correlation trace.

``cdma-lidar capture --port URL --kind {corr,raw} --column C --channel K --out FILE.npz
[--plot]`` scans column C once (the device captures from the last scanned frame) and
reads the capture through the protocol's CAPTURE request
(:meth:`cdma_lidar.protocol.link.HostLink.capture`):

* ``corr``: channel K's correlation output ``out`` over the lag gate (correlator
  units), with the lags (samples), their ranges (m; calibrated with ``--calibration``)
  and the peak the receiver reports: the paper's Fig. 3d.
* ``raw``: the column's ADC codes (int16, all averaged code repetitions and UID
  periods in time order), at ``chip_rate * samples_per_chip`` samples/s. Also written
  as a SigMF recording (``FILE.sigmf-data``, real int16 little endian ``ri16_le``,
  and ``FILE.sigmf-meta``, JSON per SigMF 1.0), the format SDR tools read.

The NPZ holds ``data`` plus ``kind``, ``column``, ``channel``, ``sample_rate_hz``,
``frame_id``, ``calibrated`` (whether ``range_m`` has the calibration offset removed)
and, for ``corr``, ``lag`` and ``range_m``; ``config`` is the device configuration as
JSON.
"""

from __future__ import annotations

import argparse
import datetime as _dt
import json
import logging
import os
import sys
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from cdma_lidar.errors import ConfigError
from cdma_lidar.fileio import atomic_open, atomic_write_text, check_writable
from cdma_lidar.host import pictures
from cdma_lidar.host.calibration import Calibration, toml_safe
from cdma_lidar.host.cli import connect_options
from cdma_lidar.host.connection import Device, connect
from cdma_lidar.host.ranging import lag_to_range_m
from cdma_lidar.host.settings import CAPTURE_KINDS
from cdma_lidar.version import __version__

__all__ = ["Capture", "capture", "cmd_capture", "write_sigmf"]

log = logging.getLogger(__name__)


class Capture(dict):
    """A capture as the arrays of its NPZ (see the module docstring)."""


def capture(device: Device, kind: str, column: int, channel: int, *,
            frame_id: int | None = None, offset_m: float | None = None) -> Capture:
    """Scan ``column`` once, then capture it (``kind`` ``corr`` or ``raw``).

    ``offset_m``: the calibration offset (m); None leaves the ranges raw (``calibrated``
    False in the capture: they still hold the system delay).
    """
    if kind not in CAPTURE_KINDS:
        raise ConfigError(f"kind must be one of {', '.join(CAPTURE_KINDS)}, not {kind!r}",
                          field="kind")
    if not 0 <= column < device.columns:
        raise ConfigError(f"--column must be from 0 to {device.columns - 1}, not {column}",
                          field="column")
    if not 0 <= channel < device.channels:
        raise ConfigError(f"--channel must be from 0 to {device.channels - 1}, not {channel}",
                          field="channel")
    results = list(device.link.scan(first_column=column, columns=1, frames=1, frame=frame_id))
    data = np.asarray(device.link.capture(kind, column=column, channel=channel))
    cfg = device.config
    spc = int(cfg["samples_per_chip"])
    rate = float(device.info.chip_rate_hz) * spc
    out = Capture(data=data, kind=np.array(kind), column=np.array(column),
                  channel=np.array(channel), sample_rate_hz=np.array(rate),
                  frame_id=np.array(int(results[0].frame) if results else -1),
                  config=np.array(json.dumps(toml_safe(dict(cfg)), sort_keys=True)),
                  calibrated=np.array(offset_m is not None))
    if kind == "corr":
        lag = int(cfg.get("gate_start", 0)) + np.arange(data.size)
        out["lag"] = lag
        out["range_m"] = lag_to_range_m(lag, spc, float(device.info.chip_rate_hz),
                                        offset_m or 0.0)
        if results:
            out["peak_lag"] = np.array(int(results[0].records["peak_lag"][channel]))
    log.info("captured %s of column %d channel %d: %d values", kind, column, channel, data.size)
    return out


def write_sigmf(data: NDArray[np.int16], sample_rate_hz: float, path: str | os.PathLike[str],
                description: str) -> tuple[Path, Path]:
    """Write ``path.sigmf-data`` (ri16_le) and ``path.sigmf-meta`` (SigMF 1.0 JSON)."""
    base = Path(path).with_suffix("")
    dpath, mpath = Path(f"{base}.sigmf-data"), Path(f"{base}.sigmf-meta")
    with atomic_open(dpath, "wb") as fh:
        fh.write(np.asarray(data, dtype="<i2").tobytes())
    meta = {
        "global": {"core:datatype": "ri16_le", "core:sample_rate": float(sample_rate_hz),
                   "core:version": "1.0.0", "core:num_channels": 1,
                   "core:description": description,
                   "core:recorder": f"cdma-lidar {__version__}"},
        "captures": [{"core:sample_start": 0,
                      "core:datetime": _dt.datetime.now(_dt.UTC).isoformat(
                          timespec="microseconds").replace("+00:00", "Z")}],
        "annotations": [],
    }
    atomic_write_text(mpath, json.dumps(meta, indent=2) + "\n")
    return dpath, mpath


def _say(text: str) -> None:
    sys.stdout.write(text + "\n")
    sys.stdout.flush()


def cmd_capture(args: argparse.Namespace) -> int:
    """Capture, write the NPZ (and SigMF, PNG)."""
    out = Path(args.out)
    if out.suffix.lower() != ".npz":
        raise ConfigError(f"--out must be a .npz file, not {str(out)!r}", field="out")
    check_writable(out, "--out")
    if args.frame_id is not None and not 0 <= args.frame_id <= 2**31 - 1:
        raise ConfigError(f"--frame-id must be from 0 to {2**31 - 1}, not {args.frame_id}",
                          field="frame_id")
    cal = Calibration.load(args.calibration) if args.calibration else None
    with connect(args.port, **connect_options(args)) as dev:
        if cal is not None:
            cal.check_applies(dev.identity(), dev.calibration_config())
        cap = capture(dev, args.kind, args.column, args.channel, frame_id=args.frame_id,
                      offset_m=cal.offset_m if cal else None)
    with atomic_open(out, "wb") as fh:
        np.savez(fh, **cap)
    files = [out]
    if args.kind == "raw":
        files += list(write_sigmf(cap["data"], float(cap["sample_rate_hz"]), out,
                                  f"cdma-lidar raw ADC codes, column {args.column}"))
    if args.plot:
        png = out.with_suffix(".png")
        pictures.capture_plot(cap, png)
        files.append(png)
    _say(f"captured {cap['data'].size} {args.kind} values of column {args.column}"
         + (f" channel {args.channel}" if args.kind == "corr" else ""))
    for f in files:
        _say(f"wrote {f}")
    return 0
