"""The ``tradeoff`` study: what each setting costs in time and buys in range accuracy.

Every point renders one frame of a scene with the simulated instrument
(:class:`cdma_lidar.scene.instrument.Instrument`), runs each column through the
bit-exact receive chain (:class:`cdma_lidar.firmware_model.receiver.FastReceiver`,
``method="auto"``) column by column as the device does, and turns the frame into ranges
with the host's pipeline (:func:`cdma_lidar.host.ranging.estimate_ranges`, perfect
calibration: the true system delay is the offset, so the errors are the ranging's own).

Axes (the instrument's parameters are scene overrides, so the rendering follows them):

* ``S`` samples per chip (``instrument.samples_per_chip``), ``R`` repetitions averaged
  (``instrument.averages``), ``degree`` of the Gold pair (``instrument.poly_u/poly_v``,
  the first verified preferred pair of that degree), ``adc_bits``
  (``instrument.adc_bits``; full scale unchanged, so fewer bits mean a coarser LSB);
* ``gate``: the receiver's gate covers the scene's range bounds + 16 samples either side
  and is at least ``gate`` lags long (``Instrument.default_gate(minimum=gate)``, rounded up
  to 16 lags): short gates are cheaper, long ones estimate the noise floor better;
* ``method``: sub-sample refinement (``none``, ``parabolic``, ``triangle``);
* ``fidelity``: the simulation's fidelity level, one of :data:`FIDELITY_LEVELS`
  (passed to the scene as option ``fidelity`` when it is not ``exact``).

The grid is the paper's configuration (S 4, R 10, degree 11, 12-bit ADC, gate 128,
triangle, exact) on each scene, the full S x R plane around it, and every other axis
varied one at a time.

Measured columns (per frame; the ``_s`` and ``_mib`` ones measure the machine):

* ``scan_time_per_frame_s``: wall time of the whole simulated scan (render + receive + ranges);
  ``scan_cpu_per_frame_s`` its CPU time (the worker process's, so BLAS threads count):
  on an idle machine with one task per core the two agree; on a loaded one the CPU
  time is the cost and the wall time mostly the queue, so the Pareto front uses CPU time;
* ``receive_time_per_frame_s``, ``receive_cpu_per_frame_s``: of the receive chain alone
  (every column through FastReceiver);
* ``peak_memory_mib``: peak traced allocation (tracemalloc) while one column (the one
  with the most lit channels) is rendered and received, first in the task (so it
  includes the instrument's per-configuration caches): the scan's working set, since
  columns are processed one at a time;
* ``render_time_per_frame_s``: of the rendering alone (the simulated instrument's share);
* ``median_error_m``, ``p95_error_m``: |range - truth| over the valid object pixels;
* ``outlier_fraction``: valid object pixels more than :data:`OUTLIER_M` off;
* ``valid_fraction``: object pixels (truth has a hit) that are valid;
* ``false_pixels``: valid pixels where the truth has no object;
* ``snr_xc_median_db``: median SNR_XC of the valid object pixels.

The reducer adds ``setting`` (what differs from the baseline) and ``on_pareto_front``
(per scene: no point keeping at least 90 % of the scene's best valid fraction is both
faster, in CPU time, and lower in p95 error), draws ``pareto.png`` and lists the front
in ``pareto.md``.
"""

from __future__ import annotations

import dataclasses
import logging
import time
import tracemalloc
from typing import Any

import numpy as np

from cdma_lidar.checks import check_int
from cdma_lidar.errors import CdmaLidarError, out_of_range
from cdma_lidar.firmware_model.pairs import pair_degrees, preferred_pairs
from cdma_lidar.firmware_model.receiver import FastReceiver
from cdma_lidar.host.frame import FrameData
from cdma_lidar.host.ranging import METHODS, estimate_ranges
from cdma_lidar.scene import load_scene
from cdma_lidar.scene.instrument import Instrument
from cdma_lidar.scene.model import FIDELITY_LEVELS  # the scene's levels (docs/scene.md)
from cdma_lidar.study.engine import RunContext, RunOptions, Setting, Study, Table, headline
from cdma_lidar.study.figures import new_figure, save_figure
from cdma_lidar.study.simulate import ranging_config, receiver_setup, true_offset_m

__all__ = ["BASELINE", "FIDELITY_LEVELS", "OUTLIER_M", "STUDY", "pareto_front", "tradeoff_task"]

log = logging.getLogger(__name__)


