"""Open a scanned cloud in Open3D, every point field kept as an attribute.

    python examples/open3d_cloud.py [--no-window]

Needs Open3D, which the base install leaves out: pip install 'cdma-lidar[open3d]'
(Linux also needs libusb-1.0-0). Without it this script says so and exits.
"""

from __future__ import annotations

import argparse
import os

import cdma_lidar
from cdma_lidar.errors import MissingExtra


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--no-window", action="store_true", help="print only, draw nothing")
    parser.add_argument("--quick", action="store_true", help="(same run; for the tests)")
    args = parser.parse_args()

    with cdma_lidar.open("virtual://paper-scene1?seed=1") as dev:
        cal = cdma_lidar.calibrate(dev, 0.5, frame_id=0)   # paper-scene1's target: 0.5 m
        result = cdma_lidar.scan(dev, calibration=cal, frame_id=1, progress=False)
    try:
        pcd = result.cloud.to_open3d()     # open3d.t.geometry.PointCloud
    except MissingExtra as exc:
        print(f"skipped: {exc}")
        return 0
    print(pcd)
    box = pcd.get_axis_aligned_bounding_box()
    print(f"bounds (m): {box.min_bound.numpy().round(2)} .. {box.max_bound.numpy().round(2)}")
    print(f"mean intensity {pcd.point.intensity.numpy().mean():.3g}, "
          f"rings {pcd.point.ring.numpy().min()} .. {pcd.point.ring.numpy().max()}")
    if not args.no_window and os.environ.get("DISPLAY"):
        import open3d as o3d  # present: to_open3d() worked

        o3d.visualization.draw_geometries([pcd.to_legacy()], window_name="cdma-lidar")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
