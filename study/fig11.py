"""The ``fig11`` study: channel capacity at 10 % ranging error (paper Supp. Note 8, Fig. 11).

K channels of equal power share one detector, each a Gold code of degree m (N = 2^m - 1
chips, members 0..K-1 of the first preferred pair) sampled S = 50 times per chip and
delayed by a random whole number of samples (uniform over the period, so the channels are
asynchronous at 1/50 chip); no other noise (the paper's set-up). Each trial draws new
delays, builds the ADC samples (:mod:`cdma_lidar.study.mai`), runs them through the whole
receive chain (:class:`~cdma_lidar.firmware_model.receiver.FastReceiver`, ``method="auto"``,
gate over the whole period) and ranges channel 0. An error is a peak lag more than half a
chip (S/2 samples) from the true delay. ``trials`` = 1000 random delays per point as in the
paper, at most: a point whose first 64, 128, 256, ... trials already put both detectors'
error rates clearly on one side of 10 % stops there (:func:`decided`; ``trials_run``
gives the count), so only the points that bracket the capacity run all 1000. ``--quick``
runs up to 256 trials on grids that bracket the paper's bounds with points far enough
from 10 % to be decided in that many trials (order 13: 352, 448, 544 around 400; order
15: 1200, where eq. 9's error rate is about 4 %, and 1800, about 20 %).

Columns: ``trials_run``, ``error_rate`` (fraction of trials; the simulation, or the SGA with
``fidelity=sga``), ``error_rate_sga`` (standard Gaussian approximation, always computed:
the deviation of the shortcut is in every table), ``snr_xc_median_db`` / ``_q1_db`` /
``_q3_db`` (SNR_XC of eq. 44 as the receiver reports it: median and quartiles, the
paper's red dots and IQR band), ``snr_ss_eq43_db`` (eq. 43 for this K and N),
``snr_eq30_db`` (eq. 30, the raw per-sample SNR), ``time_per_trial_s`` (machine).

Workable channels = the K where the error rate crosses 10 % (linear interpolation between
grid points; the largest K tried when it never does, marked in the log and figure), with a
95 % interval that counts the trials' noise and the grid's step
(:func:`cdma_lidar.study.paperlab.crossing_ci`). The grid is refined where the verdict is
read (:func:`refine_points`): while eq. 9's capacity interval of an order has no grid point
inside it (the grid's step, not the trials, sets its width), its midpoint is run, at most
``refine_rounds`` times, each round into ``OUT/fig11-refined-<round>/``; the summary and
figure read the capacities off every point run.

Detector (``detector`` setting; ``point=paper`` picks ``signed``): every trial is judged by
the receiver's largest |corr| (``error_rate``) and by eq. 9's signed maximum
(``error_rate_signed``); the headline uses one, its ``paper_point`` always eq. 9's, and its
``cause`` gives both. The paper prints lower bounds ("roughly more than 125, 400, and
1200"), kept as printed (``"> 125"``).
"""

from __future__ import annotations

import dataclasses
import logging
import math
from typing import Any

import numpy as np

from cdma_lidar.checks import check_int
from cdma_lidar.errors import out_of_range
from cdma_lidar.study.engine import (
    RunContext,
    RunOptions,
    Setting,
    Study,
    Table,
    TrialChunk,
    Trials,
)
from cdma_lidar.study.figures import new_figure, save_figure
from cdma_lidar.study.mai import (
    DETECTORS,
    code_bits,
    run_trial_blocks,
    sga_error_rate,
    snr_per_sample_eq30,
    snr_ss_eq43,
)
from cdma_lidar.study.paperlab import check_point, crossing_ci, entry, wilson

__all__ = ["FIDELITIES", "REPORT_NOTE", "STUDY", "TRIALS", "crossing", "detector_for",
           "fig11_row", "fig11_trials", "refine_points"]

log = logging.getLogger(__name__)

#: ``full``: the whole receive chain on simulated samples; ``sga``: the standard Gaussian
#: approximation only (eq. 43 and independent chip-spaced competitors), seconds not hours.
FIDELITIES = ("full", "sga")

#: Error rate defining a workable configuration (the paper's 10 % benchmark).
ERROR_THRESHOLD = 0.10

