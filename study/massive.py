"""The ``massive`` study: Fig. 11's order-15 capacity checked on the instrument (issue 40).

Shen, Lim and Zhou, "Identity-enabled CDMA LiDAR for massively parallel ranging with a
single-element receiver", Supp. Note 8 puts more than 1,200 workable channels on one
photodiode with an order-15 Gold family; ``fig11`` reproduces that as a Monte-Carlo of
multiple-access interference. Here the instrument itself ranges: ``paper-massive`` (Gold
degree 15, S = 2, R = 1, 1530-1605 nm) at K channels looks at a flat wall at
``distance_m`` (the preset's objects replaced by one plane), every column is rendered and
received by :func:`cdma_lidar.study.simulate.simulate_frame` (the device's receive chain,
its own gate), and each pixel's peak is ranged with the true calibration and no SNR
threshold.

A pixel is *wrongly ranged* when its peak lies more than half a chip (S/2 samples, 1.2 m
at 62.5 Mchip/s) from the truth or it has no peak: ``fig11``'s error. The prediction is
``fig11``'s standard Gaussian approximation (:func:`cdma_lidar.study.mai.sga_error_rate`)
at the same K, order and SNR: eq. 43 per pixel with that pixel's echo amplitude A_k, the
column's other echoes (2/3 of sum_j A_j^2) and the instrument's noise (sigma^2 / (S R)),
averaged over the pixels, with the competitors the device's search has: every lag of its
gate outside the peak's +-1 chip (it searches its gate, not the whole period as ``fig11``
does). ``fig11`` counts one competitor per chip, right at its S = 50, where a chip's lags
move together; at S = 2 neighbouring lags are only half correlated, so the independent
competitors lie between one per chip and one per lag, nearer the latter (a
noise-dominated wall at K = 40 measured 0.61, 0.81 and 0.93 wrong where one per lag
predicts 0.54, 0.80 and 0.91 and one per chip 0.45, 0.73 and 0.87; tests/study). Both
are given; the two agree when the per-lag prediction lies in the measured fraction's
95 % Wilson interval.

The wall is received by the paper's receiver whatever the preset says
(``instrument.cancel_rounds=0``: ``fig11`` models a single correlation, so the check of
its prediction runs one), and it isolates multiple access: every echo has about the same
power. ``paper-massive``'s own scene (letters at 5 m, a box at 6.5 m, a ball at 8 m, the
wall at 10 m behind: a 1/r^2 spread of echo powers, the near-far problem) is ranged too,
at the same K over ``scene_columns`` columns spread over its field (``--quick``: 4): the
share of its pixels whose peak lies at the right range (half a chip) whatever its SNR_XC,
and the share a scan keeps at the host's default threshold
(:func:`cdma_lidar.host.ranging.default_snr_threshold_db` with its neighbour support, the
boot power, no near-far control). A scan of the preset is to keep 90 % of its pixels. The
scene runs twice: with the preset's own receive chain (its interference cancellation,
``cancel_rounds`` rounds: assumed, not the paper's) and with one correlation, the
paper's receiver (the columns and entries ending in ``_single``).

Columns: ``wrong_fraction``, ``wrong_pixels``, ``pixels``, ``predicted_fraction`` (one
competitor per lag), ``predicted_per_chip`` (``fig11``'s count over the gate),
``predicted_whole_period`` (``fig11``'s own competitor count, N - 3: what a gate over the
whole period would give), ``snr_ss_median_db`` (eq. 43, median pixel), ``gate_lags``,
``rejected_fraction`` (pixels a scan would reject at the host's default SNR_XC
threshold); of the scene: ``scene_pixels`` (pixels with an echo), ``scene_right_pixels``
(peak within half a chip of the truth, no threshold), ``scene_valid_pixels`` (kept at the
default threshold), ``scene_valid_wrong_pixels`` (kept, yet off by more than half a chip),
``threshold_db`` (that threshold); ``scene_wall_pixels``, ``scene_wall_right_pixels`` and
``scene_wall_valid_pixels`` (the same for the back wall's pixels alone);
``scene_equalised_right_pixels`` and ``scene_equalised_valid_pixels`` (again, with every
echo above the median echo amplitude lowered to it by its pixel's laser power: the most a
near-far control that lowers near pixels can equalise); ``scene_cancel_rounds`` (the
rounds of interference cancellation the preset's chain ran them with) and every
``scene_*_pixels`` again with one correlation (``scene_*_pixels_single``); and, measuring
the machine, ``time_s``. The report adds ``wall_valid_fraction_k*`` (the flat wall's
pixels kept: where every echo is alike, what the threshold alone costs against multiple
access).

The full run (K = 400, 800, 1,200 x 160 columns of the wall and of the scene, 768,000
pixels) is 27 to 80 times the columns of ``--quick`` (2 of the wall and 4 of the scene per
K); the wall's 2 columns per K took 22 CPU seconds on the shared 2-core machine (3 minutes
of wall time at a load of 14), so the full run is about half an hour to an hour of CPU,
most of it the 1,200-channel columns' receive chain (``python -m bench massive``), more
with the scene's cancellation (each round correlates again).
"""

