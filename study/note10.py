"""The ``note10`` study: the grating's bow-shaped scan and its correction (paper Supp. Note 10).

The paper steers its 40 wavelengths through a 600 grooves/mm grating and scans by
rotating the grating about its normal; the first order then follows "a non-linear
bow-like curve" (eq. 47), which "creat[es] a unilateral bow-like shape in the image" of
scene 2 (Fig. 3f) and "is fixed by a unique algorithm to map distances precisely". Here,
for the pixel grids of ``paper-scene1`` (-5..5 deg) and ``paper-scene2`` (-5..0 deg):

* ``eq47_deviation_deg`` -- the largest angle between the toolkit's grating model
  (:class:`cdma_lidar.optics.grating.GratingGeometry`, which the host's reconstruction
  uses) and eq. 47 as the paper prints it, evaluated here independently
  (:func:`eq47_direction`) over every channel and rotation of both scenes;
* ``bow_sag_deg_scene{1,2}`` -- how far the middle channel's elevation moves over the
  scene's rotations (the bow), also in channel steps (the paper's 0.03 deg);
* ``uncorrected_error_cm_scene{1,2}`` -- what the correction removes: the largest distance
  at the scene's range between eq. 47's point and the point of a rectangular grid
  (azimuth linear in the rotation between the scene's edges, elevation each channel's
  at rotation 0), i.e. the error of a reconstruction that ignores the bow.

No trials: every number is geometry. ``point`` is accepted for uniformity (one point,
the paper's: its grating, wavelengths and fields of view; the incidence angle is an
assumption, :data:`cdma_lidar.study.paperlab.ASSUMPTIONS`).
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from cdma_lidar.errors import out_of_range
from cdma_lidar.optics.grating import azimuth_elevation_deg
from cdma_lidar.scene import load_scene
from cdma_lidar.study.engine import RunContext, Setting, Study, Table
from cdma_lidar.study.figures import new_figure, save_figure
from cdma_lidar.study.paperlab import check_point, entry, exact

__all__ = ["REPORT_NOTE", "STUDY", "eq47_direction", "note10_task"]

SCENES = ("paper-scene1", "paper-scene2")
#: Paper, Results: "an angular resolution of 0.03 deg" (the channel step, the bow's unit).
PAPER_CHANNEL_STEP_DEG = 0.03
#: Paper, Results on scene 2: "creating a unilateral bow-like shape in the image" (no number).
PAPER_BOW = "a unilateral bow-like shape"
#: Largest angle (deg) between two evaluations of eq. 47 that still counts as the same.
SAME_DEG = 1e-9

REPORT_NOTE = (
    "Supp. Note 10's geometry on the paper's grating (600 grooves/mm, the 40 L-band "
    "channels, the fields of view of scenes 1 and 2). The run compares the toolkit's "
    "grating model with eq. 47 as printed, and measures how far rotating the grating moves "
    "a channel's elevation (the bow) in channel steps: more than one step shows in the "
    "image as the paper's bow-like shape. The derived rows give how far a reconstruction "
    "on a rectangular grid would misplace pixels; the host's reconstruction places each "
    "pixel on eq. 47's ray instead (docs/host.md). The figure draws eq. 47 as the paper "
    "prints it (computed here, not digitised from its Fig. 15d) over the toolkit's model. "
    "The sag depends on the incidence angle, which the paper does not state (60 deg "
    "assumed)."
)


def eq47_direction(wavelength_m: Any, rotation_deg: Any, grooves_per_mm: float,
                   incidence_deg: float, gamma_rad: float) -> np.ndarray:
    """Unit first-order direction in the sensor frame, from eq. 47 and eq. 49 as printed.

    Eq. 47: K_d / (2 pi / lambda) = [-G sin t_r, sin t_i - G cos t_r,
    (1 - G^2 - sin^2 t_i + 2 G sin t_i cos t_r)^(1/2)], G = lambda / Lambda; eq. 49 turns
    the grating frame about X by gamma; the sensor frame is (x, y, z) = (-Y', X', Z').
    Broadcasts ``wavelength_m`` (m) against ``rotation_deg`` (deg).
    """
    lam, rot = np.broadcast_arrays(np.asarray(wavelength_m, float),
                                   np.deg2rad(np.asarray(rotation_deg, float)))
    g = lam * grooves_per_mm * 1e3
    si = math.sin(math.radians(incidence_deg))
    kx = -g * np.sin(rot)
    ky = si - g * np.cos(rot)
    kz = np.sqrt(1 - g**2 - si**2 + 2 * g * si * np.cos(rot))
    c, s = math.cos(gamma_rad), math.sin(gamma_rad)
    y1, z1 = c * ky - s * kz, s * ky + c * kz  # eq. 49
    return np.stack([-y1, kx, z1], axis=-1)


def _angle_deg(a: np.ndarray, b: np.ndarray) -> float:
    cos = np.clip(np.sum(a * b, axis=-1) / (np.linalg.norm(a, axis=-1)
                                            * np.linalg.norm(b, axis=-1)), -1.0, 1.0)
    # arccos loses precision near 0: the chord gives the small angle to 1e-16
    chord = np.linalg.norm(a / np.linalg.norm(a, axis=-1, keepdims=True)
                           - b / np.linalg.norm(b, axis=-1, keepdims=True), axis=-1)
    return float(np.degrees(np.max(np.where(cos > 0.999, 2 * np.arcsin(chord / 2),
                                            np.arccos(cos)))))


def _grid(options: Any) -> list[dict]:
    check_point(options["point"])
    for s in options["scenes"]:
        if s not in SCENES:
            raise out_of_range("scenes", " or ".join(SCENES), s)
    return [{"scene": s} for s in options["scenes"]]


def note10_task(params: dict, seed: np.random.SeedSequence) -> dict[str, Any]:
    """One scene's pixel grid: eq. 47 against the model, the bow's sag, the grid error."""
    del seed  # geometry only
    scene = load_scene(str(params["scene"]))
    spec = scene.instrument
    geo = spec.geometry()
    wl = np.asarray(spec.wavelengths_m)[:, None]
    rot = np.asarray(spec.rotations_deg)[None, :]
    model = geo.directions(wl, rot)
    paper = eq47_direction(wl, rot, geo.grooves_per_mm, geo.incidence_deg, geo.gamma_rad)
    az, el = azimuth_elevation_deg(paper)
    mid = el.shape[0] // 2
    sag = float(el[mid].max() - el[mid].min())
    distance = float(np.median([o.position_m[0] for o in scene.objects]))
    # a rectangular grid: azimuth linear in rotation between the edges, elevation at rotation 0
    _, el0 = azimuth_elevation_deg(eq47_direction(wl, 0.0, geo.grooves_per_mm,
                                                    geo.incidence_deg, geo.gamma_rad))
    t = (rot - rot.min()) / (rot.max() - rot.min())
    az_grid = az[mid, 0] + t * (az[mid, -1] - az[mid, 0])
    azr, elr = np.deg2rad(np.broadcast_to(az_grid, el.shape)), np.deg2rad(
        np.broadcast_to(el0, el.shape))
    grid = np.stack([np.cos(elr) * np.cos(azr), np.cos(elr) * np.sin(azr), np.sin(elr)], -1)
    err = distance * np.linalg.norm(grid - paper, axis=-1)
    steps = np.abs(np.diff(el0[:, 0]))
    return {"channels": int(el.shape[0]), "columns": int(el.shape[1]),
            "rotation_min_deg": float(rot.min()), "rotation_max_deg": float(rot.max()),
            "distance_m": distance, "eq47_deviation_deg": _angle_deg(model, paper),
            "bow_sag_deg": sag, "channel_step_deg": float(np.mean(steps)),
            "uncorrected_error_cm": float(err.max() * 100.0)}


def _reduce(table: Table, ctx: RunContext) -> dict[str, Any]:
    fig, axes = new_figure(10.0, 4.0, 1, 2)
    out: dict[str, Any] = {}
    worst = max(float(r["eq47_deviation_deg"]) for r in table.rows)
    out["eq47_deviation_deg"] = exact(
        worst, "eq. 47", "deg", verdict="exact" if worst <= SAME_DEG else "differs",
        cause=f"largest angle between the toolkit's grating model and eq. 47 as printed over "
              f"{sum(r['channels'] * r['columns'] for r in table.rows)} pixels: {worst:.2g} "
              f"deg (exact when <= {SAME_DEG:g} deg)")
    for row in table.rows:
        n = 1 if row["scene"] == "paper-scene1" else 2
        rows = row["bow_sag_deg"] / row["channel_step_deg"]
        span = f"rotation {row['rotation_min_deg']:g}..{row['rotation_max_deg']:g} deg"
        out[f"bow_sag_deg_scene{n}"] = exact(
            row["bow_sag_deg"], PAPER_BOW if n == 2 else None, "deg",
            verdict=("reproduced" if rows > 1.0 else "differs") if n == 2 else None,
            cause=f"{row['scene']}, {span}: the middle channel's elevation moves "
                  f"{row['bow_sag_deg']:.3f} deg = {rows:.1f} channel steps of "
                  f"{row['channel_step_deg']:.4f} deg (a bow visible in the image when it "
                  f"exceeds one step)")
        out[f"uncorrected_error_cm_scene{n}"] = entry(
            row["uncorrected_error_cm"], None, "cm",
            derived=f"eq. 47 against a rectangular grid at {row['distance_m']:.2f} m, {span}")
    _draw(axes, table)
    save_figure(fig, ctx.out / "note10.png")
    return out


def _draw(axes: list, table: Table) -> None:
    """Left: three channels' trajectories (model lines, eq. 47 markers), as Fig. 15d.
    Right: the scene-2 pixel grid, bow and all."""
    ax, ax2 = axes
    for row in table.rows:
        spec = load_scene(str(row["scene"])).instrument
        geo = spec.geometry()
        wl = np.asarray(spec.wavelengths_m)
        rot = np.linspace(float(row["rotation_min_deg"]), float(row["rotation_max_deg"]), 41)
        for k, colour in ((0, "tab:blue"), (len(wl) // 2, "tab:green"), (len(wl) - 1,
                                                                          "tab:red")):
            az, el = azimuth_elevation_deg(geo.directions(wl[k], rot))
            ax.plot(az, el, color=colour, lw=1.0,
                    label=f"channel {k} ({wl[k] * 1e9:.3f} nm), toolkit" if
                    row["scene"] == "paper-scene1" else None)
            paz, pel = azimuth_elevation_deg(eq47_direction(wl[k], rot[::4], geo.grooves_per_mm,
                                                            geo.incidence_deg, geo.gamma_rad))
            ax.plot(paz, pel, "x", color="k", ms=3,
                    label="paper's eq. 47 (computed, not digitised)"
                    if row["scene"] == "paper-scene1" and k == 0 else None)
        if row["scene"] == "paper-scene2":
            az, el = azimuth_elevation_deg(geo.directions(wl[:, None],
                                                          np.asarray(spec.rotations_deg)[None]))
            ax2.plot(az.ravel(), el.ravel(), ",", color="k")
            ax2.set_title("scene 2 pixel grid (40 x 160, -5..0 deg): the bow", fontsize=9)
    ax.set_xlabel("azimuth (deg)")
    ax.set_ylabel("elevation (deg)")
    ax.set_title("Supp. Fig. 15d: first-order scan trajectories", fontsize=9)
    ax.legend(fontsize=6)
    ax2.set_xlabel("azimuth (deg)")
    ax2.set_ylabel("elevation (deg)")


STUDY = Study(
    name="note10",
    description="the grating's bow-shaped scan (eq. 47) and what its correction removes "
                "(paper Supp. Note 10, Fig. 3f)",
    grid=_grid,
    task=note10_task,
    reduce=_reduce,
    settings=(
        Setting("scenes", SCENES, "scenes whose pixel grids are traced"),
        Setting("point", "default", "default or paper: one point here, the paper's own"),
    ),
    version="1",
)
