"""Ground truth of a scene: per pixel (channel, column) what the beam really hits.

The rays use the instrument's TRUE grating parameters (the host only knows the nominal
ones), so the truth is what a perfect host would measure. ``save_truth`` writes an NPZ:

    range_m        (K, C) float64  distance grating -> hit (m), NaN where nothing is hit
    point_m        (K, C, 3)       hit point in the sensor/global frame (x fwd, y left, z up), NaN
    reflectivity   (K, C) float64  NaN where nothing is hit
    object_id      (K, C) int64    index into the scene's objects, -1 where nothing is hit
    cos_incidence  (K, C) float64  0 where nothing is hit
    wavelengths_m  (K,), rotations_deg (C,), directions (K, C, 3)
    object_names   (n_objects,) str
    scene          the scene's name

and, when the caller passes the link budget (``cdma-lidar scene truth`` does, from
:meth:`cdma_lidar.scene.instrument.Instrument.link_figures`), per pixel (K, C):

    rx_power_w, amplitude_v, signal_power_v2, noise_power_v2    the link budget
    snr_db (eq. 30), snr_ss_db (eq. 43), snr_ss_avg_db, footprint_m
"""

from __future__ import annotations

import io
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from cdma_lidar.fileio import atomic_write_bytes, check_writable
from cdma_lidar.scene.model import Scene
from cdma_lidar.scene.raycast import Hits, cast

__all__ = ["Truth", "compute_truth", "save_truth"]


@dataclass(frozen=True)
class Truth:
    """Ray directions (true geometry) and their nearest hits for every pixel of a frame."""

    directions: NDArray[np.float64]
    hits: Hits

    @property
    def range_m(self) -> NDArray[np.float64]:
        """(K, C) true range (m), NaN where nothing is hit."""
        return self.hits.range_m


def compute_truth(scene: Scene) -> Truth:
    """Cast every pixel's ray (true geometry) into the scene."""
    inst = scene.instrument
    dirs = inst.geometry().directions(inst.wavelengths_m[:, None], inst.rotations_deg[None, :])
    return Truth(directions=dirs, hits=cast(scene, dirs))


def save_truth(scene: Scene, path: str | Path,
               extra: dict[str, NDArray] | None = None) -> Truth:
    """Compute the truth and write it atomically to ``path`` (.npz), with ``extra`` arrays."""
    out = check_writable(path)
    truth = compute_truth(scene)
    h = truth.hits
    buf = io.BytesIO()
    np.savez_compressed(
        buf, range_m=h.range_m, point_m=h.point_m, reflectivity=h.reflectivity,
        object_id=h.object_id, cos_incidence=h.cos_incidence,
        wavelengths_m=scene.instrument.wavelengths_m, rotations_deg=scene.instrument.rotations_deg,
        directions=truth.directions,
        object_names=np.array([o.name for o in scene.objects], dtype=str),
        scene=np.array(scene.name), **(extra or {}))
    atomic_write_bytes(out, buf.getvalue())
    return truth
