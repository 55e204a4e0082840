"""The ``tradeoff`` study: what each setting costs and buys, on axes that do not move with load.

Two trades, each on deterministic axes:

* **The instrument's**: acquisition time per frame (exact, from the configuration:
  ``C R n N / chip_rate``, columns C, repetitions R, UID periods n, code length
  N = 2**degree - 1) against range accuracy (median and 95th-percentile error, valid
  fraction; 95 % intervals over the replicate frames). Samples per chip S, ADC bits,
  gate and sub-sample method cost no acquisition time (S raises the ADC rate,
  ``adc_rate_hz = S * chip_rate``, and the receive chain's work); channel count K and
  laser power neither.
* **The modeller's**: simulation work per frame (a count, see :func:`simulation_work`)
  against the fidelity error, each level's accuracy minus the ``exact`` level's at the
  same configuration.

Every point acquires frames of a scene as the virtual board does, through the one
acquisition path (:func:`cdma_lidar.scene.acquire.acquire`: the simulated instrument's
repetition sums in batches, then the bit-exact receive chain
:class:`cdma_lidar.firmware_model.receiver.FastReceiver`, ``method="auto"``, configured as
the device is, :func:`cdma_lidar.scene.acquire.receiver_config`) and turns
each frame into ranges with the host's pipeline
(:func:`cdma_lidar.host.ranging.estimate_ranges`, perfect calibration: the true system
delay is the offset, so the errors are the ranging's own).

Axes (instrument parameters are scene overrides, so the rendering follows them):
``S`` samples per chip, ``R`` repetitions, ``degree`` of the Gold pair (the first
verified preferred pair), ``chip_mhz`` chip rate (MHz), ``K`` channels (the first K
wavelengths of the scene's comb), ``power_mw`` laser power per channel (mW; the
near-far lever: a column's channels share the detector, so power sets both a pixel's
SNR and its interference with the others), ``near_far`` (frames of the host's near-far
closed loop, :class:`cdma_lidar.host.nearfar.NearFarController`, before the measured
frame, starting from ``power_mw``: 0 is uniform power; in steady state the loop runs on
every frame, so it costs no acquisition time), ``adc_bits`` (full scale unchanged),
``gate`` (minimum gate lags, ``Instrument.default_gate(minimum=gate)``), ``method``
(sub-sample refinement) and ``fidelity`` (the simulation's level). The grid: the
paper's configuration on each scene, the S x R plane around it, fidelity crossed with
R, every other axis one at a time. Scenes at two distances: paper-scene1 (4 to 9 m),
flat-wall at 5 m and at 15 m.

Measured columns (per frame; the mean over replicates, ``_ci95`` its 95 % half-width):
``acquisition_time_per_frame_s``, ``adc_rate_hz``, ``simulation_work_per_frame`` (exact
counts); ``median_error_m``, ``p95_error_m``, ``outlier_fraction`` (valid object pixels
more than :data:`OUTLIER_M` off), ``valid_fraction`` (object pixels that are valid),
``false_pixels``, ``snr_xc_median_db``; and, measuring the machine (no front uses them):
``scan_cpu_per_frame_s``, ``render_cpu_per_frame_s``, ``receive_cpu_per_frame_s``.

The reducer adds ``setting``, ``on_pareto_front`` (the instrument's front, exact
fidelity only), ``fidelity_p95_error_m`` and ``fidelity_valid_error`` (against exact at
the same configuration), ``on_modeller_front`` (at each configuration run at more than
one level: the levels no other level there beats on both simulation work and |fidelity
p95 error|); writes ``pareto.md`` (led by the answers
of :func:`ask` for a few thresholds) and ``pareto.png``.
"""

from __future__ import annotations

