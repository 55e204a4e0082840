"""Commands whose work is imported only when they run: what keeps ``--help`` fast.

Each layer's ``cli`` module builds its part of the ``cdma-lidar`` parser from the
standard library alone and sets every command's ``func`` to :func:`later`, naming the
sibling module that does the work (and imports numpy, scipy and the rest). So
``cdma-lidar COMMAND --help`` costs what Python's start costs, and a command loads only
what it uses (``tests/cdma_lidar/test_cli_startup.py`` checks it).
"""

from __future__ import annotations

import argparse
import importlib
from collections.abc import Callable

__all__ = ["later"]


def later(name: str, module: str) -> Callable[[argparse.Namespace], int]:
    """The command ``module.name(args)``, its module imported only when the command runs."""
    def run(args: argparse.Namespace) -> int:
        return int(getattr(importlib.import_module(module), name)(args))
    run.__name__ = name
    return run