#: The paper's configuration, the centre of the grid.
BASELINE: dict[str, Any] = {"S": 4, "R": 10, "degree": 11, "adc_bits": 12, "gate": 128,
                            "method": "triangle", "fidelity": "exact"}

#: A valid pixel further than this from the truth (m) counts as an outlier.
OUTLIER_M = 0.5

#: A point is a Pareto candidate only if it keeps this share of its scene's best valid fraction.
PARETO_MIN_VALID_SHARE = 0.9

SCENES = ("paper-scene1", "flat-wall")

#: Columns that measure the machine, or (``on_pareto_front``) are derived from its timings.
MACHINE_COLUMNS = ("scan_cpu_per_frame_s", "receive_cpu_per_frame_s", "scan_time_per_frame_s",
                   "receive_time_per_frame_s", "render_time_per_frame_s", "peak_memory_mib",
                   "on_pareto_front")

_AXES = ("S", "R", "degree", "adc_bits", "gate", "method", "fidelity")


def _check_axes(options: RunOptions) -> dict[str, tuple]:
    degrees = set(pair_degrees())
    for d in options["degree"]:
        if d not in degrees:
            raise out_of_range("degree", "a degree with preferred pairs: "
                               + ", ".join(map(str, sorted(degrees))), d)
    axes = {
        "S": tuple(check_int("S", s, 1, 64) for s in options["S"]),
        "R": tuple(check_int("R", r, 1, 1024) for r in options["R"]),
        "degree": tuple(options["degree"]),
        "adc_bits": tuple(check_int("adc_bits", b, 8, 16) for b in options["adc_bits"]),
        "gate": tuple(check_int("gate", g, 16, 1 << 20) for g in options["gate"]),
        "method": tuple(options["method"]),
        "fidelity": tuple(options["fidelity"]),
    }
    for m in axes["method"]:
        if m not in METHODS:
            raise out_of_range("method", "one of " + ", ".join(METHODS), m)
    for f in axes["fidelity"]:
        if f not in FIDELITY_LEVELS:
            raise out_of_range("fidelity", "one of " + ", ".join(FIDELITY_LEVELS), f)
    for s in options["scenes"]:
        load_scene(s)  # a bad scene name fails here, naming the presets
    return axes


def _grid(options: RunOptions) -> list[dict]:
    """Baseline, the S x R plane around it, then every other axis one at a time."""
    axes = _check_axes(options)
    points: list[dict] = []
    seen: set[tuple] = set()

    def add(scene: str, **change: Any) -> None:
        p = {"scene": scene, **BASELINE, **change}
        key = tuple(p.values())
        if key not in seen:
            seen.add(key)
            points.append(p)

    for scene in options["scenes"]:
        add(scene)
        for s in axes["S"]:
            for r in axes["R"]:
                add(scene, S=s, R=r)
        for name in ("degree", "adc_bits", "gate", "method", "fidelity"):
            for v in axes[name]:
                add(scene, **{name: v})
    return points


def _scene_overrides(params: dict) -> dict[str, Any]:
    u, v = preferred_pairs(int(params["degree"]))[0]
    over: dict[str, Any] = {"instrument.samples_per_chip": int(params["S"]),
                            "instrument.averages": int(params["R"]),
                            "instrument.poly_u": list(u), "instrument.poly_v": list(v),
                            "instrument.adc_bits": int(params["adc_bits"])}
    if params["fidelity"] != "exact":
        over["fidelity"] = params["fidelity"]
    return over


