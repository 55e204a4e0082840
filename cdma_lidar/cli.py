"""The ``cdma-lidar`` command: the top of the stack, composing every layer's commands.

Each package that has commands provides ``<package>.cli.register(subparsers)``,
which adds its subcommands and sets ``func`` to a callable ``(args) -> int``;
:data:`COMMAND_MODULES` lists them in help order. Importing
:mod:`cdma_lidar.virtual` (through its ``cli``) registers the ``virtual://`` URL
scheme, so every ``--port`` accepts it.

Error contract (users and tests rely on it): a bad argument, file, port or
configuration exits with status 2 and exactly one line on stderr that names
what is wrong and what is allowed. Ctrl-C exits with 130.
"""

from __future__ import annotations

import argparse
import logging
import sys
from collections.abc import Sequence
from types import ModuleType

from cdma_lidar import __version__, demo
from cdma_lidar.errors import CdmaLidarError
from cdma_lidar.firmware_model import cli as codes_cli
from cdma_lidar.hdl_ref import vectors as hdl_cli
from cdma_lidar.host import capture as capture_cli
from cdma_lidar.host import cli as host_cli
from cdma_lidar.scene import cli as scene_cli
from cdma_lidar.study import cli as study_cli
from cdma_lidar.virtual import cli as device_cli

__all__ = ["build_parser", "main"]

log = logging.getLogger("cdma_lidar.cli")

#: Modules that contribute subcommands, in help order: codes; scene; device; info, scan,
#: calibrate; capture; study; demo; hdl.
COMMAND_MODULES: tuple[ModuleType, ...] = (codes_cli, scene_cli, device_cli, host_cli, capture_cli,
                                          study_cli, demo, hdl_cli)


class _OneLineParser(argparse.ArgumentParser):
    """argparse that reports a usage error as one line and exit status 2."""

    def error(self, message: str) -> None:  # type: ignore[override]
        self.exit(2, f"{self.prog}: error: {message}\n")


def build_parser() -> argparse.ArgumentParser:
    """The full parser with every package's subcommands registered."""
    parser = _OneLineParser(
        prog="cdma-lidar",
        description="Identity-enabled CDMA LiDAR toolkit: codes, virtual device, scans.",
    )
    parser.add_argument("--version", action="version", version=f"cdma-lidar {__version__}")
    parser.add_argument(
        "-v", "--verbose", action="count", default=0, help="more log output (-vv for debug)"
    )
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", parser_class=_OneLineParser)
    sub.required = True
    for module in COMMAND_MODULES:
        module.register(sub)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Run the CLI; returns the process exit status."""
    parser = build_parser()
    args = parser.parse_args(argv)
    level = [logging.WARNING, logging.INFO, logging.DEBUG][min(args.verbose, 2)]
    logging.basicConfig(level=level, format="%(levelname)s %(name)s: %(message)s")
    try:
        return int(args.func(args) or 0)
    except CdmaLidarError as exc:
        sys.stderr.write(f"cdma-lidar {args.command}: error: {exc}\n")
        return 2
    except KeyboardInterrupt:
        sys.stderr.write(f"cdma-lidar {args.command}: interrupted\n")
        return 130
    except BrokenPipeError:  # e.g. `cdma-lidar codes gold ... | head`
        return 0


if __name__ == "__main__":  # pragma: no cover
    raise SystemExit(main())