#: Paper, Supp. Note 8 text under Fig. 11: "workable channel numbers for orders 11, 13
#: and 15 are roughly more than 125, 400, and 1200" (printed as lower bounds).
PAPER_CHANNELS = {11: 125, 13: 400, 15: 1200}
#: Paper, Supp. Note 8: "cut-off SNR_XC of approximately 32.5 dB for the 11th-order".
PAPER_SNR_XC_THRESHOLD_DB = 32.5

REPORT_NOTE = (
    "Channel capacity comes from the whole receive chain on 50-samples-per-chip signals with "
    "random delays, as in the paper, and every trial is judged by two peak detectors: eq. 9's "
    "signed maximum of the correlation (the paper's, used at the paper's point) and the "
    "receiver's largest |corr| (the toolkit's default: a UID bit of 1 flips the code, so "
    "the receiver must accept a negative peak, which doubles the lags that can beat the "
    "true one). The `cause` column gives both capacities from the same trials; the "
    "difference between them is the detector, not the simulation. The 95 % interval counts "
    "the trials' noise and the grid's step (the crossing lies between the largest K whose "
    "Wilson interval is wholly below 10 % and the smallest wholly above it), and the grid "
    "is refined where the paper's row is judged: while eq. 9's interval of an order has no "
    "grid point inside it, its midpoint is run (up to `refine_rounds` times; those points "
    "are in `fig11-refined-<round>/` and in the figure), so the trials, not the grid's "
    "step, set its width. A point whose "
    "first trials already lie clearly on one side of 10 % for both detectors (a stricter "
    "interval, corrected for the repeated looks) stops there: `trials_run` gives each "
    "point's count, and the interval keeps its 95 % coverage. The paper "
    "prints lower bounds ('roughly more than'): a capacity is reproduced when its 95 % "
    "lower bound is at least the printed number, consistent when its interval holds it, "
    "and differs when its upper bound is below it. The standard Gaussian approximation "
    "(fidelity=sga) is shown beside the simulation for both detectors. The SNR_XC at 10 % "
    "error is eq. 44 as our receiver computes it (peak squared over the noise floor's "
    "variance); that the paper's 32.5 dB is on this scale is a hypothesis the paper does "
    "not let us test (it does not define its floor), and eq. 43 at the capacity is given "
    "as a derived quantity. An error is a peak more than half a chip from the truth (the "
    "paper does not define its error)."
)


def _grid(options: RunOptions) -> list[dict]:
    fidelity = options["fidelity"]
    if fidelity not in FIDELITIES:
        raise out_of_range("fidelity", "one of " + ", ".join(FIDELITIES), fidelity)
    s = check_int("S", options["S"], 1, 64)
    trials = check_int("trials", options["trials"], 1, 1_000_000)
    detector_for(options)  # refuses a bad detector or point before any task runs
    check_int("refine_rounds", options["refine_rounds"], 0, 10)
    points = []
    for degree in (11, 13, 15):
        n = (1 << degree) - 1
        for k in options[f"channels_order{degree}"]:
            check_int(f"channels_order{degree}", k, 2, n + 2)
            points.append({"degree": degree, "channels": int(k), "S": s, "trials": trials,
                           "fidelity": fidelity})
    if not points:
        raise out_of_range("channels_order11/13/15", "at least one channel count", "none")
    return points


def _count(params: dict) -> int:
    """Trials of one point: none for the Gaussian approximation."""
    return 0 if params["fidelity"] == "sga" else int(params["trials"])


def fig11_trials(params: dict, chunk: TrialChunk) -> dict[str, list]:
    """One chunk of a (degree, K)'s random-delay trials: gross error by the receiver's
    |corr| (``error``) and by eq. 9's signed maximum (``error_signed``), SNR_XC (dB) and
    the seconds of each trial (its block's time shared equally)."""
    degree, k, s = int(params["degree"]), int(params["channels"]), int(params["S"])
    return run_trial_blocks(code_bits(degree, k) if len(chunk) else None, s, chunk.blocks())


