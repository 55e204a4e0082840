"""Where the toolkit keeps files of its own outside any working tree."""

from __future__ import annotations

import os
from pathlib import Path

__all__ = ["default_key_file"]


def default_key_file() -> Path:
    """Where a device key belongs: outside any working tree, in
    ``$XDG_CONFIG_HOME/cdma-lidar/device.key`` (default ``~/.config/cdma-lidar/device.key``).

    The device (``cdma-lidar virtual --key-file``) writes it there and a host reaching
    ``socket://`` without ``--key-file`` or $CDMA_LIDAR_KEY_FILE reads it from there when
    it exists, so the README's commands leave no secret in the repository.
    """
    base = os.environ.get("XDG_CONFIG_HOME") or os.path.join(os.path.expanduser("~"),
                                                              ".config")
    return Path(base) / "cdma-lidar" / "device.key"
