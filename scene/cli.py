"""``cdma-lidar scene ...``: the built-in scenes and their ground truth.

    cdma-lidar scene list [--markdown]                  the built-in presets (docs/scene.md's table)
    cdma-lidar scene show SCENE                         instrument and objects, lit pixels
    cdma-lidar scene truth SCENE --out truth.npz        per-pixel ground truth (NPZ)

This module holds the options and ``scene list``, which reads the preset files
(:mod:`cdma_lidar.scene.presetfiles`) and so needs no numpy; the other commands (and
``list --markdown``, which loads every scene for its pixel counts) are in
:mod:`cdma_lidar.scene.commands`, imported when they run.
"""

from __future__ import annotations

import argparse
import sys

from cdma_lidar.lazy import later
from cdma_lidar.scene.presetfiles import preset_description, preset_names

__all__ = ["register"]

#: The module that does the commands' work.
COMMANDS_MODULE = "cdma_lidar.scene.commands"


def register(subparsers: argparse._SubParsersAction) -> None:
    """Add the ``scene`` command."""
    sc = subparsers.add_parser("scene", help="built-in scenes and their ground truth")
    sub = sc.add_subparsers(dest="scene_command", metavar="SUBCOMMAND")
    sub.required = True

    p = sub.add_parser("list", help="list the built-in scenes")
    p.add_argument("--markdown", action="store_true",
                   help="a Markdown table of name, description and pixels (docs/scene.md's)")
    p.set_defaults(func=_cmd_list)

    p = sub.add_parser("show", help="describe a scene: instrument, objects, lit pixels")
    p.add_argument("scene", help="preset name (e.g. paper-scene1, flat-wall?distance=7.5) or .toml")
    p.set_defaults(func=later("cmd_show", COMMANDS_MODULE))

    p = sub.add_parser("truth", help="write per-pixel ground truth (range, point, ...) as NPZ")
    p.add_argument("scene", help="preset name or .toml file")
    p.add_argument("--out", required=True, help="output .npz file")
    p.add_argument("--seed", type=int, default=0,
                   help="noise seed (the speckle pattern, when the scene has speckle)")
    p.set_defaults(func=later("cmd_truth", COMMANDS_MODULE))


def _cmd_list(args: argparse.Namespace) -> int:
    """``scene list``: name and description of each preset, read from its file."""
    if args.markdown:
        return later("cmd_markdown", COMMANDS_MODULE)(args)
    for name in preset_names():
        sys.stdout.write(f"{name:14s} {preset_description(name)}\n")
    return 0
