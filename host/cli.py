"""The host commands' parser: ``info``, ``scan``, ``view``, ``convert``, ``calibrate``, ``capture``.

Every command checks what it can before it touches the device (output folder
writable, extension known, numbers in range), so a bad argument costs nothing and
exits 2 with one line. Ports are any pyserial URL: a device path, a pty,
``socket://host:port`` or ``virtual://SCENE?seed=N`` (the built-in virtual device);
``scan`` also takes ``replay://FILE``, a recorded cloud fed back through the host
(:mod:`cdma_lidar.host.replay`).

This module holds only the options: it imports no numpy and none of the host stack, so
``cdma-lidar COMMAND --help`` starts as fast as Python does. What a command does is in
:mod:`cdma_lidar.host.commands` (``capture``'s in :mod:`cdma_lidar.host.capture`), imported
when the command runs; the defaults shown come from :mod:`cdma_lidar.host.settings`.
"""

from __future__ import annotations

import argparse
import math
from typing import Any

from cdma_lidar.errors import ConfigError
from cdma_lidar.host.settings import (
    CAPTURE_KINDS,
    COLOR_MAPS,
    COMBINE_MODES,
    DEFAULT_SNR_THRESHOLD_DB,
    GRPC_PORT,
    LOOPBACK,
    MIN_TIMEOUT_S,
    TARGET_DISTANCE_M,
    WEB_PORT,
)
from cdma_lidar.lazy import later

__all__ = ["add_port_options", "add_view_options", "connect_options", "register"]


#: The module that does the commands' work (``capture``'s: :mod:`cdma_lidar.host.capture`).
COMMANDS_MODULE = "cdma_lidar.host.commands"


def _positive_float(text: str) -> float:
    try:
        v = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"must be a number, not {text!r}") from None
    if not (math.isfinite(v) and v > 0):
        raise argparse.ArgumentTypeError(f"must be a positive number, not {text!r}")
    return v


def _float_in(lo: float, hi: float, unit: str) -> Any:
    """An argparse type: a number in (lo, hi] (``lo`` excluded when it is 0), in ``unit``."""
    def parse(text: str) -> float:
        v = _finite_float(text)
        if not ((lo < v if lo == 0 else lo <= v) and v <= hi):
            low = f"above {lo:g}" if lo == 0 else f"from {lo:g}"
            raise argparse.ArgumentTypeError(f"must be {low} to {hi:g} {unit}, not {text!r}")
        return v
    return parse


def _finite_float(text: str) -> float:
    try:
        v = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"must be a number, not {text!r}") from None
    if not math.isfinite(v):
        raise argparse.ArgumentTypeError(f"must be a finite number, not {text!r}")
    return v


def _reflectivity(text: str) -> float:
    v = _finite_float(text)
    if not 0 < v <= 1:
        raise argparse.ArgumentTypeError(f"must be a reflectivity in (0, 1], not {text!r}")
    return v


