"""The ``fig3`` study: the paper's 3D scans, 40 x 160 pixels at 5 m and 10 m (paper Fig. 3).

Each task scans one of the paper's scenes in-process (:func:`cdma_lidar.study.simulate.
simulate_frame`: the instrument renders every column, the bit-exact receive chain
correlates it) and ranges the frame the host's way
(:func:`cdma_lidar.host.ranging.estimate_ranges`, perfect calibration): ``paper-scene1``
(the letters "CDMA LIDAR" at three depths near 5 m, azimuth -5..5 deg) and
``paper-scene2`` (letters "NUS" and a flower near 10 m, -5..0 deg), both 40 channels x 160
columns with ten records summed, as the paper's scans.

Columns: ``channels``, ``columns``, ``object_pixels`` (pixels whose ray hits an object),
``valid_fraction`` (of those, accepted by the host), ``median_error_m`` (|range - truth|
over the accepted object pixels), ``clusters`` (runs of ``bin_m`` histogram bins each
holding at least 2 % of the accepted ranges: the paper's Fig. 3e histogram),
``clusters_truth`` (the same count on the true ranges), ``depth_step_m`` (median step
between the scene's depth groups), ``sigma_m`` (1.4826 x MAD of range - truth),
``smallest_group_share`` (of the accepted object pixels), ``time_s`` (machine). The
cause of ``clusters_scene1`` sets the ranges' 2 sigma against the depth step, which
decides whether a small middle group shows as a cluster of its own.

``point=paper`` adds what the paper's set-up had and the presets leave out: the channels
recorded one after another and summed (Supp. Note 4's sequential mixing) and the
APD430C's 400 MHz bandwidth.
"""

from __future__ import annotations

import dataclasses
import math
import time
from typing import Any

import numpy as np

from cdma_lidar.errors import out_of_range
from cdma_lidar.host.ranging import estimate_ranges
from cdma_lidar.scene import load_scene
from cdma_lidar.study.engine import RunContext, RunOptions, Setting, Study, Table, grid_product
from cdma_lidar.study.figures import new_figure, save_figure
from cdma_lidar.study.paperlab import check_point, entry, exact
from cdma_lidar.study.simulate import simulate_frame

__all__ = ["REPORT_NOTE", "STUDY", "clusters", "fig3_task"]

#: Paper, Fig. 3e: "the objects are clearly categorized into three distinct clusters".
PAPER_CLUSTERS_SCENE1 = 3
#: Paper: "3D point clouds are captured with a 40 x 160 pixels resolution".
PAPER_PIXELS = "40 x 160"
#: Paper, Fig. 3d: its two points, in words (it prints no SNR_XC value).
PAPER_POINT_WORDS = {13: "high-confidence point (point 13) with correct depth information",
                     35: "low-confidence point (point 35) with incorrect depth information"}

SCENES = ("paper-scene1", "paper-scene2")

REPORT_NOTE = (
    "The paper's two scans on the simulated instrument: every pixel through the receive "
    "chain and the host's ranging. The scene presets were built from the paper's "
    "description (letter sizes, the three depths of scene 1, the fields of view); their "
    "positions are ours, so the cluster count and the accepted fraction test the "
    "instrument on a scene like the paper's, not the paper's exact scene. At the paper's "
    "point the sequential mixing of Supp. Note 4 adds each channel's noise 40 times, which "
    "the `cause` column shows against the default."
)


def clusters(ranges_m: np.ndarray, bin_m: float, min_share: float = 0.02) -> int:
    """Clusters of a range histogram: runs of adjacent ``bin_m`` bins each holding at least
    ``min_share`` of the ranges (a few stray ranges between two depths do not join them)."""
    r = np.asarray(ranges_m, float)
    r = r[np.isfinite(r)]
    if r.size == 0:
        return 0
    edges = np.arange(r.min(), r.max() + 2 * bin_m, bin_m)
    full = np.histogram(r, bins=edges)[0] >= min_share * r.size
    return int(np.sum(full[1:] & ~full[:-1]) + full[0])


