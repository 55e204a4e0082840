"""``cdma-lidar device ...``: serve the virtual device on a pty or a TCP port.

    cdma-lidar device --scene SCENE --pty [--key-file FILE]   serve the virtual device on a
                                                        pty (FEC when asked; keyed with a file)
    cdma-lidar device --scene SCENE --tcp HOST:PORT --key-file [FILE]
                                                        ... or on a TCP socket (socket://),
                                                        hosts must hold the key in FILE
    cdma-lidar device --scene SCENE --tcp 127.0.0.1:PORT --insecure
                                                        ... loopback only, no access control

The key file is created (a fresh random key, mode 0600) if it does not exist; give the
same file to the host (``--key-file FILE`` or ``CDMA_LIDAR_KEY_FILE``).

In-process use needs no command: ``virtual://SCENE?seed=N`` works in any ``--port``.
"""

from __future__ import annotations

import argparse
import ipaddress
import os
import socket
import sys
from pathlib import Path

from cdma_lidar.errors import ConfigError, out_of_range
from cdma_lidar.protocol.auth import load_or_create_key
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
    dev.add_argument("--key-file", metavar="FILE", nargs="?", const=str(_default_key_file()),
                     help="TCP: hosts must prove they hold the key in FILE (created, mode "
                     "0600, with a fresh random key if absent); every frame is signed; "
                     "without FILE: ~/.config/cdma-lidar/device.key, outside any working "
                     "tree, where hosts on this machine find it")
    dev.add_argument("--insecure", action="store_true",
                     help="TCP without a key: anyone who can connect controls the device, "
                     "so only a loopback address is allowed")
    dev.add_argument("--session-idle", type=float, default=10.0, metavar="S",
                     help="seconds after which an idle host's session may be taken by "
                     "another host without --take-over (default 10)")
    dev.set_defaults(func=_cmd_device)


def _parse_hostport(text: str) -> tuple[str, int]:
    host, sep, port = text.rpartition(":")
    if not sep or not port.isdigit() or not 0 <= int(port) <= 65535:
        raise out_of_range("--tcp", "HOST:PORT with a port from 0 to 65535", text)
    if host.startswith("[") and host.endswith("]"):  # an IPv6 literal: [::1]:7700
        host = host[1:-1]
    return host or "127.0.0.1", int(port)


def _is_loopback(host: str) -> bool:
    try:
        return all(ipaddress.ip_address(info[4][0]).is_loopback
                   for info in socket.getaddrinfo(host, None))
    except (OSError, ValueError):
        return False


def _default_key_file() -> Path:
    """``$XDG_CONFIG_HOME/cdma-lidar/device.key`` (``~/.config/...``): the same path as
    :func:`cdma_lidar.host.connection.default_key_file`, which this layer cannot import
    (a test keeps the two equal)."""
    base = os.environ.get("XDG_CONFIG_HOME") or os.path.join(os.path.expanduser("~"),
                                                              ".config")
    return Path(base) / "cdma-lidar" / "device.key"


def _make_private_folder(folder: Path) -> None:
    try:
        folder.mkdir(mode=0o700, parents=True, exist_ok=True)
    except OSError as exc:
        raise ConfigError(f"cannot create {str(folder)!r} for the key file ({exc.strerror}); "
                          "give --key-file FILE", "--key-file") from None


def _cmd_device(args: argparse.Namespace) -> int:
    if args.seed < 0:
        raise out_of_range("--seed", "a non-negative integer", args.seed)
    if not 0.001 <= args.session_idle <= 4_294_967:
        raise out_of_range("--session-idle", "0.001 to 4294967 seconds", args.session_idle)
    if args.pty:
        if args.insecure:
            raise ConfigError("--insecure applies to --tcp only (a pty is reachable only by "
                              "local users who may open it)", "--insecure")
        scene = load_scene(args.scene)
        key = load_or_create_key(args.key_file)[0] if args.key_file else None
        return serve_pty(scene, args.seed, announce=_announce, key=key,
                         session_idle_s=args.session_idle)
    host, port = _parse_hostport(args.tcp)
    scene = load_scene(args.scene)  # a bad scene is refused before a key or a warning
    key = None
    if args.key_file and args.insecure:
        raise ConfigError("--key-file and --insecure exclude each other", "--insecure")
    if args.key_file:
        if args.key_file == str(_default_key_file()):
            _make_private_folder(_default_key_file().parent)
        key, created = load_or_create_key(args.key_file)
        if created:
            sys.stderr.write(f"cdma-lidar device: created key file {args.key_file} (mode "
                             "0600); give it to the host with --key-file\n")
    elif not args.insecure:
        raise ConfigError("--tcp needs --key-file [FILE] (hosts must prove they hold the "
                          "key; without FILE it is ~/.config/cdma-lidar/device.key, outside "
                          "the working tree); "
                          "--insecure serves without access control on a loopback address "
                          "only", "--key-file")
    elif not _is_loopback(host):
        raise out_of_range("--tcp", "a loopback address (127.0.0.1, ::1, localhost) with "
                           "--insecure", host)
    else:
        sys.stderr.write(f"cdma-lidar device: INSECURE: no access control on {host}:{port}; "
                         "any local process can control the device\n")
    try:
        return serve_tcp(scene, args.seed, host, port, announce=_announce, key=key,
                         session_idle_s=args.session_idle)
    except OSError as exc:
        raise ConfigError(f"--tcp {args.tcp}: cannot listen ({exc.strerror})", "--tcp") from exc


def _announce(text: str) -> None:
    sys.stdout.write(text + "\n")
    sys.stdout.flush()