import dataclasses
import logging
import math
import os
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from cdma_lidar.checks import check_int
from cdma_lidar.errors import CdmaLidarError, ConfigError, out_of_range
from cdma_lidar.firmware_model.pairs import pair_degrees, preferred_pairs
from cdma_lidar.firmware_model.receiver import FastReceiver
from cdma_lidar.host.frame import FrameData
from cdma_lidar.host.nearfar import NearFarController, PowerLimits
from cdma_lidar.host.ranging import METHODS, estimate_ranges
from cdma_lidar.scene import load_scene
from cdma_lidar.scene.acquire import acquire, column_batches
from cdma_lidar.scene.instrument import Instrument, RenderSettings
from cdma_lidar.scene.model import FIDELITY_LEVELS  # the scene's levels (docs/scene.md)
from cdma_lidar.study.engine import RunContext, RunOptions, Setting, Study, Table, headline
from cdma_lidar.study.figures import new_figure, save_figure
from cdma_lidar.study.simulate import ranging_config, receiver_setup, true_offset_m
from cdma_lidar.study.table import read_csv

__all__ = [
    "ASK_THRESHOLDS_M",
    "BASELINE",
    "FIDELITY_LEVELS",
    "MACHINE_COLUMNS",
    "OUTLIER_M",
    "STUDY",
    "Answer",
    "acquisition_time_s",
    "ask",
    "pareto_front",
    "simulation_work",
    "tradeoff_task",
]

log = logging.getLogger(__name__)


#: The paper's configuration, the centre of the grid.
BASELINE: dict[str, Any] = {"S": 4, "R": 10, "degree": 11, "chip_mhz": 62.5, "K": 40,
                            "power_mw": 2.5, "near_far": 0, "adc_bits": 12, "gate": 128,
                            "method": "triangle", "fidelity": "exact"}

#: A valid pixel further than this from the truth (m) counts as an outlier.
OUTLIER_M = 0.5

#: A point is a Pareto candidate only if it keeps this share of its scene's best valid fraction.
PARETO_MIN_VALID_SHARE = 0.9

#: The p95 thresholds (m) the report answers for.
ASK_THRESHOLDS_M = (0.03, 0.05, 0.1)

SCENES = ("paper-scene1", "flat-wall", "flat-wall?distance=15")

#: Columns that measure the machine: no front and no answer uses them.
MACHINE_COLUMNS = ("scan_cpu_per_frame_s", "render_cpu_per_frame_s", "receive_cpu_per_frame_s")

_AXES = tuple(BASELINE)


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
        "chip_mhz": tuple(float(c) for c in options["chip_mhz"]),
        "K": tuple(check_int("K", k, 1, 4096) for k in options["K"]),
        "power_mw": tuple(float(p) for p in options["power_mw"]),
        "near_far": tuple(check_int("near_far", n, 0, 16) for n in options["near_far"]),
        "adc_bits": tuple(check_int("adc_bits", b, 8, 16) for b in options["adc_bits"]),
        "gate": tuple(check_int("gate", g, 16, 1 << 20) for g in options["gate"]),
        "method": tuple(options["method"]),
        "fidelity": tuple(options["fidelity"]),
    }
    for c in axes["chip_mhz"]:
        if not 0.001 <= c <= 10_000:
            raise out_of_range("chip_mhz", "0.001 to 10000 (MHz)", c)
    for p in axes["power_mw"]:
        if not 0 < p <= 10_000:
            raise out_of_range("power_mw", "above 0 and at most 10000 (mW)", p)
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
    """Baseline, the S x R plane, fidelity x R, then every other axis one at a time."""
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
        for f in axes["fidelity"]:
            for r in axes["R"]:
                add(scene, fidelity=f, R=r)
        for name in ("degree", "chip_mhz", "K", "power_mw", "near_far", "adc_bits", "gate",
                     "method"):
            for v in axes[name]:
                add(scene, **{name: v})
    return points


def _scene_overrides(params: dict) -> dict[str, Any]:
    u, v = preferred_pairs(int(params["degree"]))[0]
    over: dict[str, Any] = {"instrument.samples_per_chip": int(params["S"]),
                            "instrument.averages": int(params["R"]),
                            "instrument.poly_u": list(u), "instrument.poly_v": list(v),
                            "instrument.chip_rate_hz": float(params["chip_mhz"]) * 1e6,
                            "instrument.wavelengths.count": int(params["K"]),
                            "instrument.laser_power_w": float(params["power_mw"]) * 1e-3,
                            "instrument.adc_bits": int(params["adc_bits"])}
    if params["fidelity"] != "exact":
        over["fidelity"] = params["fidelity"]
    return over


