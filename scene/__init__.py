"""The simulated world behind the virtual device: scenes, rays, optics, noise, other users.

``load_scene(name_or_path)`` gives a validated :class:`cdma_lidar.scene.model.Scene`
(:mod:`cdma_lidar.scene.scenefile` reads the TOML, :mod:`cdma_lidar.scene.loader` finds
presets and files); ``cdma_lidar.scene.instrument.Instrument(scene, seed)`` renders its ADC
samples and repetition sums (its parts: ``codebook``, ``echoes``, ``noise``, ``sums``,
``plans``); :func:`cdma_lidar.scene.acquire.acquire` renders and receives a batch of
columns, the one acquisition path of the virtual device and every study.

``PRESETS``, ``load_scene`` and ``Scene`` are loaded from their modules on first use (PEP
562), so importing a light module of this package (``cli``, ``presetfiles``) loads no
numpy: ``cdma-lidar scene list`` and ``scene --help`` start as fast as Python does.
"""

import importlib
from typing import Any

__all__ = ["PRESETS", "Scene", "load_scene"]


def __getattr__(name: str) -> Any:
    if name in ("PRESETS", "load_scene"):
        return getattr(importlib.import_module("cdma_lidar.scene.loader"), name)
    if name == "Scene":
        return importlib.import_module("cdma_lidar.scene.model").Scene
    raise AttributeError(f"module 'cdma_lidar.scene' has no attribute {name!r}")