from __future__ import annotations

import dataclasses
import logging
import math
import time
import urllib.parse
from typing import Any

import numpy as np

from cdma_lidar.checks import check_int
from cdma_lidar.errors import out_of_range
from cdma_lidar.host.ranging import estimate_ranges, mai_ceiling_db
from cdma_lidar.scene import load_scene
from cdma_lidar.scene.instrument import Instrument
from cdma_lidar.study.engine import RunContext, Setting, Study, Table, grid_product
from cdma_lidar.study.figures import new_figure, save_figure
from cdma_lidar.study.mai import sga_error_rate, snr_ss_eq43
from cdma_lidar.study.paperlab import entry, wilson
from cdma_lidar.study.simulate import SimulatedScan, device_power_w, simulate_frame
from cdma_lidar.units import SPEED_OF_LIGHT_M_S

__all__ = ["REPORT_NOTE", "STUDY", "flat_wall_scene", "massive_task", "predicted_error",
           "scene_shares"]

log = logging.getLogger(__name__)

#: The preset whose instrument is checked.
PRESET = "paper-massive"

#: The paper report's paragraph for this study (:func:`cdma_lidar.study.paper.write_report`).
REPORT_NOTE = (
    "The instrument-level check of Fig. 11's order-15 capacity: paper-massive (Gold degree "
    "15, S = 2, R = 1) renders, receives and ranges a flat wall at K = 400, 800 and 1200 "
    "through the device's own receive chain and gate, and the share of wrongly ranged "
    "pixels (a peak more than half a chip off, or none) is compared with fig11's Gaussian "
    "approximation at the same K, order and SNR, counting the gate's lags as the "
    "competitors. The row is reproduced when that prediction lies in the measured share's "
    "95 % interval at every K; the wall is received by one correlation, the paper's "
    "receiver, as fig11 models it. The `scene_*` quantities range paper-massive's own scene "
    "(objects at 5-10 m before a wall at 10 m) at the same K with the preset's receive "
    "chain, which cancels the echoes it found and correlates again (an assumption, not the "
    "paper's receiver), and, in the entries ending in `_single`, with one correlation: the "
    "share of peaks at the "
    "right range whatever their SNR_XC, and the share a scan keeps at the host's default "
    "threshold with the boot power and no near-far control; a scan of the preset is to "
    "keep 90 %, and the gap between the two shares is what near-far control and the "
    "threshold have to close. The scene's shares are also given for the back wall alone, for "
    "the objects before it, and with every echo above the median lowered to it (the most a "
    "near-far control that lowers near pixels could equalise); the flat wall's kept share "
    "is what the threshold costs where every echo is alike.")


#: The pixel counts of :func:`scene_shares` (each given again with one correlation, ``_single``).
SCENE_COUNTS = ("scene_pixels", "scene_right_pixels", "scene_valid_pixels",
                "scene_valid_wrong_pixels", "scene_wall_pixels", "scene_wall_right_pixels",
                "scene_wall_valid_pixels", "scene_equalised_right_pixels",
                "scene_equalised_valid_pixels")


