"""Watch a near-far scan live in rerun from Python: cloud, range and SNR_XC images, power.

    python examples/live_view.py [--web] [--frames 4] [--out out/examples]

Saves the recording to OUT/near-far.rrd (open it with ``rerun OUT/near-far.rrd``); with
``--web`` also serves rerun's web viewer until Ctrl-C. Needs the extra ``view``:
pip install 'cdma-lidar[view]'. Without it this script says so and exits.
The command line does the same: cdma-lidar view --port virtual://near-far --near-far ...
"""

from __future__ import annotations

import argparse
from pathlib import Path

import cdma_lidar
from cdma_lidar.errors import MissingExtra
from cdma_lidar.host.view import LiveView, ViewOptions, wait_forever


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=4, help="frames (near-far needs 2+)")
    parser.add_argument("--web", action="store_true", help="also serve a web viewer")
    parser.add_argument("--out", default="out/examples", help="folder for the .rrd file")
    parser.add_argument("--quick", action="store_true", help="three frames")
    args = parser.parse_args()
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)

    try:
        view = LiveView(ViewOptions(save=str(out / "near-far.rrd"), web=args.web,
                                    color_by="snr"))
    except MissingExtra as exc:
        print(f"skipped: {exc}")
        return 0
    if view.url:
        print(f"web viewer: {view.url}")
    cdma_lidar.scan("virtual://near-far?seed=1", frames=3 if args.quick else args.frames,
                    near_far=True, frame_id=1, progress=False, on_frame=view.log_frame)
    print(f"recorded {view.frames} frames to {out / 'near-far.rrd'}")
    view.close(wait=wait_forever)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
