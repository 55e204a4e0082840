"""The Python quick start: open a device by URL, scan it, run a study, in one call each.

::

    import cdma_lidar

    with cdma_lidar.open("virtual://paper-scene1?seed=1") as dev:   # or /dev/ttyUSB0, ...
        cal = cdma_lidar.calibrate(dev, 0.5)   # zeroth-order target at 0.5 m
        result = cdma_lidar.scan(dev, frames=2, combine="mean", calibration=cal)
    xyz = result.cloud.to_numpy()          # (N, 3) x y z in m; .to_open3d() for Open3D
    table = cdma_lidar.run_study("detection", "out/detection", quick=True).table

``import cdma_lidar`` stays light: these names are loaded from this module on first use
(``cdma_lidar.__getattr__``). This module sits at the top of the layers, beside the CLI,
because it composes the virtual device (importing :mod:`cdma_lidar.virtual` registers
the ``virtual://`` URL scheme, so no other import is needed), the host and the studies.
The objects it returns are the host's and the study engine's own
(:class:`cdma_lidar.host.connection.Device`, :class:`cdma_lidar.host.scan.ScanResult`,
:class:`cdma_lidar.study.engine.RunResult`); docs/host.md and docs/studies.md describe them.
"""

from __future__ import annotations

import os
import tempfile
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

import cdma_lidar.virtual  # noqa: F401  (importing it registers the virtual:// URL scheme)
from cdma_lidar.host.calibration import Calibration
from cdma_lidar.host.connection import Device, connect
from cdma_lidar.host.pointcloud import PointCloud
from cdma_lidar.host.scan import ScanOptions, ScanResult, calibrate_device, run_scan
from cdma_lidar.study.catalogue import get_study
from cdma_lidar.study.engine import RunResult
from cdma_lidar.study.engine import run_study as _run_study

__all__ = ["calibrate", "open", "run_study", "scan"]


def open(url: str, *, timeout_s: float = 1.0, take_over: bool = False,
         key_file: str | None = None, settings: Mapping[str, Any] | None = None) -> Device:
    """Connect to the device at ``url``; use it as a context manager to close it.

    ``url`` is any port ``cdma-lidar --port`` takes: a device path, a pty,
    ``socket://HOST:PORT`` or ``virtual://SCENE?seed=N`` (a built-in scene such as
    ``paper-scene1`` or ``flat-wall?distance=7.5``, or a scene .toml). ``timeout_s``
    (s) is the wait for each answer; ``settings`` configures the device first
    (``{"averages": 20, "peaks": 4}``, as ``--set``).
    """
    device = connect(url, timeout_s=timeout_s, take_over=take_over, key_file=key_file)
    if settings:
        try:
            device.link.set_config(**dict(settings))
            device.refresh_config()
        except BaseException:
            device.close()
            raise
    return device


def scan(device: Device | str, out: str | os.PathLike[str] | None = None, *,
         frames: int = 1,
         calibration: Calibration | str | os.PathLike[str] | None = None,
         frame_id: int | None = None, progress: bool = True,
         on_frame: Callable[[int, PointCloud, NDArray[np.float64]], None] | None = None,
         **options: Any) -> ScanResult:
    """Scan ``frames`` frames and return the clouds (and write ``out`` if given).

    ``device``: an open :class:`Device` or a URL (opened and closed here). ``out``: a
    .ply, .pcd, .npz, .las or .mcap file, or None to keep the result in memory only.
    ``calibration``: a :class:`Calibration` (from :func:`calibrate`) or its TOML file
    (``cdma-lidar calibrate``): its offset and intensity gain apply. ``frame_id`` seeds a
    virtual device's noise (same seed and id, same cloud). ``on_frame(index, cloud,
    power)`` sees each frame as it is finished.
    ``options`` are :class:`cdma_lidar.host.scan.ScanOptions` fields (``near_far=True``,
    ``combine="mean"``, ``snr_threshold_db=12``, ...).
    """
    if isinstance(device, str):
        with open(device) as dev:
            return scan(dev, out, frames=frames, calibration=calibration, frame_id=frame_id,
                        progress=progress, on_frame=on_frame, **options)
    if calibration is not None:
        cal = (calibration if isinstance(calibration, Calibration)
               else Calibration.load(calibration))
        cal.check_applies(device.identity(), device.calibration_config())
        options = {"offset_m": cal.offset_m, "intensity_gain": cal.intensity_gain, **options}
    opts = ScanOptions(frames=frames, **options)
    if out is not None:
        return run_scan(device, out, opts, progress=progress, frame_id=frame_id,
                        on_frame=on_frame)
    # run_scan writes a file; until the scan is split into open / acquire / finish, an
    # in-memory scan writes a small .npz into a folder that is removed at once.
    with tempfile.TemporaryDirectory(prefix="cdma-lidar-") as tmp:
        result = run_scan(device, Path(tmp) / "scan.npz", opts, progress=progress,
                          frame_id=frame_id, on_frame=on_frame)
    result.files = []
    return result


def calibrate(device: Device | str, target_distance_m: float, *, shots: int = 20,
              out: str | os.PathLike[str] | None = None,
              frame_id: int | None = None) -> Calibration:
    """Measure the system delay on the zeroth-order target ``target_distance_m`` (m) away.

    ``device``: an open :class:`Device` or a URL. ``shots`` repeated shots go into one
    range histogram (Supplementary Note 6); ``out`` also saves the calibration as TOML
    for ``cdma-lidar scan --calibration``. A virtual scene names its target distance
    (``cdma_lidar.scene.load_scene(name).calibration.target_distance_m``).
    """
    if isinstance(device, str):
        with open(device) as dev:
            return calibrate(dev, target_distance_m, shots=shots, out=out, frame_id=frame_id)
    cal = calibrate_device(device, target_distance_m, shots=shots, frame_id=frame_id)
    if out is not None:
        cal.save(out)
    return cal


def run_study(name: str, out: str | os.PathLike[str], *, quick: bool = False,
              workers: int | None = 0, progress: bool = False, **settings: Any) -> RunResult:
    """Run the study ``name`` (``cdma-lidar study list``) into folder ``out``.

    ``quick``: the study's small grid. ``workers``: 0 (default) runs in this process,
    N a local Dask cluster of N processes (extra ``study``). ``settings`` override the
    study's settings (as ``--set KEY=VALUE``). The result's ``table`` is the study's
    tidy table (``table.column("name")`` is a numpy array), also in ``out/results.csv``.
    """
    return _run_study(get_study(name), out, quick=quick, workers=workers, progress=progress,
                      overrides={k: str(v) for k, v in settings.items()})
