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

This module holds only the options (no numpy), so ``device --help`` starts as fast as
Python; the work is in :mod:`cdma_lidar.virtual.commands`, imported when it runs.
"""

from __future__ import annotations

import argparse

from cdma_lidar.lazy import later
from cdma_lidar.paths import default_key_file

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
    dev.add_argument("--key-file", metavar="FILE", nargs="?", const=str(default_key_file()),
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
    dev.set_defaults(func=later("cmd_device", "cdma_lidar.virtual.commands"))
