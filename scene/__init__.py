"""The simulated world behind the virtual device: scenes, rays, optics, noise, other users.

``load_scene(name_or_path)`` gives a validated :class:`cdma_lidar.scene.model.Scene`;
``cdma_lidar.scene.instrument.Instrument(scene, seed)`` renders its ADC samples column by column.
"""

from cdma_lidar.scene.model import PRESETS, Scene, load_scene

__all__ = ["PRESETS", "Scene", "load_scene"]