def _ghost(text: str) -> tuple[int, int]:
    try:
        start, length = (int(x) for x in text.split(":"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"must be START:LENGTH in samples, not {text!r}"
                                         ) from None
    if start < 0 or length < 1:
        raise argparse.ArgumentTypeError(f"needs START >= 0 and LENGTH >= 1, not {text!r}")
    return start, length


def _setting(text: str) -> tuple[str, Any]:
    if "=" not in text:
        raise argparse.ArgumentTypeError(f"must be KEY=VALUE, not {text!r}")
    key, raw = text.split("=", 1)
    parts = [p.strip() for p in raw.split(",")]
    vals: list[Any] = []
    for p in parts:
        try:
            vals.append(int(p))
        except ValueError:
            vals.append(p)
    return key.strip(), (tuple(vals) if len(vals) > 1 else vals[0])


def add_port_options(p: argparse.ArgumentParser, *, required: bool = True) -> None:
    """--port, --timeout and the session/access options every device command takes.

    ``required=False`` where a ``--config`` profile may give the port instead.
    """
    p.add_argument("--port", required=required, metavar="URL",
                   help="device path, pty, socket://HOST:PORT or virtual://SCENE?seed=N"
                        + (" (scan: also replay://FILE, a recorded cloud)" if not required
                           else ""))
    p.add_argument("--timeout", type=_float_in(MIN_TIMEOUT_S, 3600, "s"), default=1.0,
                   metavar="S", help=f"seconds to wait for each answer (default 1, from "
                                     f"{MIN_TIMEOUT_S:g} to 3600)")
    # Access to a shared device (protocol v2 sessions and keys, docs/protocol.md).
    p.add_argument("--take-over", action="store_true",
                   help="end another host's session on the device instead of failing busy")
    p.add_argument("--key-file", metavar="FILE",
                   help="the device's key (socket:// default: $CDMA_LIDAR_KEY_FILE)")


def connect_options(args: argparse.Namespace) -> dict[str, Any]:
    """connect() options from --timeout, --take-over and --key-file.

    A recording (``replay://FILE``) is refused here: only ``scan`` and ``view`` read one.
    """
    if args.port.lower().startswith("replay://"):
        raise ConfigError(f"--port {args.port} is a recording: scan and view replay it, "
                          f"{getattr(args, 'command', 'this command')} needs a device "
                          "(a device path, socket://HOST:PORT or virtual://SCENE)",
                          field="port")
    return {"timeout_s": args.timeout, "take_over": args.take_over, "key_file": args.key_file}


def _add_set(p: argparse.ArgumentParser) -> None:
    p.add_argument("--set", type=_setting, action="append", default=[], metavar="KEY=VALUE",
                   help="configure the device first (e.g. averages=20, peaks=4); repeatable")


def register(subparsers: Any) -> None:
    """Add the host's subcommands to the ``cdma-lidar`` parser."""
    p = subparsers.add_parser("info", help="show a device's identity, geometry and configuration")
    add_port_options(p)
    p.set_defaults(func=later("cmd_info", COMMANDS_MODULE))

    p = subparsers.add_parser("scan", help="scan a device and write a point cloud")
    p.add_argument("--config", metavar="FILE",
                   help="scan profile (TOML): any option of this command as KEY = VALUE "
                        "(port = \"virtual://paper-scene1\", frames = 4, set = "
                        "[\"averages=20\"]); options on the command line win")
    add_port_options(p, required=False)
    p.add_argument("--out", metavar="FILE",
                   help="point cloud: .ply, .pcd, .npz, .las or .mcap (ROS 2 PointCloud2: one "
                        "message per frame with --combine last, else one combined message), "
                        "by extension")
    p.add_argument("--frames", type=int, default=1, metavar="N",
                   help="frames to scan (default 1)")
    p.add_argument("--combine", choices=COMBINE_MODES, default="last",
                   help="how N frames become one cloud: last (default; the only choice for "
                        "N = 1), mean (SNR-weighted; the better one for a still scene: the "
                        "random error falls as 1/sqrt(N)), median (ignores a frame that "
                        "locked on a wrong peak)")
    p.add_argument("--keep-foreign", action="store_true",
                   help="keep other users' returns in the cloud (flag 4, their UID in "
                        "user_id) instead of only reporting them")
    p.add_argument("--calibrate-intensity", type=_reflectivity, metavar="R",
                   help="this scan sees a flat target of reflectivity R (0..1]: measure the "
                        "intensity gain and store it in the --calibration file")
    p.add_argument("--calibration", metavar="FILE", help="calibration TOML from 'calibrate'")
    p.add_argument("--near-far", action="store_true",
                   help="adjust per-pixel power between frames (needs --frames 2 or more; "
                        "one update usually settles it)")
    p.add_argument("--snr-threshold", type=_finite_float, metavar="DB",
                   help="SNR_XC threshold in dB: pixels below it are rejected (default "
                        f"{DEFAULT_SNR_THRESHOLD_DB:g}, lower where multiple-access "
                        "interference caps SNR_XC near it: docs/host.md)")
    p.add_argument("--min-support", type=int, default=1, metavar="N",
                   help="keep a pixel above the threshold only if N of its 8 neighbours are "
                        "too, at a lag within 1.5 samples (default 1; 0: the threshold alone)")
    p.add_argument("--interpolate", action="store_true",
                   help="fill runs of up to 2 rejected channels by linear interpolation "
                        "along the column (flag 1)")
    p.add_argument("--ghost-window", type=_ghost, action="append", default=[],
                   metavar="START:LEN", help="lags (samples) of a known grating ghost")
    p.add_argument("--ghost-map", metavar="FILE",
                   help="ghost windows (TOML) saved by --save-ghost-map on an empty field")
    p.add_argument("--save-ghost-map", metavar="FILE",
                   help="this scan sees an empty field: save its detections as a ghost map")
    p.add_argument("--power-cap", type=_positive_float, metavar="X",
                   help="near-far: cap per column, in units of the per-pixel maximum power "
                        "(at most the number of channels: every pixel at its maximum)")
    p.add_argument("--pictures", action="store_true",
                   help="also write SNR heatmap, depth image and 3D view PNGs beside --out")
    again = p.add_mutually_exclusive_group()
    again.add_argument("--resume", action="store_true",
                       help="finish an interrupted scan (OUT.partial.npz) without redoing "
                            "columns")
    again.add_argument("--force", action="store_true",
                       help="start afresh even though OUT.partial.npz holds an interrupted "
                            "scan (it is overwritten)")
    p.add_argument("--frame-id", type=int, metavar="N",
                   help="id of the first frame (default random); a virtual device seeds its "
                        "noise with it, so the same seed and id give the same cloud")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    _add_set(p)
    p.set_defaults(func=later("cmd_scan", COMMANDS_MODULE), profile_parser=p)
    scan = p

    # view: every scan option (--out optional) and where the live view goes
    p = subparsers.add_parser(
        "view", parents=[scan], add_help=False,
        help="scan a device and watch the cloud, range and SNR_XC images live (rerun)",
        description="Scan as `scan` does and watch each frame as it arrives: the point "
                    "cloud, the range and SNR_XC images and the power matrix, in rerun.")
    add_view_options(p)
    p.set_defaults(func=later("cmd_view", COMMANDS_MODULE), profile_parser=p)

    p = subparsers.add_parser("convert", help="convert a point cloud file to another format",
                              description="Read a cloud cdma-lidar wrote (.ply, .pcd, .npz, "
                              ".las, .mcap) and write it in the format OUT's extension names: "
                              "every frame into .mcap, the last frame into the others; an "
                              ".mcap's metadata record is kept.")
    p.add_argument("in_file", metavar="IN", help="cloud file to read")
    p.add_argument("out_file", metavar="OUT", help="cloud file to write")
    p.set_defaults(func=later("cmd_convert", COMMANDS_MODULE))

    p = subparsers.add_parser("calibrate",
                              help="measure the system delay on the zeroth-order target")
    add_port_options(p)
    p.add_argument("--target-distance", type=_float_in(*TARGET_DISTANCE_M, "m"), required=True,
                   metavar="METRES",
                   help="known distance from the grating to the calibration target (m, "
                        f"{TARGET_DISTANCE_M[0]:g} to {TARGET_DISTANCE_M[1]:g})")
    p.add_argument("--shots", type=int, default=20, metavar="N",
                   help="repeated shots (default 20)")
    p.add_argument("--out", required=True, metavar="FILE", help="calibration file (.toml)")
    p.add_argument("--snr-threshold", type=_finite_float, metavar="DB",
                   help=f"SNR_XC threshold in dB (default {DEFAULT_SNR_THRESHOLD_DB:g}, or "
                        "lower as in scan --help)")
    p.add_argument("--max-spread", type=_float_in(0, 1000, "m"), metavar="M",
                   help="widest acceptable histogram standard deviation (m)")
    _add_set(p)
    p.set_defaults(func=later("cmd_calibrate", COMMANDS_MODULE))

    p = subparsers.add_parser("capture", help="capture a correlation trace or raw ADC codes "
                                              "of one column (npz, SigMF, plot)")
    add_port_options(p)
    p.add_argument("--kind", choices=CAPTURE_KINDS, required=True,
                   help="corr: one channel's correlation over the gate; raw: the column's ADC "
                        "codes (also written as SigMF)")
    p.add_argument("--column", type=int, required=True, metavar="C", help="grating column")
    p.add_argument("--channel", type=int, default=0, metavar="K",
                   help="channel of the correlation trace (default 0)")
    p.add_argument("--out", required=True, metavar="FILE", help="capture file (.npz)")
    p.add_argument("--calibration", metavar="FILE",
                   help="calibration TOML: the trace's range axis without the system delay")
    p.add_argument("--frame-id", type=int, metavar="N", help="frame id of the scan captured")
    p.add_argument("--plot", action="store_true", help="also write FILE.png (Fig. 3d)")
    p.set_defaults(func=later("cmd_capture", "cdma_lidar.host.capture"))


def add_view_options(p: argparse.ArgumentParser) -> None:
    """``--save``, ``--web``, ``--spawn``, ``--color-by``, ``--bind`` and the viewer's ports."""
    g = p.add_argument_group("viewer (rerun; pip install 'cdma-lidar[view]')")
    g.add_argument("--save", metavar="FILE.rrd",
                   help="write the recording to an .rrd file (open it with `rerun FILE.rrd`)")
    g.add_argument("--web", action="store_true",
                   help="serve a web viewer from this process and print its URL; Ctrl-C "
                        "ends it (the default without a display)")
    g.add_argument("--spawn", action="store_true",
                   help="open rerun's native viewer (the default with a display)")
    g.add_argument("--color-by", choices=COLOR_MAPS, default="range",
                   help="colour the points by range (default), SNR_XC, intensity or ring")
    g.add_argument("--web-port", type=_port, default=WEB_PORT, metavar="PORT",
                   help=f"HTTP port of the web viewer (default {WEB_PORT})")
    g.add_argument("--grpc-port", type=_port, default=GRPC_PORT, metavar="PORT",
                   help=f"port the web viewer reads the frames from (default {GRPC_PORT})")
    g.add_argument("--steer", action="store_true",
                   help="scan frame after frame and take settings typed here, one a line: "
                        "threshold DB, averages N, cap X, near-far on|off, color FIELD, quit "
                        "(--frames N > 1: stop after N frames; else at quit or Ctrl-C)")
    g.add_argument("--bind", default=LOOPBACK, metavar="ADDRESS",
                   help=f"address the served ports listen on (default {LOOPBACK}: this "
                        "machine only; 0.0.0.0 serves every interface, unauthenticated)")


def _port(text: str) -> int:
    try:
        v = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"must be a port number, not {text!r}") from None
    if not 1 <= v <= 65535:
        raise argparse.ArgumentTypeError(f"must be from 1 to 65535, not {text!r}")
    return v
