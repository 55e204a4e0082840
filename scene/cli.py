"""``cdma-lidar scene ...`` and ``cdma-lidar device ...``: scenes, their truth, the virtual device.

    cdma-lidar scene list                               the built-in presets
    cdma-lidar scene show SCENE                         instrument and objects, lit pixels
    cdma-lidar scene truth SCENE --out truth.npz        per-pixel ground truth (NPZ)
    cdma-lidar device --scene SCENE --pty               serve the virtual device on a pty
    cdma-lidar device --scene SCENE --tcp HOST:PORT     ... or on a TCP socket (socket://)
"""

from __future__ import annotations

import argparse
import logging
import sys

from cdma_lidar.errors import ConfigError, out_of_range
from cdma_lidar.fileio import check_writable

__all__ = ["register"]

log = logging.getLogger(__name__)


def register(subparsers: argparse._SubParsersAction) -> None:
    """Add the ``scene`` and ``device`` commands."""
    sc = subparsers.add_parser("scene", help="built-in scenes and their ground truth")
    sub = sc.add_subparsers(dest="scene_command", metavar="SUBCOMMAND")
    sub.required = True

    p = sub.add_parser("list", help="list the built-in scenes")
    p.set_defaults(func=_cmd_list)

    p = sub.add_parser("show", help="describe a scene: instrument, objects, lit pixels")
    p.add_argument("scene", help="preset name (e.g. paper-scene1, flat-wall?distance=7.5) or .toml")
    p.set_defaults(func=_cmd_show)

    p = sub.add_parser("truth", help="write per-pixel ground truth (range, point, ...) as NPZ")
    p.add_argument("scene", help="preset name or .toml file")
    p.add_argument("--out", required=True, help="output .npz file")
    p.set_defaults(func=_cmd_truth)

    dev = subparsers.add_parser(
        "device", help="serve the virtual device (a simulated instrument) on a pty or TCP port")
    dev.add_argument("--scene", default="paper-scene1", help="preset name or .toml file")
    dev.add_argument("--seed", type=int, default=0, help="noise seed (default 0)")
    where = dev.add_mutually_exclusive_group(required=True)
    where.add_argument("--pty", action="store_true", help="create a pty and print its path")
    where.add_argument("--tcp", metavar="HOST:PORT", help="listen on a TCP socket")
    dev.set_defaults(func=_cmd_device)


def _cmd_list(args: argparse.Namespace) -> int:
    from cdma_lidar.scene.model import PRESETS, load_scene

    for name in PRESETS:
        sys.stdout.write(f"{name:14s} {load_scene(name).description}\n")
    return 0


def _cmd_show(args: argparse.Namespace) -> int:
    from cdma_lidar.scene.instrument import Instrument
    from cdma_lidar.scene.model import load_scene

    scene = load_scene(args.scene)
    inst = Instrument(scene, 0)
    spec = scene.instrument
    h = inst.truth.hits
    lines = [
        f"scene {scene.name}: {scene.description}",
        f"  pixels {spec.channels} x {spec.columns}, lit {int(h.lit.sum())}, "
        f"channels lit somewhere {int(h.lit.any(axis=1).sum())}",
        f"  wavelengths {spec.wavelengths_m[0] * 1e9:.3f}..{spec.wavelengths_m[-1] * 1e9:.3f} nm, "
        f"rotations {spec.rotations_deg.min():.3f}..{spec.rotations_deg.max():.3f} deg",
        f"  code degree {spec.code_degree}, {spec.chip_rate_hz / 1e6:g} Mchip/s, "
        f"S={spec.samples_per_chip}, R={spec.averages}, uid {spec.uid}/{spec.uid_bits} bits",
        f"  noise rms {inst.noise_rms_v * 1e3:.3f} mV, default gate {inst.default_gate()}",
        f"  calibration target (zeroth order) at {scene.calibration.target_distance_m:g} m: "
        f"calibrate with --target-distance {scene.calibration.target_distance_m:g}",
    ]
    for i, obj in enumerate(scene.objects):
        sel = h.object_id == i
        rng = h.range_m[sel]
        span = f"{rng.min():.3f}..{rng.max():.3f} m" if rng.size else "not seen"
        lines.append(f"  objects[{i}] {obj.kind:6s} {obj.name:14s} pixels {int(sel.sum()):5d} "
                     f"range {span}")
    sys.stdout.write("\n".join(lines) + "\n")
    return 0


def _cmd_truth(args: argparse.Namespace) -> int:
    from cdma_lidar.scene.model import load_scene
    from cdma_lidar.scene.truth import save_truth

    if not str(args.out).lower().endswith(".npz"):
        raise ConfigError(f"--out must be a .npz file, not {args.out!r}", "out")
    check_writable(args.out, "--out")
    scene = load_scene(args.scene)
    try:
        truth = save_truth(scene, args.out)
    except OSError as exc:  # the folder changed under us after the check
        raise ConfigError(f"--out {args.out!r}: cannot write it ({exc.strerror}); choose a "
                          "writable folder", "out") from None
    lit = truth.hits.lit
    rng = truth.range_m[lit]
    summary = f"{rng.min():.3f}..{rng.max():.3f} m" if rng.size else "no hits"
    sys.stdout.write(f"{args.out}: {lit.shape[0]} x {lit.shape[1]} pixels, "
                     f"{int(lit.sum())} hit ({summary})\n")
    return 0


def _parse_hostport(text: str) -> tuple[str, int]:
    host, sep, port = text.rpartition(":")
    if not sep or not port.isdigit() or not 0 <= int(port) <= 65535:
        raise out_of_range("--tcp", "HOST:PORT with a port from 0 to 65535", text)
    return host or "127.0.0.1", int(port)


def _cmd_device(args: argparse.Namespace) -> int:
    from cdma_lidar.scene.model import load_scene
    from cdma_lidar.virtual.serve import serve_pty, serve_tcp

    if args.seed < 0:
        raise out_of_range("--seed", "a non-negative integer", args.seed)
    scene = load_scene(args.scene)
    if args.pty:
        return serve_pty(scene, args.seed, announce=_announce)
    host, port = _parse_hostport(args.tcp)
    try:
        return serve_tcp(scene, args.seed, host, port, announce=_announce)
    except OSError as exc:
        raise ConfigError(f"--tcp {args.tcp}: cannot listen ({exc.strerror})", "--tcp") from exc


def _announce(text: str) -> None:
    sys.stdout.write(text + "\n")
    sys.stdout.flush()