def flat_wall_scene(channels: int, columns: int, distance_m: float,
                    snr_db: float | None = None) -> str:
    """``paper-massive`` at K ``channels`` and ``columns``, facing one flat wall, received
    by the paper's receiver (one correlation: ``instrument.cancel_rounds=0``, as ``fig11``
    models it), a scene name for :func:`~cdma_lidar.study.simulate.simulate_frame`;
    ``snr_db`` replaces the link budget's noise (per-sample SNR of the median echo, dB)."""
    wall = (f'[{{kind = "plane", name = "wall", position_m = [{distance_m!r}, 0.0, 0.0], '
            'size_m = [40.0, 40.0], reflectivity = 0.5}]')
    options: dict[str, Any] = {"channels": channels, "columns": columns, "objects": wall,
                               "instrument.cancel_rounds": 0}
    if snr_db is not None:
        options["instrument.snr_db"] = snr_db
    return f"{PRESET}?{urllib.parse.urlencode(options)}"


def predicted_error(inst: Instrument, competitors: int) -> tuple[float, float]:
    """(fraction of pixels fig11's SGA predicts wrong, median eq. 43 SNR in dB).

    Eq. 43 per lit pixel (k, c): ``N A_k^2 / (sigma^2 / (S R) + 2/3 sum_{j != k} A_j^2)``
    with the column's echo amplitudes A (V) and the instrument's noise rms sigma (V per
    sample), against ``competitors`` independent lags; a pixel without an echo is wrong.
    """
    spec = inst.spec
    s, r = spec.samples_per_chip, spec.averages
    amp = inst.gain_v_per_w * inst.default_power_w            # (K, C) V
    lit = amp > 0
    a2 = np.where(lit, amp, 0.0) ** 2
    others = a2.sum(axis=0, keepdims=True) - a2
    with np.errstate(divide="ignore", invalid="ignore"):
        # eq. 43 with every other channel's power relative to this one's
        ratio = np.where(lit, others / np.where(lit, a2, 1.0), np.inf)
        noise = np.where(lit, inst.noise_rms_v / np.where(lit, amp, 1.0), np.inf)
    snr = np.array([snr_ss_eq43(spec.code_length, 1.0 + q, float(z), 1.0, s, r)
                    for q, z in zip(ratio[lit], noise[lit], strict=True)])
    # the error rate of each distinct SNR (to 0.01 dB) once: the pixels of a wall are alike
    snr_db = np.round(10 * np.log10(snr), 2)
    values, counts = np.unique(snr_db, return_counts=True)
    rates = np.array([sga_error_rate(10 ** (v / 10), competitors) for v in values])
    unlit = int(np.count_nonzero(~lit))   # no echo: always wrong
    frac = (float(np.sum(rates * counts)) + unlit) / lit.size
    return frac, float(np.median(snr_db)) if snr_db.size else math.nan


def _grid(options: Any) -> list[dict]:
    chans = [check_int("channels", k, 2, 2048) for k in options["channels"]]
    if not chans:
        raise out_of_range("channels", "at least one channel count", "none")
    cols = check_int("columns", options["columns"], 1, 160)
    scene = check_int("scene_columns", options["scene_columns"], 0, 160)
    d = float(options["distance_m"])
    if not 1.0 <= d <= 50.0:
        raise out_of_range("distance_m", "from 1 to 50 m", d)
    text = str(options["snr_db"]).strip()
    try:
        snr = None if text == "" else float(text)
    except ValueError:
        snr = math.nan
    if snr is not None and not -80.0 <= snr <= 120.0:   # (nan fails the comparison too)
        raise out_of_range("snr_db", "empty (the link budget) or a number from -80 to 120 dB",
                           text)
    return grid_product(channels=chans, columns=[cols], distance_m=[d], snr_db=[snr],
                        scene_columns=[scene])


