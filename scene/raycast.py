"""Ray casting: where each pixel's beam first meets an object.

Rays start at the grating (the origin of the sensor frame) along unit directions from
:meth:`cdma_lidar.optics.grating.GratingGeometry.directions`. Every object kind returns, per
ray, the distance ``t`` (m) to its first hit in front of the origin (``inf`` if none) and the
cosine of the incidence angle (between the ray and the surface normal, in [0, 1], used for
Lambertian reflection). The nearest object wins.

Extruded text is modelled by its front face only: the glyph outlines (matplotlib's
``TextPath``, even-odd filled, so counters such as the hole in "A" stay empty) are tested
at the ray's intersection with the front plane. The extrusion's sides would only be seen
by rays at grazing angles to the face, which the scenes here do not have.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from cdma_lidar.scene.model import ObjectSpec, Scene

__all__ = ["Hits", "cast", "glyph_polygons", "intersect"]


@dataclass(frozen=True)
class Hits:
    """Nearest hit per ray; arrays have the rays' leading shape (e.g. (K, C)).

    range_m: distance from the grating (m), NaN where nothing is hit.
    point_m: hit point (m) in the sensor frame, NaN where nothing is hit.
    cos_incidence: |cos| of the angle between ray and surface normal, 0 where no hit.
    reflectivity: the object's reflectivity, NaN where nothing is hit.
    object_id: index into ``scene.objects``, -1 where nothing is hit.
    """

    range_m: NDArray[np.float64]
    point_m: NDArray[np.float64]
    cos_incidence: NDArray[np.float64]
    reflectivity: NDArray[np.float64]
    object_id: NDArray[np.int64]

    @property
    def lit(self) -> NDArray[np.bool_]:
        """True where the ray hits an object."""
        return self.object_id >= 0


@functools.lru_cache(maxsize=64)
def glyph_polygons(text: str, font: str, height_m: float) -> tuple[NDArray[np.float64], ...]:
    """Glyph outlines of ``text`` as closed polygons (m), ink box ``height_m`` tall, centred at 0.

    Coordinates (u, v): u to the right along the text, v up.
    """
    # matplotlib loaded lazily: about 0.2 s of import that only scenes with text need
    from matplotlib.font_manager import FontProperties
    from matplotlib.textpath import TextPath  # (lazy, as above)

    path = TextPath((0.0, 0.0), text, size=1.0, prop=FontProperties(family=font))
    ext = path.get_extents()
    scale = height_m / ext.height
    centre = np.array([(ext.x0 + ext.x1) / 2, (ext.y0 + ext.y1) / 2])
    return tuple((np.asarray(p, dtype=np.float64) - centre) * scale for p in path.to_polygons())


def _inside_even_odd(polys: tuple[NDArray, ...], uv: NDArray[np.float64]) -> NDArray[np.bool_]:
    from matplotlib.path import Path  # lazy: only text objects need matplotlib (0.2 s import)

    inside = np.zeros(len(uv), dtype=bool)
    for poly in polys:
        lo, hi = poly.min(axis=0), poly.max(axis=0)
        cand = np.all((uv >= lo) & (uv <= hi), axis=1)
        if np.any(cand):
            hit = Path(poly).contains_points(uv[cand])
            idx = np.flatnonzero(cand)
            inside[idx[hit]] ^= True
    return inside


def intersect(obj: ObjectSpec, origin: NDArray[np.float64],
              dirs: NDArray[np.float64]) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Distance ``t`` (m, inf if missed) and |cos incidence| of rays (M, 3) against one object."""
    rot = obj.rotation
    o = (origin - obj.position_m) @ rot  # local frame: rot.T @ (o - p)
    d = dirs @ rot
    m = len(d)
    t = np.full(m, np.inf)
    cos = np.zeros(m)
    with np.errstate(divide="ignore", invalid="ignore"):
        if obj.kind in ("plane", "text"):
            # local plane x = 0, normal along local x
            tt = -o[0] / d[:, 0]
            ok = np.isfinite(tt) & (tt > 1e-9)
            hit = o[None, :] + tt[:, None] * d
            if obj.kind == "plane":
                if obj.size_m is not None:
                    ok &= (np.abs(hit[:, 1]) <= obj.size_m[0] / 2) & \
                          (np.abs(hit[:, 2]) <= obj.size_m[1] / 2)
            else:
                ok &= d[:, 0] > 0  # the front face faces -x: seen from the front only
                polys = glyph_polygons(obj.text, obj.font, obj.height_m)
                idx = np.flatnonzero(ok)
                uv = np.stack([-hit[idx, 1], hit[idx, 2]], axis=1)
                keep = _inside_even_odd(polys, uv)
                ok[idx[~keep]] = False
            t[ok] = tt[ok]
            cos[ok] = np.abs(d[ok, 0])
        elif obj.kind == "box":
            half = obj.size_m / 2
            t1 = (-half - o) / d
            t2 = (half - o) / d
            tnear = np.nanmax(np.minimum(t1, t2), axis=1)
            tfar = np.nanmin(np.maximum(t1, t2), axis=1)
            ok = (tnear <= tfar) & (tfar > 1e-9)
            tentry = np.where(tnear > 1e-9, tnear, tfar)
            axis = np.argmax(np.where(tnear[:, None] > 1e-9, np.minimum(t1, t2),
                                      np.maximum(t1, t2) * -1), axis=1)
            t[ok] = tentry[ok]
            cos[ok] = np.abs(d[ok, axis[ok]])
        elif obj.kind == "sphere":
            b = d @ o
            c = o @ o - obj.radius_m ** 2
            disc = b * b - c
            sq = np.sqrt(np.maximum(disc, 0.0))
            t_in, t_out = -b - sq, -b + sq
            tt = np.where(t_in > 1e-9, t_in, t_out)
            ok = (disc >= 0) & (tt > 1e-9)
            t[ok] = tt[ok]
            normal = o[None, :] + tt[:, None] * d
            normal /= np.linalg.norm(normal, axis=1, keepdims=True)
            cos[ok] = np.abs(np.sum(normal[ok] * d[ok], axis=1))
        else:  # pragma: no cover - model.py rejects other kinds
            raise AssertionError(obj.kind)
    return t, cos