def _grid(options: RunOptions) -> list[dict]:
    paper = check_point(options["point"]) == "paper"
    gap = float(options["bin_m"])
    if not 0.0 < gap < 10.0:
        raise out_of_range("bin_m", "0..10 m", gap)
    for s in options["scenes"]:
        if s not in SCENES:
            raise out_of_range("scenes", " or ".join(SCENES), s)
    pts = grid_product(scene=list(options["scenes"]), sequential_mixing=[paper],
                       detector_bandwidth_mhz=[400.0 if paper else 200.0], bin_m=[gap],
                       depth_scale=[1.0])
    scale = float(options["depth_scale"])
    if not 1.0 <= scale <= 10.0:
        raise out_of_range("depth_scale", "1..10", scale)
    if scale != 1.0 and "paper-scene1" in options["scenes"]:  # scene 1 again, depths spread
        pts.append({**pts[0], "scene": "paper-scene1", "depth_scale": scale})
    return pts


def _spread(scene: str, scale: float) -> str:
    """Query moving scene 1's objects ``scale`` times as far from their mean depth (m)."""
    if scale == 1.0:
        return ""
    xs = [float(o.position_m[0]) for o in load_scene(scene).objects]
    mid = float(np.mean(xs))
    return "".join(f"&objects[{i}].position_m[0]={mid + (x - mid) * scale:.6f}"
                   for i, x in enumerate(xs))


def fig3_task(params: dict, seed: np.random.SeedSequence) -> dict[str, Any]:
    """One scan of one scene: accepted fraction, error and clusters of the object pixels."""
    t0 = time.perf_counter()
    scene = (f"{params['scene']}?instrument.sequential_mixing="
             f"{'true' if params['sequential_mixing'] else 'false'}"
             f"&instrument.detector_bandwidth_hz={float(params['detector_bandwidth_mhz']) * 1e6}"
             + _spread(str(params["scene"]), float(params["depth_scale"])))
    scan = simulate_frame(scene, seed=int(seed.generate_state(1)[0]))
    img = estimate_ranges(scan.frame, dataclasses.replace(scan.ranging,
                                                          offset_m=scan.true_offset_m))
    obj = np.isfinite(scan.truth_range_m)
    ok = obj & img.valid
    signed = (img.range_m - scan.truth_range_m)[ok]
    err = np.abs(signed)
    truth = scan.truth_range_m[ok]
    # the scene's depth groups (true ranges split at gaps over 5 cm): their step and the
    # smallest group's share of the pixels, against the ranges' 2 sigma
    t = np.sort(truth)
    cuts = t[:-1][np.diff(t) > 0.05] if t.size else t
    group = np.searchsorted(cuts, truth, side="left")
    step = float(np.median(np.diff([np.median(truth[group == g]) for g in np.unique(group)]))
                 ) if cuts.size else math.nan
    return {"channels": int(obj.shape[0]), "columns": int(obj.shape[1]),
            "object_pixels": int(obj.sum()),
            "valid_fraction": float(ok.sum() / max(obj.sum(), 1)),
            "median_error_m": float(np.median(err)) if err.size else math.nan,
            "clusters": clusters(img.range_m[ok], float(params["bin_m"])),
            "clusters_truth": clusters(truth, float(params["bin_m"])),
            "depth_step_m": step,
            "sigma_m": float(1.4826 * np.median(np.abs(signed - np.median(signed))))
            if signed.size else math.nan,
            "smallest_group_share": float(np.bincount(group).min() / group.size)
            if group.size else math.nan,
            "ranges_m": " ".join(f"{x:.4f}" for x in img.range_m[ok]),
            **line3(img, scan.truth_range_m, scan.ranging.snr_threshold_db),
            "time_s": time.perf_counter() - t0}