def fig11_row(params: dict, trials: dict[str, np.ndarray]) -> dict[str, Any]:
    """The point's columns from all its trials (or the SGA alone)."""
    degree, k = int(params["degree"]), int(params["channels"])
    n = (1 << degree) - 1
    ss = snr_ss_eq43(n, k)
    sga = sga_error_rate(ss, competitors=n - 3)
    sga_signed = sga_error_rate(ss, competitors=n - 3, detector="signed")
    row: dict[str, Any] = {
        "trials_run": 0 if params["fidelity"] == "sga" else len(trials["error"]),
        "snr_ss_eq43_db": 10 * math.log10(ss),
        "snr_eq30_db": 10 * math.log10(snr_per_sample_eq30(k, 0.0)),
        "error_rate_sga": sga,
        "error_rate_sga_signed": sga_signed,
    }
    if params["fidelity"] == "sga":
        row.update(error_rate=sga, error_rate_signed=sga_signed,
                   snr_xc_median_db=row["snr_ss_eq43_db"],
                   snr_xc_q1_db=math.nan, snr_xc_q3_db=math.nan, time_per_trial_s=0.0)
        return row
    q1, med, q3 = np.percentile(trials["snr_xc_db"], [25, 50, 75])
    row.update(error_rate=float(np.mean(trials["error"])),
               error_rate_signed=float(np.mean(trials["error_signed"])),
               snr_xc_median_db=float(med),
               snr_xc_q1_db=float(q1), snr_xc_q3_db=float(q3),
               time_per_trial_s=float(np.mean(trials["seconds"])))
    return row


def decided(params: dict, trials: dict[str, np.ndarray]) -> bool:
    """Whether a point's first trials already put it on one side of the 10 % threshold.

    Asked by the engine at its looks (64, 128, 256, ... trials, :meth:`Trials.looks`):
    True when, for both detectors, the Wilson interval of the error rate lies wholly
    below or wholly above 10 % at the level ``1 - 0.025 / looks`` per side (Bonferroni
    over the interim looks: the chance that a stopped point sits on the wrong side stays
    under the 2.5 % per side of a fixed-size 95 % interval). A stopped point then has
    fewer trials (``trials_run``) and its 95 % interval still excludes 10 %, so the
    capacity's interval (:func:`~cdma_lidar.study.paperlab.crossing_ci`) is what the
    full count would bracket; only points that stay near 10 % run every trial.
    """
    from scipy.special import ndtri  # deferred: scipy costs 0.3 s at start-up

    interim = len(TRIALS.looks(int(params["trials"]))) - 1
    z = float(ndtri(1.0 - 0.025 / max(interim, 1)))
    for column in ("error", "error_signed"):
        n = len(trials[column])
        lo, hi = wilson(int(np.sum(trials[column])), n, z)
        if not (hi < ERROR_THRESHOLD or lo > ERROR_THRESHOLD):
            return False
    return True


#: How the engine runs a point: its trials in chunks (blocks of 8 with their own seeds),
#: stopped early once both detectors put it clearly on one side of 10 % (:func:`decided`).
TRIALS = Trials(count=_count, run=fig11_trials, summarise=fig11_row, stop=decided)


def crossing(x: np.ndarray, err: np.ndarray, y: np.ndarray | None = None,
             level: float = ERROR_THRESHOLD) -> tuple[float, bool]:
    """Where ``err`` (ordered by ``x``) first rises through ``level``: x there (or y there).

    Linear interpolation between the last point at or below ``level`` and the next above.
    Returns (value, reached): when no point is above the level, the last x (or y) and False;
    when the first point is already above, that point's value and True.
    """
    order = np.argsort(x)
    x, err = np.asarray(x, float)[order], np.asarray(err, float)[order]
    yy = x if y is None else np.asarray(y, float)[order]
    above = np.flatnonzero(err > level)
    if above.size == 0:
        return float(yy[-1]), False
    i = int(above[0])
    if i == 0:
        return float(yy[0]), True
    e0, e1 = err[i - 1], err[i]
    t = (level - e0) / (e1 - e0) if e1 != e0 else 0.0
    return float(yy[i - 1] + t * (yy[i] - yy[i - 1])), True


def detector_for(options: RunOptions) -> str:
    """The detector the headline ``ours`` uses: eq. 9's signed maximum at ``point=paper``."""
    check_point(options["point"])
    det = "signed" if options["point"] == "paper" else options["detector"]
    if det not in DETECTORS:
        raise out_of_range("detector", " or ".join(DETECTORS), det)
    return det


def _error_column(det: str, sga: bool = False) -> str:
    return ("error_rate_sga" if sga else "error_rate") + ("_signed" if det == "signed" else "")