def acquisition_time_s(columns: int, repetitions: int, uid_bits: int, degree: int,
                       chip_rate_hz: float) -> float:
    """Time (s) the instrument needs for one frame: ``C R n (2**degree - 1) / chip_rate``."""
    return columns * repetitions * uid_bits * ((1 << degree) - 1) / chip_rate_hz


def simulation_work(lit: int, samples: int, repetitions: int, how: str,
                    tabulated: bool = False) -> int:
    """Operations the simulator performs for one column of ``samples`` (L) per repetition.

    Echo synthesis (a static scene's, once per frame when cold), in real multiply-adds:
    by the Fourier synthesis ``4 lit (L/2 + 1)`` (one complex multiply-add per bin of
    each lit channel's kernel) and ``2 L ceil(log2 L)`` for the inverse FFT when anything
    is lit; from waveform tables (``tabulated``: the ``accumulated`` level where they
    fit) two axpys of L per lit channel, ``2 lit L``. Noise and ADC, in values drawn or
    quantised, by ``how`` the column's repetition sum was made: ``"exact"`` (the sum
    drawn from its law) L Gaussians, (R - 1) L uniform bytes and L floors;
    ``"accumulated"`` L table Gaussians and L floors; ``"repetitions"`` (drawn one by
    one) R L Gaussians and R L quantisations.
    """
    if tabulated and how == "accumulated":
        echo = 2 * lit * samples
    else:
        echo = 4 * lit * (samples // 2 + 1) + (
            2 * samples * math.ceil(math.log2(samples)) if lit else 0)
    noise = {"exact": (repetitions + 1) * samples, "accumulated": 2 * samples,
             "repetitions": 2 * repetitions * samples}[how]
    return echo + noise


def _errors(img: Any, truth: np.ndarray) -> dict[str, float]:
    obj = np.isfinite(truth)
    ok = img.valid & obj
    err = np.abs(img.range_m - truth)[ok]
    snr = img.snr_xc_db[ok]
    nan = float("nan")
    return {
        "median_error_m": float(np.median(err)) if err.size else nan,
        "p95_error_m": float(np.percentile(err, 95)) if err.size else nan,
        "outlier_fraction": float(np.mean(err > OUTLIER_M)) if err.size else nan,
        "valid_fraction": float(np.mean(img.valid[obj])) if obj.any() else nan,
        "false_pixels": int(np.count_nonzero(img.valid & ~obj)),
        "snr_xc_median_db": float(np.median(snr)) if snr.size else nan,
    }


def _frame(inst: Instrument, rx: FastReceiver, cfg: RenderSettings, frame: int,
           power_w: np.ndarray, ranging: Any) -> tuple[Any, int, float, float]:
    """(range image, simulation work, CPU s rendering, CPU s receiving) of one frame at
    laser power ``power_w`` (K, C) W: the virtual board's acquisition
    (:func:`cdma_lidar.scene.acquire.acquire`, in its batches)."""
    spec = inst.spec
    c, length = inst.columns, cfg.frame_samples
    lit = inst.truth.hits.lit.sum(axis=0)
    data = FrameData.empty(inst.channels, c, spec.uid_bits, 1, frame)
    work = 0
    cpu_render = cpu_rx = 0.0
    tabulated = inst.echo_tabulated(cfg)
    for cols in column_batches(0, c, length):
        got = acquire(inst, rx, cfg, frame, cols, [power_w[:, col] for col in cols])
        cpu_render += got.render_cpu_s
        cpu_rx += got.receive_cpu_s
        for col, ok in zip(cols, got.drawn.tolist(), strict=True):
            work += simulation_work(int(lit[col]), length, cfg.averages,
                                    inst.fidelity if ok else "repetitions",
                                    tabulated=tabulated)
        for col, out in zip(cols, got.outputs, strict=True):
            data.set_column(col, out, angle_deg=float(spec.rotations_deg[col]))
    return estimate_ranges(data, ranging), work, cpu_render, cpu_rx