def scene_shares(channels: int, columns: int, seed: int, single: bool = False
                 ) -> dict[str, Any]:
    """``paper-massive``'s own scene at K ``channels`` over ``columns`` columns (spread over
    its azimuth), received by the preset's chain (``single``: by one correlation, the
    paper's receiver, whatever the preset's ``cancel_rounds``): pixels with an echo,
    those whose peak is within half a chip of the truth at no threshold, those a scan
    keeps at the host's default threshold (its SNR_XC threshold and neighbour support,
    the boot power), and those kept yet wrong; the same
    counts for the pixels on the back wall (the scene's planes) alone; and, with every echo
    above the median echo amplitude lowered to it (each pixel's laser power scaled down by
    its amplitude over the median: the most a near-far control that lowers near pixels
    can equalise, knowing the truth), the right and kept pixels again; and the rounds of
    cancellation the chain ran (``scene_cancel_rounds``)."""
    name = f"{PRESET}?channels={channels}&columns={columns}" + (
        "&instrument.cancel_rounds=0" if single else "")
    sim = simulate_frame(name, seed=seed)
    right, valid, threshold = _ranged(sim)
    lit = np.isfinite(sim.truth_range_m)
    inst = Instrument(load_scene(name), seed=seed)
    planes = [i for i, o in enumerate(inst.scene.objects) if o.kind == "plane"]
    wall = lit & np.isin(inst.truth.hits.object_id, planes)
    amp = inst.gain_v_per_w * inst.default_power_w                          # (K, C) V
    top = float(np.median(amp[lit])) if lit.any() else 0.0
    with np.errstate(divide="ignore", invalid="ignore"):
        scale = np.where(amp > top, top / amp, 1.0)
    even = simulate_frame(name, seed=seed, power_w=device_power_w(inst) * scale)
    even_right, even_valid, _ = _ranged(even)
    return {"scene_pixels": int(lit.sum()), "scene_right_pixels": int(np.sum(right & lit)),
            "scene_valid_pixels": int(np.sum(valid & lit)),
            "scene_valid_wrong_pixels": int(np.sum(valid & lit & ~right)),
            "scene_wall_pixels": int(wall.sum()),
            "scene_wall_right_pixels": int(np.sum(right & wall)),
            "scene_wall_valid_pixels": int(np.sum(valid & wall)),
            "scene_equalised_right_pixels": int(np.sum(even_right & lit)),
            "scene_equalised_valid_pixels": int(np.sum(even_valid & lit)),
            "scene_cancel_rounds": inst.spec.cancel_rounds, "threshold_db": threshold}


def _ranged(sim: SimulatedScan) -> tuple[np.ndarray, np.ndarray, float]:
    """(peak within half a chip of the truth at no threshold, kept by the host's default
    ranging, that ranging's threshold in dB), both with the true calibration."""
    ranging = dataclasses.replace(sim.ranging, offset_m=sim.true_offset_m)
    image = estimate_ranges(sim.frame, dataclasses.replace(ranging, snr_threshold_db=0.0,
                                                           min_support=0))
    half_chip_m = SPEED_OF_LIGHT_M_S / (4 * sim.ranging.chip_rate_hz)
    with np.errstate(invalid="ignore"):
        right = np.abs(image.range_m - sim.truth_range_m) <= half_chip_m
    return right, estimate_ranges(sim.frame, ranging).valid, ranging.snr_threshold_db