#: Paper, Fig. 3c/3d: line 3 (one column, all 40 channels) and its points 13 and 35
#: (1-based: a high-confidence pixel with the correct depth, and a low-confidence one with
#: an incorrect depth). The column: the middle of the scan (the paper's is not given).
POINTS_3D = (13, 35)
#: A depth within the paper's own 25.68 cm resolution of the truth is correct.
CORRECT_M = 0.2568


def line3(img: Any, truth: np.ndarray, threshold_db: float) -> dict[str, Any]:
    """Fig. 3c/3d on line 3 (the middle column): each of :data:`POINTS_3D`'s SNR_XC (dB)
    and whether its depth is correct, and over the whole scan the median SNR_XC of the
    object pixels with a correct depth and of those with an incorrect one."""
    col = truth.shape[1] // 2
    err = np.abs(img.range_m - truth)
    obj = np.isfinite(truth)
    good = obj & (err <= CORRECT_M)
    bad = obj & ~good
    out: dict[str, Any] = {"line3_column": col, "snr_threshold_db": float(threshold_db)}
    for p in POINTS_3D:
        out[f"snr_xc_point{p}_db"] = float(img.snr_xc_db[p - 1, col])
        out[f"correct_point{p}"] = int(good[p - 1, col])
        out[f"object_point{p}"] = int(obj[p - 1, col])
    out["snr_xc_correct_median_db"] = float(np.median(img.snr_xc_db[good])) if good.any() \
        else math.nan
    out["snr_xc_incorrect_median_db"] = float(np.median(img.snr_xc_db[bad])) if bad.any() \
        else math.nan
    out["incorrect_pixels"] = int(bad.sum())
    return out


def _points_3d(row: dict, where: str) -> dict[str, Any]:
    """Fig. 3c/3d's rows: point 13 confident and correct, point 35 not confident and wrong
    (the criterion, written before the run: SNR_XC above the receiver's threshold with a
    depth within 25.68 cm, and below it or wrong); the scene is ours, so the mechanism row
    compares the whole scan's correct and incorrect pixels' median SNR_XC."""
    thr = float(row["snr_threshold_db"])
    out: dict[str, Any] = {}
    for p, confident in zip(POINTS_3D, (True, False), strict=True):
        snr, ok = float(row[f"snr_xc_point{p}_db"]), bool(row[f"correct_point{p}"])
        holds = (snr >= thr and ok) if confident else (snr < thr or not ok)
        out[f"snr_xc_point{p}_db"] = exact(
            snr, PAPER_POINT_WORDS[p], "dB", verdict="reproduced" if holds else "differs",
            criterion=("SNR_XC at or above the threshold and the depth within 25.68 cm"
                       if confident else "SNR_XC below the threshold or the depth wrong"),
            cause=f"{where}: line 3 = column {row['line3_column']}, point {p} "
                  f"{'on an object' if row[f'object_point{p}'] else 'on no object'}, "
                  f"SNR_XC {snr:.1f} dB against the threshold {thr:.1f} dB, depth "
                  f"{'correct' if ok else 'wrong'}")
    good, bad = float(row["snr_xc_correct_median_db"]), float(row["snr_xc_incorrect_median_db"])
    out["snr_xc_wrong_minus_right_db"] = exact(
        bad - good, None, "dB",
        derived=f"median SNR_XC of the {row['incorrect_pixels']} object pixels with a wrong "
                f"depth minus that of the correct ones (Fig. 3c: false depths have low "
                f"SNR_XC)")
    return out