def tradeoff_task(params: dict, seed: np.random.SeedSequence) -> dict[str, Any]:
    """One frame of ``params["scene"]`` at one configuration; see the module docstring.

    A configuration the scene or the receiver refuses is a row with ``status`` "refused"
    and the ``reason``.
    """
    try:
        inst = Instrument(load_scene(params["scene"], _scene_overrides(params)),
                          seed=int(seed.generate_state(1)[0]))
        rcfg, codes = receiver_setup(inst, gate=inst.default_gate(minimum=int(params["gate"])))
        rx = FastReceiver(rcfg, codes)
    except CdmaLidarError as exc:
        return {"status": "refused", "reason": str(exc)}
    spec = inst.spec
    cfg = RenderSettings.from_spec(spec)
    ranging = dataclasses.replace(ranging_config(inst), offset_m=true_offset_m(inst),
                                  method=str(params["method"]))
    power = inst.default_power_w
    loops = int(params["near_far"])
    if loops:
        limits = PowerLimits(max_power=spec.max_pixel_power_w, total_cap=spec.total_power_cap_w)
        control = NearFarController(power.shape, ranging.snr_threshold_db, limits,
                                    initial_power=float(params["power_mw"]) * 1e-3)
        for f in range(1, loops + 1):
            img = _frame(inst, rx, cfg, f, control.power, ranging)[0]
            control.update(img.snr_xc_db, img.peak)
        power = control.power
    cpu0 = time.process_time()
    img, work, cpu_render, cpu_rx = _frame(inst, rx, cfg, 0, power, ranging)
    cpu_scan = time.process_time() - cpu0
    c = inst.columns
    return {
        "status": "ok", "reason": "",
        "out_shift": rcfg.out_shift, "gate_lags": rcfg.gate_len,
        "correlator": rx.correlator_method,
        "acquisition_time_per_frame_s": acquisition_time_s(
            c, cfg.averages, cfg.uid_bits, spec.code_degree, spec.chip_rate_hz),
        "adc_rate_hz": spec.chip_rate_hz * cfg.samples_per_chip,
        "simulation_work_per_frame": work,
        **_errors(img, inst.truth.range_m),
        "scan_cpu_per_frame_s": cpu_scan, "render_cpu_per_frame_s": cpu_render,
        "receive_cpu_per_frame_s": cpu_rx,
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


def _label(row: dict) -> str:
    diff = [f"{k}={row[k]}" for k in _AXES if row.get(k) != BASELINE[k]]
    return ", ".join(diff) if diff else "paper baseline"


def _instrument_key(row: dict) -> tuple:
    return (row["scene"], *(row[k] for k in _AXES if k != "fidelity"))


def _fidelity_errors(table: Table, ok: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(p95 error, valid fraction) of each row minus the exact level's at the same
    configuration (NaN where that row is missing or refused)."""
    exact = {_instrument_key(r): r for i, r in enumerate(table.rows)
             if r["fidelity"] == "exact" and ok[i]}
    dp = np.full(len(table), np.nan)
    dv = np.full(len(table), np.nan)
    for i, r in enumerate(table.rows):
        ref = exact.get(_instrument_key(r))
        if ok[i] and ref is not None:
            dp[i] = r["p95_error_m"] - ref["p95_error_m"]
            dv[i] = r["valid_fraction"] - ref["valid_fraction"]
    return dp, dv


def _reduce(table: Table, ctx: RunContext) -> dict[str, Any]:
    ok = np.array([s == "ok" for s in table.column("status")])
    scenes = table.column("scene")
    exact = np.array([r["fidelity"] == "exact" for r in table.rows])
    t, e = table.column("acquisition_time_per_frame_s"), table.column("p95_error_m")
    valid = table.column("valid_fraction")
    work = table.column("simulation_work_per_frame")
    dp, dv = _fidelity_errors(table, ok)
    # the modeller's trade: configurations run at more than one fidelity level
    levels: dict[tuple, int] = {}
    for i, r in enumerate(table.rows):
        if ok[i]:
            levels[_instrument_key(r)] = levels.get(_instrument_key(r), 0) + 1
    compared = np.isfinite(dp) & np.array([levels.get(_instrument_key(r), 0) > 1
                                           for r in table.rows])
    front = np.zeros(len(table), bool)
    modeller = np.zeros(len(table), bool)
    for scene in dict.fromkeys(scenes):
        mine = ok & (scenes == scene)
        if not (mine & exact).any():
            continue
        best = np.nanmax(np.where(mine & exact, valid, np.nan))
        eligible = mine & exact & (valid >= PARETO_MIN_VALID_SHARE * best)
        front |= pareto_front(t, e, eligible)
    # the modeller's choice is between levels at one configuration of the instrument
    for key in {_instrument_key(r) for r, c in zip(table.rows, compared, strict=True) if c}:
        same = compared & np.array([_instrument_key(r) == key for r in table.rows])
        modeller |= pareto_front(work, np.abs(dp), same)
    table.add_column("setting", [_label(r) for r in table.rows])
    table.add_column("on_pareto_front", front)
    table.add_column("fidelity_p95_error_m", dp)
    table.add_column("fidelity_valid_error", dv)
    table.add_column("on_modeller_front", modeller)

    summary: dict[str, Any] = {}
    for scene in dict.fromkeys(scenes):
        base = [i for i, r in enumerate(table.rows) if r["scene"] == scene
                and all(r[k] == v for k, v in BASELINE.items()) and ok[i]]
        if base:
            b = table.rows[base[0]]
            for col, unit in (("median_error_m", "m"), ("p95_error_m", "m"),
                              ("valid_fraction", "1"), ("acquisition_time_per_frame_s", "s"),
                              ("simulation_work_per_frame", "values")):
                summary[f"{scene}_baseline_{col}"] = headline(b[col], None, unit)
        summary[f"{scene}_pareto_points"] = headline(int((front & (scenes == scene)).sum()),
                                                     None, "configurations")
        answer = ask(table, 0.05, scene=scene)
        summary[f"{scene}_fastest_p95_under_5cm_s"] = headline(
            answer.best["acquisition_time_per_frame_s"] if answer.best else None, None, "s")
    summary["configurations"] = headline(len(table), None, "configurations")
    summary["refused"] = headline(int((~ok).sum()), None, "configurations")
    _figure(table, ok, exact, front, modeller, np.where(compared, dp, np.nan), ctx)
    _write_report(table, front, compared, ctx)
    return summary


def _figure(table: Table, ok: np.ndarray, exact: np.ndarray, front: np.ndarray,
            modeller: np.ndarray, dp: np.ndarray, ctx: RunContext) -> None:
    scenes = list(dict.fromkeys(table.column("scene")))
    fig, axes = new_figure(5.5 * len(scenes), 9.0, 2, len(scenes))
    grid = np.asarray(axes, dtype=object).reshape(2, len(scenes))
    t, e = table.column("acquisition_time_per_frame_s"), table.column("p95_error_m")
    w = table.column("simulation_work_per_frame")
    for j, scene in enumerate(scenes):
        mine = ok & (table.column("scene") == scene)
        ax = grid[0, j]
        pts = mine & exact
        ax.scatter(t[pts & ~front], e[pts & ~front], s=18, color="0.6", label="configuration")
        f = np.flatnonzero(pts & front)
        f = f[np.argsort(t[f], kind="stable")]
        ax.plot(t[f], e[f], "o-", color="C3", label="Pareto front")
        for i in f:
            ax.annotate(_label(table.rows[i]), (t[i], e[i]), fontsize=6,
                        xytext=(4, 3), textcoords="offset points")
        _log_axes(ax, t[pts], e[pts])
        ax.set_xlabel("acquisition time per frame (s)")
        ax.set_ylabel("95th-percentile range error (m)")
        ax.set_title(f"{scene}: the instrument's trade")
        ax.grid(alpha=0.3, which="both")
        ax.legend(fontsize=8)
        ax = grid[1, j]
        has = mine & np.isfinite(dp)
        for level, colour in zip(FIDELITY_LEVELS, ("C0", "C1", "C2", "C4"), strict=False):
            sel = has & (table.column("fidelity") == level)
            ax.scatter(w[sel], np.abs(dp[sel]) + 1e-4, s=18, color=colour, label=level)
        m = has & modeller
        ax.scatter(w[m], np.abs(dp[m]) + 1e-4, s=60, facecolors="none", edgecolors="C3",
                   label="undominated at its configuration")
        _log_axes(ax, w[has], np.abs(dp[has]) + 1e-4)
        ax.set_xlabel("simulation work per frame (values computed)")
        ax.set_ylabel("|p95 error - exact's| + 0.1 mm (m)")
        ax.set_title(f"{scene}: the modeller's trade")
        ax.grid(alpha=0.3, which="both")
        ax.legend(fontsize=8)
    save_figure(fig, ctx.out / "pareto.png")


def _log_axes(ax: Any, x: np.ndarray, y: np.ndarray) -> None:
    """Log scales where there are positive values to show; a note where there are none."""
    if np.any((x > 0) & (y > 0) & np.isfinite(x) & np.isfinite(y)):
        ax.set_xscale("log")
        ax.set_yscale("log")
    else:
        ax.text(0.5, 0.5, "nothing to show", ha="center", transform=ax.transAxes)


def answers_markdown(table: Table, thresholds: tuple[float, ...] = ASK_THRESHOLDS_M,
                     min_valid: float = 0.95) -> str:
    """The table of :func:`ask` answers per scene and p95 threshold (Markdown)."""
    lines = ["| scene | p95 at most (m) | fastest configuration | acquisition s/frame | "
             "p95 error (m) | valid | runner-up |", "|---|---|---|---|---|---|---|"]
    for scene in dict.fromkeys(table.column("scene")):
        for thr in thresholds:
            a = ask(table, thr, scene=scene, min_valid=min_valid)
            if a.best is None:
                lines.append(f"| {scene} | {thr:g} | none meets it | | | | |")
                continue
            b = a.best
            runner = a.runner_up["setting"] if a.runner_up else "none"
            lines.append(f"| {scene} | {thr:g} | {b['setting']} | "
                         f"{b['acquisition_time_per_frame_s']:.4g} | {_interval(b, 'p95_error_m')}"
                         f" | {_interval(b, 'valid_fraction')} | {runner} |")
    return "\n".join(lines) + "\n"


def results_markdown(table: Table) -> str:
    """Every row: setting, acquisition time, ADC rate, simulation work, errors with their
    95 % half-widths, valid fraction, false pixels and the two fronts (Markdown)."""
    lines = ["| scene | setting | acquisition ms/frame | ADC MS/s | work (Mvalues) | "
             "median error (m) | p95 error (m) | valid | false px | front | modeller |",
             "|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in table.rows:
        if r["status"] != "ok":
            lines.append(f"| {r['scene']} | {r['setting']} | refused: {r['reason']} "
                         "| | | | | | | | |")
            continue
        lines.append(
            f"| {r['scene']} | {r['setting']} | {1e3 * r['acquisition_time_per_frame_s']:.4g} | "
            f"{r['adc_rate_hz'] / 1e6:.4g} | {r['simulation_work_per_frame'] / 1e6:.4g} | "
            f"{_interval(r, 'median_error_m')} | {_interval(r, 'p95_error_m')} | "
            f"{_interval(r, 'valid_fraction')} | {r['false_pixels']:.3g} | "
            f"{'**yes**' if r['on_pareto_front'] else ''} | "
            f"{'yes' if r['on_modeller_front'] else ''} |")
    return "\n".join(lines) + "\n"


def _write_report(table: Table, front: np.ndarray, compared: np.ndarray,
                  ctx: RunContext) -> None:
    cols = ["scene", "setting", "acquisition_time_per_frame_s", "adc_rate_hz",
            "median_error_m", "p95_error_m", "valid_fraction", "false_pixels"]
    rows = [table.rows[i] for i in np.flatnonzero(front)]
    rows.sort(key=lambda r: (r["scene"], r["acquisition_time_per_frame_s"], r["p95_error_m"]))
    mcols = ["scene", "setting", "simulation_work_per_frame", "fidelity_p95_error_m",
             "fidelity_valid_error", "on_modeller_front"]
    mrows = [r for r, c in zip(table.rows, compared, strict=True) if c]
    text = ("# The speed/accuracy trade\n\n"
            "## Fastest configuration meeting a 95th-percentile error (valid fraction at "
            "least 0.95; `cdma-lidar study ask tradeoff DIR --max-p95 M`)\n\n"
            + answers_markdown(table)
            + "\n## The instrument's Pareto front: acquisition time per frame vs p95 error\n\n"
            f"Exact fidelity; points keeping at least {PARETO_MIN_VALID_SHARE:.0%} of their "
            "scene's best valid fraction; none is both faster and more accurate.\n\n"
            + Table(cols, [{c: r[c] for c in cols} for r in rows]).to_markdown()
            + "\n## The modeller's trade: simulation work vs fidelity error against exact\n\n"
            + Table(mcols, [{c: r[c] for c in mcols} for r in mrows]).to_markdown()
            + "\n## Every configuration\n\n" + results_markdown(table))
    (ctx.out / "pareto.md").write_text(text)


# ---------------------------------------------------------------------------------------
# asking a finished run


@dataclass(frozen=True)
class Answer:
    """The fastest configuration meeting the constraints (None: none does), the next one."""

    scene: str
    max_p95_m: float
    min_valid: float
    best: dict[str, Any] | None
    runner_up: dict[str, Any] | None
    candidates: int

    def describe(self) -> str:
        """A few lines for a terminal."""
        head = (f"{self.scene}: p95 error <= {self.max_p95_m:g} m, valid fraction >= "
                f"{self.min_valid:g}")
        if self.best is None:
            return f"{head}: no configuration meets it\n"
        lines = [f"{head}: {self.candidates} configurations meet it"]
        for name, row in (("fastest", self.best), ("runner-up", self.runner_up)):
            if row is None:
                lines.append(f"  {name}: none")
                continue
            lines.append(
                f"  {name}: {row['setting']}: acquisition {row['acquisition_time_per_frame_s']:.4g}"
                f" s/frame, ADC {row['adc_rate_hz'] / 1e6:.4g} MS/s, p95 "
                f"{_interval(row, 'p95_error_m')} m, median {_interval(row, 'median_error_m')} m,"
                f" valid {_interval(row, 'valid_fraction')}")
        return "\n".join(lines) + "\n"


def _interval(row: dict, col: str) -> str:
    """``value`` or ``value ± half-width`` (95 % over the replicate frames)."""
    v = row[col]
    ci = row.get(f"{col}_ci95")
    if ci is None or not isinstance(ci, int | float) or not math.isfinite(ci):
        return f"{v:.3g}"
    return f"{v:.3g} ± {ci:.2g}"


def _load(results: Table | str | os.PathLike[str]) -> Table:
    if isinstance(results, Table):
        return results
    path = Path(results)
    csv_path = path / "results.csv" if path.is_dir() else path
    if not csv_path.is_file():
        raise ConfigError(f"DIR {str(path)!r}: no results.csv there; give the --out folder of "
                          "a finished 'study run tradeoff'", "dir")
    table = read_csv(csv_path)
    need = ("scene", "fidelity", "status", "acquisition_time_per_frame_s", "p95_error_m",
            "valid_fraction")
    missing = [c for c in need if c not in table.columns]
    if missing:
        raise ConfigError(f"DIR {str(path)!r}: results.csv is not a tradeoff table (no "
                          f"{', '.join(missing)}); rerun 'study run tradeoff'", "dir")
    return table


def ask(results: Table | str | os.PathLike[str], max_p95_m: float, *, scene: str | None = None,
        min_valid: float = 0.95, max_adc_rate_hz: float | None = None) -> Answer:
    """The fastest configuration of a finished tradeoff run meeting the constraints.

    ``results``: the run's folder (or its results.csv, or the table). Among the rows at
    ``exact`` fidelity (the others are the modeller's trade) of ``scene`` (may be left
    out when the run has one scene) with status ok, p95 error at most ``max_p95_m``
    (m), valid fraction at least ``min_valid`` and ADC rate at most ``max_adc_rate_hz``:
    the least acquisition time per frame, ties broken by the lower p95 error, then the
    setting's label. Raises ConfigError for a bad folder or value.
    """
    if not (isinstance(max_p95_m, int | float) and math.isfinite(max_p95_m) and max_p95_m > 0):
        raise out_of_range("max_p95", "a positive number of metres", max_p95_m)
    if not (isinstance(min_valid, int | float) and 0 <= min_valid <= 1):
        raise out_of_range("min_valid", "0 to 1", min_valid)
    if max_adc_rate_hz is not None and not max_adc_rate_hz > 0:
        raise out_of_range("max_adc_rate", "a positive rate in Hz", max_adc_rate_hz)
    table = _load(results)
    scenes = list(dict.fromkeys(table.column("scene")))
    if scene is None:
        if len(scenes) != 1:
            raise ConfigError(f"--scene: the run has several scenes; give one of "
                              f"{', '.join(scenes)}", "scene")
        scene = scenes[0]
    elif scene not in scenes:
        raise ConfigError(f"--scene {scene!r}: not in this run; one of {', '.join(scenes)}",
                          "scene")
    rows = []
    for r in table.rows:
        if r["scene"] != scene or r["status"] != "ok" or r["fidelity"] != "exact":
            continue
        p95, valid = r["p95_error_m"], r["valid_fraction"]
        if not (isinstance(p95, int | float) and isinstance(valid, int | float)):
            continue
        if not (p95 <= max_p95_m and valid >= min_valid):
            continue
        if max_adc_rate_hz is not None and r["adc_rate_hz"] > max_adc_rate_hz:
            continue
        rows.append({**r, "setting": r.get("setting") or _label(r)})
    rows.sort(key=lambda r: (r["acquisition_time_per_frame_s"], r["p95_error_m"], r["setting"]))
    return Answer(scene, float(max_p95_m), float(min_valid), rows[0] if rows else None,
                  rows[1] if len(rows) > 1 else None, len(rows))


def _settings() -> tuple[Setting, ...]:
    return (
        Setting("scenes", SCENES, "scenes (presets, with options, or TOML files)",
                quick=SCENES[1:]),
        Setting("S", (1, 2, 4, 8, 16), "samples per chip, crossed with R", quick=(2, 8)),
        Setting("R", (1, 3, 10, 30, 100), "repetitions averaged, crossed with S and fidelity",
                quick=(1, 10)),
        Setting("degree", (9, 10, 11, 13, 15), "code degrees (one at a time)", quick=(10,)),
        Setting("chip_mhz", (31.25, 62.5, 125.0), "chip rates, MHz (one at a time)",
                quick=(125.0,)),
        Setting("K", (10, 20, 40), "channel counts (one at a time)", quick=(20,)),
        Setting("power_mw", (1.25, 2.5, 5.0), "laser power per channel, mW (one at a time)",
                quick=(5.0,)),
        Setting("near_far", (0, 2), "near-far closed-loop frames before the measured one "
                "(0: uniform power; one at a time)", quick=(2,)),
        Setting("adc_bits", (8, 10, 12, 14, 16), "ADC bits (one at a time)", quick=(8,)),
        Setting("gate", (64, 128, 256, 1024), "minimum gate lags (one at a time)",
                quick=(64,)),
        Setting("method", METHODS, "sub-sample refinement (one at a time)", quick=("none",)),
        Setting("fidelity", FIDELITY_LEVELS, "simulation fidelity levels, crossed with R"),
        Setting("replicates", 3, "independent frames per configuration", quick=2),
    )


STUDY = Study(
    name="tradeoff",
    description="acquisition time vs range accuracy (the instrument's trade) and simulation "
                "work vs fidelity error (the modeller's) over S, R, degree, chip rate, K, "
                "power, ADC bits, gate, sub-sample method and fidelity; Pareto fronts; "
                "'study ask tradeoff' queries a finished run",
    grid=_grid,
    task=tradeoff_task,
    reduce=_reduce,
    settings=_settings(),
    machine_columns=MACHINE_COLUMNS,
    version="3",  # 3: deterministic axes (acquisition time, simulation work), new axes
)
