"""The work of ``cdma-lidar device`` (its options: :mod:`cdma_lidar.virtual.cli`).

Imported when the command runs: the scene, the protocol's keys and the server.
"""

from __future__ import annotations

import argparse
import ipaddress
import socket
import sys
from pathlib import Path

from cdma_lidar.errors import ConfigError, out_of_range
from cdma_lidar.paths import default_key_file
from cdma_lidar.protocol.auth import load_or_create_key
from cdma_lidar.scene import load_scene
from cdma_lidar.virtual.serve import serve_pty, serve_tcp

__all__ = ["cmd_device"]


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


def _make_private_folder(folder: Path) -> None:
    try:
        folder.mkdir(mode=0o700, parents=True, exist_ok=True)
    except OSError as exc:
        raise ConfigError(f"cannot create {str(folder)!r} for the key file ({exc.strerror}); "
                          "give --key-file FILE", "--key-file") from None


def cmd_device(args: argparse.Namespace) -> int:
    """``device``: serve the virtual device on a pty or a TCP port until interrupted."""
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
    _check_free(args.tcp, host, port)  # and a taken port: one line, no warning before it
    key = None
    if args.key_file and args.insecure:
        raise ConfigError("--key-file and --insecure exclude each other", "--insecure")
    if args.key_file:
        if args.key_file == str(default_key_file()):
            _make_private_folder(default_key_file().parent)
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


def _check_free(text: str, host: str, port: int) -> None:
    """ConfigError unless ``port`` can be listened on at ``host`` (checked, then closed)."""
    try:
        infos = socket.getaddrinfo(host, port, type=socket.SOCK_STREAM)
    except OSError:
        return  # an unresolvable host: serve_tcp says so
    family, _, _, _, addr = infos[0]
    with socket.socket(family, socket.SOCK_STREAM) as s:
        s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)  # as servers do: a port
        try:                                                      # in TIME_WAIT is free
            s.bind(addr)
        except OSError as exc:
            raise ConfigError(f"--tcp {text}: cannot listen ({exc.strerror}): another device "
                              "or program listens there; choose another port",
                              "--tcp") from None


def _announce(text: str) -> None:
    sys.stdout.write(text + "\n")
    sys.stdout.flush()
