"""``cdma-lidar demo``: calibrate and scan paper-scene1 on the virtual device, with pictures.

The README's main job. It sits at the top of the stack because it composes the
simulated world (for the ground truth it compares against), the virtual device and
the host, which no lower layer may do. Its options are registered by
:mod:`cdma_lidar.cli`, so that ``cdma-lidar demo --help`` loads none of this stack.
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
import time
from pathlib import Path

import numpy as np

import cdma_lidar.virtual  # noqa: F401  (importing it registers the virtual:// URL scheme)
from cdma_lidar.errors import ConfigError
from cdma_lidar.fileio import check_writable
from cdma_lidar.host.connection import connect
from cdma_lidar.host.ranging import estimate_ranges, precision_eq27_m
from cdma_lidar.host.scan import ScanOptions, calibrate_device, run_scan, summarise
from cdma_lidar.scene import load_scene
from cdma_lidar.scene.truth import compute_truth

__all__ = ["DEMO_SCENE", "cmd_demo"]

#: The built-in scene the demo scans: the letters "CDMA LIDAR" at about 5 m.
DEMO_SCENE = "paper-scene1"


def _say(*parts: object) -> None:
    """One line of command output on stdout (CLI results, not logging)."""
    sys.stdout.write(" ".join(str(p) for p in parts) + "\n")
    sys.stdout.flush()


def cmd_demo(args: argparse.Namespace) -> int:
    """Calibrate and scan the paper's scene 1 on the virtual device; print a summary."""

    folder = Path(args.out)
    try:
        folder.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise ConfigError(f"--out {str(folder)!r}: cannot create the folder ({exc.strerror}); "
                          "choose a writable place", field="out") from None
    check_writable(folder / "calibration.toml", "--out")
    t0 = time.monotonic()
    scene = load_scene(DEMO_SCENE)
    url = f"virtual://{DEMO_SCENE}?seed={args.seed}"
    with connect(url) as dev:
        cal = calibrate_device(dev, scene.calibration.target_distance_m, shots=20,
                               frame_id=0)
        cal.save(folder / "calibration.toml")
        res = run_scan(dev, folder / f"{DEMO_SCENE}.ply", ScanOptions(offset_m=cal.offset_m),
                       progress=not args.no_progress, pictures_too=True, frame_id=1)
    truth = compute_truth(scene).range_m
    s = summarise(res.image, truth)
    rc = res.image.config
    obj_valid = res.image.valid & np.isfinite(truth)
    sigma = float(precision_eq27_m(rc.chip_rate_hz, rc.samples_per_symbol,
                                   snr_xc_db=float(np.median(res.image.snr_xc_db[obj_valid]))))
    _say(f"device        {url} ({dev.info.serial})")
    _say(f"calibration   offset {cal.offset_m:.4f} m, spread {cal.spread_m:.4f} m "
          f"({cal.samples} returns)")
    _say(f"pixels        {int(s['pixels'])} ({dev.channels} channels x {dev.columns} columns), "
          f"{int(s['object_pixels'])} on objects")
    _say(f"valid         {100 * s['valid_fraction']:.1f} % of all pixels, "
          f"{100 * s['object_valid_fraction']:.1f} % of object pixels, "
          f"{int(s['false_valid'])} valid without an object")
    _say(f"range error   median {100 * s['median_error_m']:.2f} cm, 95th percentile "
          f"{100 * s['p95_error_m']:.2f} cm (eq. 27 precision {100 * sigma:.2f} cm)")
    for method in ("none", "parabolic"):
        alt = estimate_ranges(res.data, dataclasses.replace(rc, method=method))
        e = summarise(alt, truth)
        _say(f"  {method:9s}   median {100 * e['median_error_m']:.2f} cm, 95th percentile "
              f"{100 * e['p95_error_m']:.2f} cm")
    for f in res.files:
        _say(f"wrote         {f}")
    _say(f"time          {time.monotonic() - t0:.1f} s")
    return 0
