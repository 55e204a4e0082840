"""The built-in scenes as files: ``scene/presets/*.toml``, their names and descriptions.

Reads the files with the standard library alone (no numpy, no scene model), so
``cdma-lidar scene list`` and the help of every command that takes a scene start as fast
as Python does. :mod:`cdma_lidar.scene.loader` finds the presets here too: adding a
preset is adding a file, and this folder is the one list of them.
"""

from __future__ import annotations

import tomllib
from importlib import resources
from importlib.abc import Traversable

__all__ = ["preset_description", "preset_file", "preset_names"]


def _presets_folder() -> Traversable:
    return resources.files("cdma_lidar.scene").joinpath("presets")


def preset_names() -> tuple[str, ...]:
    """Names of the built-in scenes: the ``*.toml`` files of ``scene/presets``, sorted."""
    return tuple(sorted(p.name.removesuffix(".toml") for p in _presets_folder().iterdir()
                        if p.is_file() and p.name.endswith(".toml")))


def preset_file(name: str) -> Traversable:
    """The TOML file of the preset ``name`` (one of :func:`preset_names`)."""
    return _presets_folder().joinpath(f"{name}.toml")


def preset_description(name: str) -> str:
    """The ``description`` of the preset ``name``: what ``load_scene(name).description`` says.

    Read from the file's top-level ``description`` key without validating the scene
    (``tests/scene/test_cli.py`` checks it agrees with the loaded scene for every preset).
    """
    return str(tomllib.loads(preset_file(name).read_text("utf-8")).get("description", ""))
