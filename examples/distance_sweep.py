"""Sweep a flat wall's distance and see the range error and the valid pixels change.

    python examples/distance_sweep.py [--quick] [--frames 2]

The virtual wall's echo falls as 1/r^2 (a physical link budget), so the SNR_XC falls,
the range error grows and, past the instrument's reach, pixels drop out.
"""

from __future__ import annotations

import argparse

import numpy as np

import cdma_lidar
from cdma_lidar.scene import load_scene
from cdma_lidar.scene.truth import compute_truth


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="three distances instead of eight")
    parser.add_argument("--frames", type=int, default=1, help="frames per distance (mean)")
    args = parser.parse_args()
    distances = [2.0, 8.0, 30.0] if args.quick else [1.0, 2.0, 4.0, 8.0, 15.0, 30.0, 60.0, 120.0]

    scene = load_scene("flat-wall")
    with cdma_lidar.open("virtual://flat-wall?seed=1") as dev:   # calibrate once
        cal = cdma_lidar.calibrate(dev, scene.calibration.target_distance_m, frame_id=0)

    print(f"{'distance m':>10} {'valid %':>8} {'SNR_XC dB':>10} {'median error cm':>16}")
    for d in distances:
        url = f"virtual://flat-wall?seed=1&distance={d}"
        combine = "mean" if args.frames > 1 else "last"
        result = cdma_lidar.scan(url, frames=args.frames, combine=combine, calibration=cal,
                                 frame_id=1, progress=False)
        image = result.image
        truth = compute_truth(load_scene(f"flat-wall?distance={d}")).range_m
        ok = image.valid & np.isfinite(truth)
        err = np.abs(image.range_m - truth)[ok]
        median_err = f"{100 * np.median(err):.2f}" if err.size else "-"
        print(f"{d:10.1f} {100 * image.valid.mean():8.1f} "
              f"{np.median(image.snr_xc_db):10.1f} {median_err:>16}")


if __name__ == "__main__":
    main()
