"""The simulated world behind the virtual device: scenes, rays, optics, noise, other users.

``load_scene(name_or_path)`` gives a validated :class:`cdma_lidar.scene.model.Scene`
(:mod:`cdma_lidar.scene.scenefile` reads the TOML, :mod:`cdma_lidar.scene.loader` finds
presets and files); ``cdma_lidar.scene.instrument.Instrument(scene, seed)`` renders its ADC
samples and repetition sums (its parts: ``codebook``, ``echoes``, ``noise``, ``sums``,
``plans``); :func:`cdma_lidar.scene.acquire.acquire` renders and receives a batch of
columns, the one acquisition path of the virtual device and every study.
"""

from cdma_lidar.scene.loader import PRESETS, load_scene
from cdma_lidar.scene.model import Scene

__all__ = ["PRESETS", "Scene", "load_scene"]
