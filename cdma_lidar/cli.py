"""The ``cdma-lidar`` command: the top of the stack, composing every layer's commands.

Each package that has commands provides ``<package>.cli.register(subparsers)``,
which adds its subcommands and sets ``func`` to a callable ``(args) -> int`` (a
:func:`cdma_lidar.lazy.later`, whose module is imported when the command runs);
:data:`COMMANDS` names, in help order, each command, the module that registers it and
its one-line help. Only the module of the command being run is imported, so
``cdma-lidar --help`` and every command start without loading the others (numpy,
scipy, matplotlib and the study catalogue cost seconds). ``tests/test_cli_startup.py``
checks that the table says what each module registers. Importing
:mod:`cdma_lidar.virtual` (a few lines) registers the ``virtual://`` URL scheme, so
every ``--port`` accepts it.

Error contract (users and tests rely on it): a bad argument, file, port or
configuration exits with status 2 and exactly one line on stderr that names
what is wrong and what is allowed. Ctrl-C exits with 130.
"""

from __future__ import annotations

import argparse
import importlib
import logging
import sys
from collections.abc import Sequence
from typing import NamedTuple

import cdma_lidar.virtual  # noqa: F401  (importing it registers the virtual:// URL scheme)
from cdma_lidar.errors import CdmaLidarError
from cdma_lidar.lazy import later
from cdma_lidar.version import __version__

__all__ = ["COMMANDS", "build_parser", "main", "register"]

log = logging.getLogger("cdma_lidar.cli")


class Command(NamedTuple):
    """A top-level command: its name, the module whose ``register`` adds it, its help."""

    name: str
    module: str
    help: str


#: Every top-level command in help order. The module is imported only when its
#: command runs (or the full parser is built); the help is what ``--help`` lists.
COMMANDS: tuple[Command, ...] = (
    Command("codes", "cdma_lidar.firmware_model.cli",
            "m-sequences, Gold codes, preferred pairs, UIDs"),
    Command("scene", "cdma_lidar.scene.cli", "built-in scenes and their ground truth"),
    Command("device", "cdma_lidar.virtual.cli",
            "serve the virtual device (a simulated instrument) on a pty or TCP port"),
    Command("info", "cdma_lidar.host.cli", "show a device's identity, geometry and configuration"),
    Command("scan", "cdma_lidar.host.cli", "scan a device and write a point cloud"),
    Command("view", "cdma_lidar.host.cli",
            "scan a device and watch the cloud, range and SNR_XC images live (rerun)"),
    Command("convert", "cdma_lidar.host.cli", "convert a point cloud file to another format"),
    Command("calibrate", "cdma_lidar.host.cli",
            "measure the system delay on the zeroth-order target"),
    Command("capture", "cdma_lidar.host.cli",
            "capture a correlation trace or raw ADC codes of one column (npz, SigMF, plot)"),
    Command("study", "cdma_lidar.study.cli",
            "sweeps of the speed/accuracy trade (docs/studies.md)"),
    Command("demo", "cdma_lidar.cli",
            "calibrate and scan paper-scene1 on the virtual device, with pictures"),
    Command("hdl", "cdma_lidar.hdl_ref.cli", "reference RTL: test vectors"),
)


#: The module that does ``demo``'s work (:func:`register` adds its options).
DEMO_MODULE = "cdma_lidar.demo"


class _OneLineParser(argparse.ArgumentParser):
    """argparse that reports a usage error as one line and exit status 2."""

    def error(self, message: str) -> None:  # type: ignore[override]
        self.exit(2, f"{self.prog}: error: {message}\n")


def _chosen(argv: Sequence[str]) -> str | None:
    """The command word of ``argv`` (its first argument not starting with '-'), if any."""
    return next((a for a in argv if not a.startswith("-")), None)


def build_parser(only: str | None = None) -> argparse.ArgumentParser:
    """The ``cdma-lidar`` parser.

    ``only``: register just the module of this command (the others are listed with
    their help and no options); None registers every module.
    """
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
    modules = {c.module for c in COMMANDS if only is None or c.name == only}
    for module in dict.fromkeys(c.module for c in COMMANDS if c.module in modules):
        importlib.import_module(module).register(sub)
    for command in COMMANDS:
        if command.module not in modules:
            sub.add_parser(command.name, help=command.help, add_help=False)
    return parser


def register(subparsers: argparse._SubParsersAction) -> None:
    """Add ``demo`` (its work, :func:`cdma_lidar.demo.cmd_demo`, imported when it runs)."""
    p = subparsers.add_parser(
        "demo", help="calibrate and scan paper-scene1 on the virtual device, with pictures")
    p.add_argument("--out", default="cdma-lidar-demo", metavar="DIR",
                   help="folder for the results (default ./cdma-lidar-demo)")
    p.add_argument("--seed", type=int, default=1, help="noise seed of the virtual device")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.set_defaults(func=later("cmd_demo", DEMO_MODULE))


def main(argv: Sequence[str] | None = None) -> int:
    """Run the CLI; returns the process exit status."""
    argv = list(sys.argv[1:] if argv is None else argv)
    word = _chosen(argv)
    known = {c.name for c in COMMANDS}
    parser = build_parser(only=word if word in known else "")
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
