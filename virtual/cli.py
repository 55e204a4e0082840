"""``cdma-lidar device ...``: serve the virtual device on a pty or a TCP port.

    cdma-lidar device --scene SCENE --pty               serve the virtual device on a pty
    cdma-lidar device --scene SCENE --tcp HOST:PORT     ... or on a TCP socket (socket://)

In-process use needs no command: ``virtual://SCENE?seed=N`` works in any ``--port``.
"""

from __future__ import annotations

import argparse
import sys

from cdma_lidar.errors import ConfigError, out_of_range
from cdma_lidar.scene import load_scene
from cdma_lidar.virtual.serve import serve_pty, serve_tcp

__all__ = ["register"]


def register(subparsers: argparse._SubParsersAction) -> None:
    """Add the ``device`` command."""
    dev = subparsers.add_parser(
        "device", help="serve the virtual device (a simulated instrument) on a pty or TCP port")
    dev.add_argument("--scene", default="paper-scene1", help="preset name or .toml file")
    dev.add_argument("--seed", type=int, default=0, help="noise seed (default 0)")
    where = dev.add_mutually_exclusive_group(required=True)
    where.add_argument("--pty", action="store_true", help="create a pty and print its path")
    where.add_argument("--tcp", metavar="HOST:PORT", help="listen on a TCP socket")
    dev.set_defaults(func=_cmd_device)


def _parse_hostport(text: str) -> tuple[str, int]:
    host, sep, port = text.rpartition(":")
    if not sep or not port.isdigit() or not 0 <= int(port) <= 65535:
        raise out_of_range("--tcp", "HOST:PORT with a port from 0 to 65535", text)
    return host or "127.0.0.1", int(port)


def _cmd_device(args: argparse.Namespace) -> int:
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
