"""cdma-lidar: shared plumbing for the toolkit (errors, CLI entry point, atomic files).

The product packages are ``firmware_model``, ``protocol``, ``host``, ``scene`` and
``hdl_ref``; this small package holds what all of them share, so none of them has
to import another just for an exception class.

The Python quick start, ``cdma_lidar.open(URL)``, ``.calibrate(...)``, ``.scan(...)``
and ``.run_study(...)``, lives in :mod:`cdma_lidar.api` at the top of the layers;
its names are loaded from there on first use (PEP 562), so ``import cdma_lidar`` loads
nothing else and the core never imports an upper layer at import time. ``__version__``
lives in :mod:`cdma_lidar.version` (what the layers import; a constant, re-exported here).
"""

import importlib
from typing import Any

from cdma_lidar.version import __version__

#: Names of :mod:`cdma_lidar.api` that ``cdma_lidar.NAME`` loads on first use.
API_NAMES = ("calibrate", "open", "run_study", "scan")

# `open` stays out of __all__: `from cdma_lidar import *` must not shadow the built-in.
__all__ = ["API_NAMES", "__version__", "calibrate", "run_study", "scan"]


def __getattr__(name: str) -> Any:
    if name in API_NAMES:
        return getattr(importlib.import_module("cdma_lidar.api"), name)
    raise AttributeError(f"module 'cdma_lidar' has no attribute {name!r}")