def _reduce(table: Table, ctx: RunContext) -> dict[str, Any]:
    fig, axes = new_figure(4.2 * len(table.rows), 3.4, 1, len(table.rows))
    axes = axes if isinstance(axes, list) else [axes]
    out: dict[str, Any] = {}
    for ax, row in zip(axes, table.rows, strict=True):
        r = np.array([float(x) for x in str(row["ranges_m"]).replace('"', " ").split()])
        ax.hist(r, bins=80, color="tab:blue")
        ax.set_xlabel("range (m)")
        ax.set_ylabel("pixels")
        spread = float(row["depth_scale"]) != 1.0
        tag = f", depth steps x{row['depth_scale']:g}" if spread else ""
        ax.set_title(f"{row['scene']}{tag}: {row['clusters']} clusters", fontsize=9)
        row["ranges_m"] = "(figure)"
        if spread:
            continue
        if row["scene"] == "paper-scene1":
            ax.text(0.02, 0.97, "paper Fig. 3e: three clusters near 5 m\n(positions not "
                    "printed: not drawn)", transform=ax.transAxes, va="top", fontsize=7)
        n = 1 if row["scene"] == "paper-scene1" else 2
        where = (f"{row['scene']}, sequential mixing {'on' if row['sequential_mixing'] else 'off'},"
                 f" {row['detector_bandwidth_mhz']:g} MHz detector")
        out[f"pixels_scene{n}"] = exact(f"{row['channels']} x {row['columns']}", PAPER_PIXELS,
                                        "pixels", verdict="exact" if
                                        f"{row['channels']} x {row['columns']}" == PAPER_PIXELS
                                        else "differs")
        if n == 1:
            out["clusters_scene1"] = entry(
                int(row["clusters"]), PAPER_CLUSTERS_SCENE1, "clusters", exact=True,
                cause=f"{where}: {row['clusters']} clusters ({row['clusters_truth']} in the "
                      f"true ranges), {row['valid_fraction']:.3f} of the object pixels "
                      f"accepted, median error {row['median_error_m'] * 100:.1f} cm, "
                      f"2 sigma {2 * row['sigma_m'] * 100:.1f} cm against the preset's depth "
                      f"step of {row['depth_step_m'] * 100:.1f} cm (ours: the paper gives no "
                      f"depths), the smallest depth group holding "
                      f"{row['smallest_group_share']:.3f} of the pixels")
        if n == 1:
            out.update(_points_3d(row, where))
        out[f"valid_fraction_scene{n}"] = entry(
            row["valid_fraction"], None, "1", derived=f"{where}; of {row['object_pixels']} "
                                                      "object pixels")
        out[f"median_error_m_scene{n}"] = entry(row["median_error_m"], None, "m",
                                                derived="accepted object pixels")
    for row in table.rows:
        if float(row["depth_scale"]) != 1.0 and "clusters_scene1" in out:
            out["clusters_scene1"]["cause"] += (
                f"; the same instrument with scene 1's depth steps x{row['depth_scale']:g} "
                f"({row['depth_step_m'] * 100:.1f} cm): {row['clusters']} clusters, 2 sigma "
                f"{2 * row['sigma_m'] * 100:.1f} cm")
            out["clusters_scene1_depths_spread"] = entry(
                int(row["clusters"]), None, "clusters",
                derived=f"scene 1 with its depth steps x{row['depth_scale']:g}")
    save_figure(fig, ctx.out / "fig3.png")
    return out


STUDY = Study(
    name="fig3",
    description="the paper's 40 x 160 scans at 5 and 10 m: accepted pixels, error and the "
                "range clusters (paper Fig. 3)",
    grid=_grid,
    task=fig3_task,
    reduce=_reduce,
    settings=(
        Setting("scenes", SCENES, "scenes to scan"),
        Setting("bin_m", 0.025, "histogram bin (m) of the cluster count"),
        Setting("depth_scale", 2.0, "scene 1 is scanned again with its objects this many "
                "times as far apart in depth (1: not); the cause of the cluster count cites it"),
        Setting("point", "default", "default (the presets) or paper (plus sequential mixing "
                "and the 400 MHz APD)"),
    ),
    machine_columns=("time_s",),
    version="3",
)