def cast(scene: Scene, directions: NDArray[np.float64],
         origin: NDArray[np.float64] | None = None) -> Hits:
    """Nearest hit of every ray in ``directions`` (..., 3) against all objects of ``scene``."""
    dirs = np.asarray(directions, dtype=np.float64)
    shape = dirs.shape[:-1]
    flat = dirs.reshape(-1, 3)
    o = np.zeros(3) if origin is None else np.asarray(origin, dtype=np.float64)
    best_t = np.full(len(flat), np.inf)
    best_cos = np.zeros(len(flat))
    best_id = np.full(len(flat), -1, dtype=np.int64)
    for i, obj in enumerate(scene.objects):
        t, cos = intersect(obj, o, flat)
        closer = t < best_t
        best_t[closer] = t[closer]
        best_cos[closer] = cos[closer]
        best_id[closer] = i
    lit = best_id >= 0
    rng = np.where(lit, best_t, np.nan)
    t_fin = np.where(lit, best_t, 0.0)
    point = np.where(lit[:, None], o[None, :] + t_fin[:, None] * flat, np.nan)
    refl_table = np.array([obj.reflectivity for obj in scene.objects] + [np.nan])
    refl = refl_table[best_id]
    return Hits(range_m=rng.reshape(shape), point_m=point.reshape(*shape, 3),
                cos_incidence=np.where(lit, best_cos, 0.0).reshape(shape),
                reflectivity=refl.reshape(shape), object_id=best_id.reshape(shape))