def tradeoff_task(params: dict, seed: np.random.SeedSequence) -> dict[str, Any]:
    """One frame of ``params["scene"]`` at one configuration; see the module docstring.

    A configuration the scene or the receiver refuses is a row with ``status`` "refused"
    and the ``reason``.
    """
    try:
        inst = Instrument(load_scene(params["scene"], _scene_overrides(params)),
                          seed=int(seed.generate_state(1)[0]))
        cfg, codes = receiver_setup(inst, gate=inst.default_gate(minimum=int(params["gate"])))
        rx = FastReceiver(cfg, codes)
    except CdmaLidarError as exc:
        return {"status": "refused", "reason": str(exc)}
    spec = inst.spec
    k, c = inst.channels, inst.columns
    # Memory first, on the column with the most lit channels; it also warms the
    # instrument's per-configuration caches, so the timed loop is a steady-state frame.
    busiest = int(np.argmax(inst.truth.hits.lit.sum(axis=0)))
    tracemalloc.start()
    try:
        rx.column(inst.render(busiest))
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()

    frame = FrameData.empty(k, c, spec.uid_bits, 1, 0)
    t_render = t_rx = cpu_rx = 0.0
    t0, cpu0 = time.perf_counter(), time.process_time()
    for col in range(c):
        ta = time.perf_counter()
        samples = inst.render(col)
        tb, cpu_b = time.perf_counter(), time.process_time()
        out = rx.column(samples)
        t_rx += time.perf_counter() - tb
        cpu_rx += time.process_time() - cpu_b
        t_render += tb - ta
        frame.set_column(col, out, angle_deg=float(spec.rotations_deg[col]))
    ranging = dataclasses.replace(ranging_config(inst), offset_m=true_offset_m(inst),
                                  method=str(params["method"]))
    img = estimate_ranges(frame, ranging)
    t_scan, cpu_scan = time.perf_counter() - t0, time.process_time() - cpu0

    truth = inst.truth.range_m
    obj = np.isfinite(truth)
    ok = img.valid & obj
    err = np.abs(img.range_m - truth)[ok]
    snr = img.snr_xc_db[ok]
    return {
        "status": "ok", "reason": "",
        "out_shift": cfg.out_shift, "gate_lags": cfg.gate_len,
        "correlator": rx.correlator_method,
        "median_error_m": float(np.median(err)) if err.size else float("nan"),
        "p95_error_m": float(np.percentile(err, 95)) if err.size else float("nan"),
        "outlier_fraction": float(np.mean(err > OUTLIER_M)) if err.size else float("nan"),
        "valid_fraction": float(np.mean(img.valid[obj])) if obj.any() else float("nan"),
        "false_pixels": int(np.count_nonzero(img.valid & ~obj)),
        "snr_xc_median_db": float(np.median(snr)) if snr.size else float("nan"),
        "scan_cpu_per_frame_s": cpu_scan, "receive_cpu_per_frame_s": cpu_rx,
        "scan_time_per_frame_s": t_scan, "receive_time_per_frame_s": t_rx,
        "render_time_per_frame_s": t_render,
        "peak_memory_mib": peak / 2**20,
    }


def pareto_front(time_s: np.ndarray, error_m: np.ndarray, eligible: np.ndarray) -> np.ndarray:
    """Boolean mask of the eligible points no other eligible point beats on both axes.

    Point i is dominated when some eligible j has time_j <= time_i and error_j <= error_i
    with at least one strict. NaN times or errors are never on the front.
    """
    t, e = np.asarray(time_s, float), np.asarray(error_m, float)
    ok = np.asarray(eligible, bool) & np.isfinite(t) & np.isfinite(e)
    front = ok.copy()
    for i in np.flatnonzero(ok):
        better = ok & (t <= t[i]) & (e <= e[i]) & ((t < t[i]) | (e < e[i]))
        front[i] = not better.any()
    return front


#: The time axis of the Pareto front: CPU time of the whole simulated scan per frame.
PARETO_TIME = "scan_cpu_per_frame_s"


def _time(table: Table) -> np.ndarray:
    """CPU time per frame of the scan: the best of the replicates when there are several."""
    best = f"{PARETO_TIME}_best"
    return table.column(best if best in table.columns else PARETO_TIME)


def _label(row: dict) -> str:
    diff = [f"{k}={row[k]}" for k in _AXES if row[k] != BASELINE[k]]
    return ", ".join(diff) if diff else "paper baseline"


def _reduce(table: Table, ctx: RunContext) -> dict[str, Any]:
    status = table.column("status")
    ok = np.array([s == "ok" for s in status])
    scenes = table.column("scene")
    t, e = _time(table), table.column("p95_error_m")
    valid = table.column("valid_fraction")
    front = np.zeros(len(table), bool)
    for scene in dict.fromkeys(scenes):
        mine = ok & (scenes == scene)
        if not mine.any():
            continue
        best = np.nanmax(np.where(mine, valid, np.nan))
        eligible = mine & (valid >= PARETO_MIN_VALID_SHARE * best)
        front |= pareto_front(t, e, eligible)
    table.add_column("on_pareto_front", front)
    table.add_column("setting", [_label(r) for r in table.rows])

    summary: dict[str, Any] = {}
    for scene in dict.fromkeys(scenes):
        base = [i for i, r in enumerate(table.rows) if r["scene"] == scene
                and all(r[k] == v for k, v in BASELINE.items()) and ok[i]]
        if base:
            b = table.rows[base[0]]
            summary[f"{scene}_baseline_median_error_m"] = headline(b["median_error_m"], None, "m")
            summary[f"{scene}_baseline_p95_error_m"] = headline(b["p95_error_m"], None, "m")
            summary[f"{scene}_baseline_valid_fraction"] = headline(b["valid_fraction"], None, "1")
            summary[f"{scene}_baseline_scan_cpu_per_frame_s"] = headline(
                b["scan_cpu_per_frame_s"], None, "s")
        summary[f"{scene}_pareto_points"] = headline(int((front & (scenes == scene)).sum()),
                                                     None, "configurations")
    summary["configurations"] = headline(len(table), None, "configurations")
    summary["refused"] = headline(int((~ok).sum()), None, "configurations")
    _figure(table, ok, front, ctx)
    _write_front(table, front, ctx)
    return summary


