"""Scan a built-in scene on the virtual device and look at the cloud with numpy.

    python examples/scan_preset.py [--scene paper-scene1] [--out out/examples]

Calibrates on the scene's zeroth-order target, scans one frame, writes a PLY (open it in
CloudCompare, MeshLab or Open3D) and prints what the numpy arrays hold.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

import cdma_lidar
from cdma_lidar.scene import load_scene


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scene", default="paper-scene1", help="built-in scene or .toml")
    parser.add_argument("--out", default="out/examples", help="folder for the PLY file")
    parser.add_argument("--quick", action="store_true", help="(same run; for the tests)")
    args = parser.parse_args()
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)

    target_m = load_scene(args.scene).calibration.target_distance_m
    with cdma_lidar.open(f"virtual://{args.scene}?seed=1") as dev:
        cal = cdma_lidar.calibrate(dev, target_m, frame_id=0)
        result = cdma_lidar.scan(dev, out / f"{args.scene}.ply", calibration=cal, frame_id=1,
                                 progress=False)

    cloud = result.cloud                          # organised: (channels, columns) arrays
    xyz = cloud.to_numpy()                        # (N, 3) x forward, y left, z up, in m
    snr = cloud.to_numpy(("snr_xc",))[:, 0]       # dB, one per point
    print(f"{args.scene}: {cloud.shape[0]} channels x {cloud.shape[1]} columns, "
          f"{len(xyz)} points with a range (offset {cal.offset_m:.3f} m)")
    print(f"range {np.min(np.linalg.norm(xyz, axis=1)):.2f} .. "
          f"{np.max(np.linalg.norm(xyz, axis=1)):.2f} m, SNR_XC median {np.median(snr):.1f} dB")
    print(f"x {xyz[:, 0].min():.2f} .. {xyz[:, 0].max():.2f} m, "
          f"y {xyz[:, 1].min():.2f} .. {xyz[:, 1].max():.2f} m, "
          f"z {xyz[:, 2].min():.2f} .. {xyz[:, 2].max():.2f} m")
    print(f"wrote {result.files[0]}")


if __name__ == "__main__":
    main()