def massive_task(params: dict, seed: np.random.SeedSequence) -> dict[str, Any]:
    """One K: render, receive and range the flat wall; count the wrongly ranged pixels;
    then the preset's own scene (:func:`scene_shares`) when ``scene_columns`` > 0."""
    k, cols = int(params["channels"]), int(params["columns"])
    snr = params.get("snr_db")
    name = flat_wall_scene(k, cols, float(params["distance_m"]),
                           None if snr is None else float(snr))
    t0 = time.perf_counter()
    wall_seed, scene_seed = (int(v) for v in seed.generate_state(2))
    sim = simulate_frame(name, seed=wall_seed)
    inst = Instrument(load_scene(name), seed=0)
    gate_lags = inst.default_gate()[1]
    spec = inst.spec
    right, valid, threshold = _ranged(sim)
    s = spec.samples_per_chip
    predicted, snr_median = predicted_error(inst, max(gate_lags - 2 * s - 1, 1))
    per_chip, _ = predicted_error(inst, max(gate_lags // s - 3, 1))
    whole, _ = predicted_error(inst, spec.code_length - 3)
    scene_columns = int(params.get("scene_columns", 0))
    scene: dict[str, Any] = dict.fromkeys((*SCENE_COUNTS, "scene_cancel_rounds"), 0)
    if scene_columns:   # the preset's chain, then the paper's (the same seed: the same light)
        scene = scene_shares(k, scene_columns, scene_seed)
        single = scene_shares(k, scene_columns, scene_seed, single=True)
    else:
        single = dict.fromkeys(SCENE_COUNTS, 0)
    scene.update({f"{key}_single": single[key] for key in SCENE_COUNTS})
    scene.setdefault("threshold_db", threshold)
    return {"wrong_fraction": float(np.mean(~right)), "wrong_pixels": int(np.sum(~right)),
            "pixels": int(right.size), "predicted_fraction": predicted,
            "predicted_per_chip": per_chip,
            "predicted_whole_period": whole, "snr_ss_median_db": snr_median,
            "gate_lags": int(gate_lags), "rejected_fraction": float(np.mean(~valid)),
            **scene, "time_s": time.perf_counter() - t0}


def _reduce(table: Table, ctx: RunContext) -> dict[str, Any]:
    k = table.column("channels")
    wrong, pixels = table.column("wrong_pixels"), table.column("pixels")
    pred, whole = table.column("predicted_fraction"), table.column("predicted_whole_period")
    frac = wrong / pixels
    cis = [wilson(int(w), int(n)) for w, n in zip(wrong, pixels, strict=True)]
    agree = [lo <= p <= hi for (lo, hi), p in zip(cis, pred, strict=True)]
    table.add_column("ci95_low", [c[0] for c in cis])
    table.add_column("ci95_high", [c[1] for c in cis])
    table.add_column("agrees_with_fig11", [int(a) for a in agree])
    fig, ax = new_figure(6, 4)
    o = np.argsort(k)
    lo, hi = table.column("ci95_low")[o], table.column("ci95_high")[o]
    ax.errorbar(k[o], frac[o], yerr=[frac[o] - lo, hi - frac[o]], fmt="o", color="k",
                capsize=3, label="instrument: wrongly ranged pixels (95 %)")
    ax.plot(k[o], pred[o], "s--", color="tab:red",
            label="fig11's SGA, the device's gate (a competitor per lag)")
    ax.plot(k[o], table.column("predicted_per_chip")[o], "^:", color="tab:orange",
            label="fig11's SGA, the device's gate (a competitor per chip)")
    ax.plot(k[o], whole[o], ":", color="tab:gray", label="fig11's SGA, a whole-period search")
    scene = table.column("scene_pixels")[o] > 0
    if scene.any():
        n = table.column("scene_pixels")[o][scene]
        for key, mark, color, label in (
                ("right", "v", "tab:blue", "scene: peak not at the right range"),
                ("valid", "x", "tab:blue", "scene: not kept at the default threshold"),
                ("equalised_valid", "+", "tab:blue", "scene, echoes equalised: not kept"),
                ("valid_pixels_single", "x", "tab:green",
                 "scene, one correlation (the paper's receiver): not kept")):
            column = key if key.endswith("single") else f"{key}_pixels"
            ax.plot(k[o][scene], 1 - table.column(f"scene_{column}")[o][scene] / n, mark,
                    color=color, label=label)
    ax.set_xlabel("channels K (order 15, S = 2)")
    ax.set_ylabel("fraction of pixels")
    ax.set_yscale("symlog", linthresh=1e-4)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7)
    save_figure(fig, ctx.out / "massive.png")
    out: dict[str, Any] = {}
    for i in np.argsort(k):
        kk = k[i]
        out[f"wrong_fraction_k{int(kk)}"] = entry(
            float(frac[i]), None, "1", ci95=cis[i],
            verdict="agrees" if agree[i] else "disagrees",
            cause=f"fig11's SGA at K = {int(kk)}, order 15, this SNR and gate: "
                  f"{pred[i]:.3g} ({'inside' if agree[i] else 'outside'} the 95 % interval "
                  f"of {int(wrong[i])} of {int(pixels[i])} pixels); one competitor per chip: "
                  f"{table.column('predicted_per_chip')[i]:.3g}; a whole-period search: "
                  f"{whole[i]:.3g}")
    o = np.argsort(k)
    out["agreeing_channel_counts"] = entry(
        int(sum(agree)), None, "of " + str(len(agree)), paper_point=int(sum(agree)),
        exact=True, cause="fig11's prediction inside the 95 % interval of the wrongly "
        "ranged pixels at K = " + ", ".join(
            f"{int(k[i])} ({int(wrong[i])} of {int(pixels[i])} wrong, {pred[i]:.2g} "
            "predicted)" for i in o if agree[i]) + "; outside at K = "
        + (", ".join(str(int(k[i])) for i in o if not agree[i]) or "none"))
    rejected = table.column("rejected_fraction")
    chips = 2 ** load_scene(PRESET).instrument.code_degree - 1   # N of the preset's codes
    for i in np.argsort(k):
        kk = int(k[i])
        out[f"wall_valid_fraction_k{kk}"] = entry(
            float(1 - rejected[i]), None, "1", verdict=None,
            cause=f"the flat wall's pixels kept at the host's default "
                  f"{float(table.column('threshold_db')[i]):.1f} dB at K = {kk}: every echo "
                  f"alike, so what the threshold costs where multiple access alone limits "
                  f"SNR_XC (ceiling {mai_ceiling_db(kk, chips):.1f} dB)")
        thr = float(table.column("threshold_db")[i])
        rounds = int(table.column("scene_cancel_rounds")[i])
        for tail, chain in (("", f"the preset's receive chain ({rounds} rounds of "
                             "interference cancellation)"),
                            ("_single", "one correlation (the paper's receiver)")):
            counts = {key: int(table.column(f"{key}{tail}")[i]) for key in SCENE_COUNTS}
            n, nw = counts["scene_pixels"], counts["scene_wall_pixels"]
            valid, wall_valid = counts["scene_valid_pixels"], counts["scene_wall_valid_pixels"]
            for key, what, hits, of in (
                    ("right", "peaks within half a chip of the truth at no threshold",
                     counts["scene_right_pixels"], n),
                    ("valid", f"pixels kept at the host's default {thr:.1f} dB", valid, n),
                    ("wall_valid", f"pixels of the back wall (10 m) kept at {thr:.1f} dB",
                     wall_valid, nw),
                    ("objects_valid", f"pixels of the objects before the wall kept at "
                     f"{thr:.1f} dB", valid - wall_valid, n - nw),
                    ("equalised_right", "peaks at the right range with every echo above the "
                     "median lowered to it (the most a near-far control could equalise)",
                     counts["scene_equalised_right_pixels"], n),
                    ("equalised_valid", f"pixels kept at {thr:.1f} dB with every echo above "
                     "the median lowered to it", counts["scene_equalised_valid_pixels"], n)):
                if not of:
                    continue
                out[f"scene_{key}_fraction_k{kk}{tail}"] = entry(
                    hits / of, None, "1", ci95=wilson(hits, of), verdict=None,
                    cause=f"paper-massive's scene (5-10 m) at K = {kk}, {chain}: {hits} of "
                          f"{of} {what}"
                          + (f" ({counts['scene_valid_wrong_pixels']} of them off by more "
                             "than half a chip); a scan is to keep 90 %"
                             if key == "valid" else ""))
    return out


STUDY = Study(
    name="massive",
    description="Fig. 11's order-15 capacity on the instrument: wrongly ranged pixels of a flat "
                "wall at K = 400, 800, 1200 (paper-massive) vs fig11's prediction",
    grid=_grid,
    task=massive_task,
    reduce=_reduce,
    settings=(
        Setting("channels", (400, 800, 1200), "channel counts K (2..2048) over paper-massive's "
                "band"),
        Setting("columns", 160, "columns of the wall per K (1..160)", quick=2),
        Setting("distance_m", 8.0, "distance of the flat wall (m, 1..50)"),
        Setting("snr_db", "", "per-sample SNR of the median echo (dB) replacing the link "
                "budget's noise; empty: the link budget's"),
        Setting("scene_columns", 160, "columns of paper-massive's own scene per K (0..160; "
                "0: the wall only)", quick=4),
    ),
    machine_columns=("time_s",),
)