def _figure(table: Table, ok: np.ndarray, front: np.ndarray, ctx: RunContext) -> None:
    scenes = list(dict.fromkeys(table.column("scene")))
    fig, axes = new_figure(6.5 * len(scenes), 5.0, 1, len(scenes))
    axes = axes if isinstance(axes, list) else [axes]
    t, e = _time(table), table.column("p95_error_m")
    for ax, scene in zip(axes, scenes, strict=True):
        mine = ok & (table.column("scene") == scene)
        ax.scatter(t[mine & ~front], e[mine & ~front], s=18, color="0.6", label="configuration")
        f = np.flatnonzero(mine & front)
        f = f[np.argsort(t[f])]
        ax.plot(t[f], e[f], "o-", color="C3", label="Pareto front")
        for i in f:
            ax.annotate(_label(table.rows[i]), (t[i], e[i]), fontsize=6,
                        xytext=(4, 3), textcoords="offset points")
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.set_xlabel("CPU time per frame, whole simulated scan (s)")
        ax.set_ylabel("95th-percentile range error (m)")
        ax.set_title(scene)
        ax.grid(alpha=0.3, which="both")
        ax.legend(fontsize=8)
    save_figure(fig, ctx.out / "pareto.png")


def _write_front(table: Table, front: np.ndarray, ctx: RunContext) -> None:
    cols = ["scene", "setting", "scan_cpu_per_frame_s", "receive_cpu_per_frame_s",
            "median_error_m", "p95_error_m", "valid_fraction", "false_pixels"]
    rows = [table.rows[i] for i in np.flatnonzero(front)]
    rows.sort(key=lambda r: (r["scene"], r["scan_cpu_per_frame_s"]))
    text = ("# Pareto front: CPU time per frame vs 95th-percentile range error\n\n"
            f"Points keeping at least {PARETO_MIN_VALID_SHARE:.0%} of their scene's best "
            "valid fraction; none is both faster and more accurate.\n\n"
            + Table(cols, [{c: r[c] for c in cols} for r in rows]).to_markdown())
    (ctx.out / "pareto.md").write_text(text)


def _settings() -> tuple[Setting, ...]:
    return (
        Setting("scenes", SCENES, "scenes (presets or TOML files)"),
        Setting("S", (1, 2, 4, 8, 16), "samples per chip, crossed with R", quick=(1, 2, 4, 8)),
        Setting("R", (1, 3, 10, 30, 100), "repetitions averaged, crossed with S", quick=(1, 10)),
        Setting("degree", (9, 10, 11, 13, 15), "code degrees (one at a time)", quick=(9, 13)),
        Setting("adc_bits", (8, 10, 12, 14, 16), "ADC bits (one at a time)", quick=(8, 16)),
        Setting("gate", (64, 128, 256, 1024), "minimum gate lags (one at a time)",
                quick=(64,)),
        Setting("method", METHODS, "sub-sample refinement (one at a time)", quick=("none",)),
        Setting("fidelity", FIDELITY_LEVELS, "simulation fidelity levels (one at a time)"),
        Setting("replicates", 3, "independent frames per configuration", quick=1),
    )


STUDY = Study(
    name="tradeoff",
    description="speed vs range accuracy over S, R, code degree, ADC bits, gate, sub-sample "
                "method and fidelity on paper-scene1 and flat-wall; Pareto front",
    grid=_grid,
    task=tradeoff_task,
    reduce=_reduce,
    settings=_settings(),
    machine_columns=MACHINE_COLUMNS,
    version="2",  # 2: CPU times added, the Pareto front on CPU time
)