def refine_points(table: Table) -> dict[int, list[int]]:
    """The channel counts a refining round adds, per degree: the midpoint of eq. 9's
    (signed detector's, the one the paper's row is judged by) 95 % capacity interval
    where that interval is bounded at both ends and no grid point lies strictly inside
    it, so the grid's step, not the trials, sets its width. Nothing for the Gaussian
    approximation (no interval) or an interval of adjacent integers."""
    out: dict[int, list[int]] = {}
    for d in sorted({int(x) for x in table.column("degree")}):
        t = table.where(degree=d)
        if str(t.rows[0]["fidelity"]) != "full":
            continue
        k = t.column("channels")
        lo, hi = crossing_ci(k, t.column(_error_column("signed")), t.column("trials_run"))
        if lo is None or hi is None or np.any((k > lo) & (k < hi)):
            continue
        mid = int(lo + hi) // 2
        if lo < mid < hi:
            out[d] = [mid]
    return out


def _refine(table: Table, ctx: RunContext) -> Table:
    """``table`` with the points of up to ``refine_rounds`` refining rounds
    (:func:`refine_points`), each run as a sub-study with this run's settings."""
    rows = list(table.rows)
    same = {k: ctx.options[k] for k in ("S", "trials", "fidelity", "detector", "point")}
    for i in range(1, int(ctx.options["refine_rounds"]) + 1):
        new = refine_points(Table(table.columns, rows))
        if not new:
            break
        log.info("fig11: refining round %d: %s", i, new)
        # the points alone: the capacities are read here, off every point run
        sub = dataclasses.replace(STUDY, name=f"{STUDY.name}-refined-{i}", reduce=None)
        res = ctx.run_sub(sub, {**same, "refine_rounds": 0,
                                **{f"channels_order{d}": tuple(new.get(d, ()))
                                   for d in (11, 13, 15)}})
        rows += res.table.rows
    return Table(table.columns, rows)


def _reduce(table: Table, ctx: RunContext) -> dict[str, Any]:
    det = detector_for(ctx.options)
    table = _refine(table, ctx)
    degrees = [d for d in (11, 13, 15) if len(table.where(degree=d))]
    fig, axes = new_figure(4.2 * len(degrees), 3.6, 1, len(degrees))
    axes = axes if isinstance(axes, list) else [axes]
    summary: dict[str, Any] = {}
    for ax, d in zip(axes, degrees, strict=True):
        t = table.where(degree=d)
        k = t.column("channels")
        trials = t.column("trials_run")
        full = str(t.rows[0]["fidelity"]) == "full"
        caps: dict[str, tuple[float, bool, tuple]] = {}
        for name in DETECTORS:
            err = t.column(_error_column(name))
            cap, reached = crossing(k, err)
            ci = crossing_ci(k, err, trials) if full else (cap, cap)
            caps[name] = (cap, reached, ci)
        cap, reached, ci = caps[det]
        err, sga = t.column(_error_column(det)), t.column(_error_column(det, sga=True))
        cap_sga, _ = crossing(k, sga)
        med = t.column("snr_xc_median_db")
        thr, _ = crossing(k, err, med)
        thr_signed, _ = crossing(k, t.column(_error_column("signed")), med)
        if not reached:
            log.warning("order %d: error rate stays below %g up to %d channels", d,
                        ERROR_THRESHOLD, int(k.max()))
        order = np.argsort(k)
        ax.fill_between(k[order], t.column("snr_xc_q1_db")[order],
                        t.column("snr_xc_q3_db")[order], color="tab:blue", alpha=0.25,
                        label="SNR_XC IQR")
        ax.plot(k[order], med[order], "o", color="tab:red", ms=4, label="SNR_XC median")
        ax.plot(k[order], t.column("snr_ss_eq43_db")[order], "--", color="gray",
                label="eq. 43")
        ax.set_xlabel("channels K")
        ax.set_ylabel("SNR_XC (dB)")
        ax.set_title(f"order {d}, {det}: {'>' if not reached else '~'}{cap:.0f} channels"
                     f" (paper >{PAPER_CHANNELS[d]})", fontsize=9)
        ax.grid(alpha=0.3)
        er = ax.twinx()
        for name, style in (("signed", "s-"), ("abs", "^--")):
            er.plot(k[order], t.column(_error_column(name))[order], style, color="k", ms=3,
                    lw=0.8, label=f"error rate, {name}")
        er.plot(k[order], sga[order], ":", color="k", label=f"error rate (SGA, {det})")
        er.axhline(ERROR_THRESHOLD, color="tab:green", lw=0.8)
        er.axvline(PAPER_CHANNELS[d], color="tab:purple", ls=":", lw=0.8)
        er.set_ylim(-0.02, 1.02)
        er.set_ylabel("error rate")
        if d == degrees[0]:
            ax.legend(fontsize=7, loc="upper right")
            er.legend(fontsize=7, loc="center right")
        signed, absolute = caps["signed"], caps["abs"]

        def fmt(c: tuple) -> str:
            return f"{'>' if not c[1] else ''}{c[0]:.0f} (95 %: {_span(c[2])})"

        summary[f"workable_channels_order{d}"] = entry(
            cap, f"> {PAPER_CHANNELS[d]}", "channels", ci95=ci, paper_point=signed[0],
            paper_point_ci95=signed[2],
            cause=f"same trials: signed detector (eq. 9) {fmt(signed)}; |corr| "
                  f"{fmt(absolute)}; SGA ({det}) {cap_sga:.0f}")
        summary[f"workable_channels_order{d}_sga"] = entry(cap_sga, None, "channels",
                                                           derived="SGA")
        summary[f"snr_xc_threshold_db_order{d}"] = entry(
            thr, PAPER_SNR_XC_THRESHOLD_DB if d == 11 else None, "dB", paper_point=thr_signed,
            ci95=_along(ci, k, med), paper_point_ci95=_along(signed[2], k, med),
            cause="eq. 44 as our receiver computes it; the paper's floor is not defined "
                  "(scale: a hypothesis, not a finding)" if d == 11 else None)
        n = (1 << d) - 1
        summary[f"snr_ss_eq43_at_capacity_db_order{d}"] = entry(
            10 * math.log10(snr_ss_eq43(n, cap)), None, "dB",
            derived=f"eq. 43 at our capacity; at the paper's {PAPER_CHANNELS[d]}: "
                    f"{10 * math.log10(snr_ss_eq43(n, PAPER_CHANNELS[d])):.1f} dB")
    save_figure(fig, ctx.out / "fig11.png")
    return summary


def _along(ci: tuple, k: np.ndarray, med: np.ndarray) -> tuple[float | None, float | None]:
    """The median SNR_XC at the ends of a capacity interval: the threshold's interval."""
    order = np.argsort(k)
    ends = [None if e is None else float(np.interp(e, k[order], med[order])) for e in ci]
    if None in ends:
        return None, None
    return min(ends), max(ends)  # type: ignore[type-var]


def _span(ci: tuple) -> str:
    """A 95 % interval as text; an end the grid does not bound is left open."""
    lo, hi = ci
    if lo is None and hi is None:
        return "not bounded by the grid"
    if lo is None:
        return f"<= {hi:.0f}"
    if hi is None:
        return f">= {lo:.0f}"
    return f"{lo:.0f}-{hi:.0f}"


STUDY = Study(
    name="fig11",
    description="channel capacity at 10 % error vs K, orders 11/13/15, 50 samples per chip "
                "(paper Fig. 11; fidelity=sga for the Gaussian approximation)",
    grid=_grid,
    task=None,
    trials=TRIALS,
    reduce=_reduce,
    settings=(
        Setting("channels_order11", tuple(range(25, 251, 25)), "channel counts K, order 11",
                quick=(96, 112, 128, 144, 160)),
        Setting("channels_order13", tuple(range(100, 1001, 100)), "channel counts K, order 13",
                quick=(352, 448, 544)),
        Setting("channels_order15", tuple(range(300, 2401, 300)), "channel counts K, order 15",
                quick=(1200, 1800)),
        Setting("S", 50, "samples per chip (the paper's 50)"),
        Setting("trials", 1000, "random-delay trials per point (the paper's 1000); a point "
                "stops at 64, 128, 256, ... trials once decided (see decided())",
                quick=256),
        Setting("refine_rounds", 3, "rounds that add the midpoint of eq. 9's capacity "
                "interval while no grid point lies inside it (0: the grid alone)", quick=2),
        Setting("fidelity", "full", "full (whole receive chain) or sga (Gaussian approximation)"),
        Setting("detector", "abs", "peak detector of the headline: abs (largest |corr|, the "
                "receiver's) or signed (eq. 9's maximum); both are in every table"),
        Setting("point", "default", "default, or paper: the paper's point (eq. 9's signed "
                "detector)"),
    ),
    machine_columns=("time_per_trial_s",),
    version="2",
)
