"""The ``fig2d`` study: depth resolution vs chip rate and sample rate (paper Fig. 2d, eq. 28).

For each chip rate f_c (``chip_rates_mhz``) and samples per chip S (sample rate S f_c):
``repeats`` single-channel ranges of a wall at ``distance`` m on the simulated instrument
(:mod:`cdma_lidar.study.pointrange`; degree 11, R = ``averages``, a detector of
``detector_bandwidth_mhz``, the physical link budget), the measured 2 sigma with its
bootstrap 95 % interval, and eq. 28 at the pixel's own SNR. The instrument's noise is
white up to the ADC's Nyquist frequency, so a faster ADC buys more samples, not less
noise per sample; its echoes are shaped by the detector, which eq. 28 does not know about.
``point=paper`` ranges the ``paper-lab`` instrument instead (:data:`PAPER_POINT`).

Columns: ``resolution_2sigma_m``, ``resolution_lo95_m`` / ``_hi95_m``, ``gross_errors``
(ranges more than half a chip off, left out), ``resolution_eq28_m``, ``snr_effective_db``
(the SNR eq. 28 uses: eq. 30 x R periods), ``sample_rate_hz``, ``time_s`` (machine).

Headlines: the measured 2 sigma at 62.5 and 200 Mchip/s (S = ``headline_S``) next to the
paper's 25.68 cm (62.5 MHz) and its prediction of "millimeter-level" resolution at 200 MHz
(printed without a number; read as below 1 cm, and said so in the row).
"""

from __future__ import annotations

import time
from typing import Any

import numpy as np

from cdma_lidar.checks import check_int
from cdma_lidar.errors import out_of_range
from cdma_lidar.host.ranging import METHODS, sample_range_m
from cdma_lidar.study.engine import (
    RunContext,
    RunOptions,
    Setting,
    Study,
    Table,
    grid_product,
)
from cdma_lidar.study.fig2c import PAPER_RESOLUTION_M, bootstrap_std_ci
from cdma_lidar.study.figures import new_figure, save_figure
from cdma_lidar.study.paperlab import check_point, entry
from cdma_lidar.study.pointrange import repeat_ranges

__all__ = ["PAPER_POINT", "REPORT_NOTE", "STUDY", "fig2d_task", "point_settings"]

REPORT_NOTE = (
    "Resolution falls with the chip rate (1/B in eq. 28) as the paper predicts. The level "
    "depends on the SNR, as in Fig. 2c: the `cause` column gives the configuration and eq. "
    "28 at its SNR. At 200 Mchip/s the paper predicts 'millimeter-level' resolution "
    "without a number (read here as below 1 cm). The detector's bandwidth is a setting "
    "(detector_bandwidth_mhz; the paper's APD430C is specified to 400 MHz, the toolkit's "
    "default instrument has 200 MHz): a detector slower than the chips rounds the "
    "correlation peak, which eq. 28 does not contain. Along S, eq. 28 stays flat (white "
    "noise to Nyquist: N_s x SNR is constant); the measured 2 sigma also carries the "
    "sub-sample estimator's own error, which the figure shows against eq. 28."
)


#: What ``point=paper`` changes (assumptions in cdma_lidar.study.paperlab): the paper-lab
#: instrument with its 400 MHz APD, 10 m, one record per range, the peak index, and
#: S = 4 and 50 (the paper's simulation rate) with the headline at 50.
PAPER_POINT = {"scene": "paper-lab", "distance": 10.0, "averages": 1,
               "detector_bandwidth_mhz": 400.0, "method": "none", "S": (4, 50),
               "headline_S": 50}


def point_settings(options: RunOptions) -> dict[str, Any]:
    """The configuration ranged: the settings, or :data:`PAPER_POINT` at ``point=paper``."""
    if check_point(options["point"]) == "paper":
        return dict(PAPER_POINT)
    return {"scene": "flat-wall", "distance": options["distance"],
            "averages": options["averages"],
            "detector_bandwidth_mhz": options["detector_bandwidth_mhz"],
            "method": options["method"], "S": options["S"], "headline_S": options["headline_S"]}


def _grid(options: RunOptions) -> list[dict]:
    p = point_settings(options)
    rates = [float(r) for r in options["chip_rates_mhz"]]
    for r in rates:
        if not 1.0 <= r <= 2000.0:
            raise out_of_range("chip_rates_mhz", "1..2000 MHz", r)
    if not rates:
        raise out_of_range("chip_rates_mhz", "at least one value", "none")
    bw = float(p["detector_bandwidth_mhz"])
    if not 1.0 <= bw <= 100_000.0:
        raise out_of_range("detector_bandwidth_mhz", "1..100000 MHz", bw)
    if p["method"] not in METHODS:
        raise out_of_range("method", "one of " + ", ".join(METHODS), p["method"])
    return grid_product(chip_rate_mhz=rates,
                        S=[check_int("S", s, 1, 64) for s in p["S"]],
                        repeats=[check_int("repeats", options["repeats"], 3, 100_000)],
                        distance=[float(p["distance"])], scene=[p["scene"]],
                        averages=[check_int("averages", p["averages"], 1, 1024)],
                        detector_bandwidth_mhz=[bw], method=[p["method"]])


def fig2d_task(params: dict, seed: np.random.SeedSequence) -> dict[str, Any]:
    """One (chip rate, S): repeated ranges, measured 2 sigma (bootstrap 95 %) and eq. 28."""
    t0 = time.perf_counter()
    f_c = float(params["chip_rate_mhz"]) * 1e6
    s = int(params["S"])
    r = repeat_ranges(str(params["scene"]), {
        "distance": float(params["distance"]), "instrument.chip_rate_hz": f_c,
        "instrument.samples_per_chip": s, "instrument.averages": int(params["averages"]),
        "instrument.sequential_mixing": False,
        "instrument.detector_bandwidth_hz": float(params["detector_bandwidth_mhz"]) * 1e6},
        int(params["repeats"]), int(seed.generate_state(1)[0]), method=str(params["method"]))
    err = r.range_m - r.truth_m
    err = err[np.abs(err) <= sample_range_m(1, f_c) / 2]  # gross errors apart (as fig2c)
    lo, hi = bootstrap_std_ci(err, int(seed.generate_state(2)[1]))
    return {"resolution_2sigma_m": 2 * float(np.std(err, ddof=1)),
            "resolution_lo95_m": 2 * lo, "resolution_hi95_m": 2 * hi,
            "gross_errors": int(r.range_m.size - err.size),
            "resolution_eq28_m": 2 * r.precision_eq27_m,
            "snr_effective_db": r.snr_effective_db,
            "sample_rate_hz": f_c * s,
            "time_s": time.perf_counter() - t0}


def _at(table: Table, rate_mhz: float, s: int, column: str) -> float | None:
    t = table.where(chip_rate_mhz=rate_mhz, S=s)
    return float(t.column(column)[0]) if len(t) else None


def _reduce(table: Table, ctx: RunContext) -> dict[str, Any]:
    fig, ax = new_figure(6.5, 4.2)
    colours = ["tab:blue", "tab:orange", "tab:green", "tab:red", "tab:purple", "tab:brown"]
    for i, s in enumerate(sorted(set(table.column("S").astype(int)))):
        t = table.where(S=s)
        rate = t.column("chip_rate_mhz")
        o = np.argsort(rate)
        col = colours[i % len(colours)]
        ax.plot(rate[o], t.column("resolution_2sigma_m")[o] * 100, "o-", color=col,
                label=f"S = {s}, measured 2 sigma")
        ax.plot(rate[o], t.column("resolution_eq28_m")[o] * 100, "--", color=col,
                label=f"S = {s}, eq. 28")
    ax.plot([62.5], [PAPER_RESOLUTION_M * 100], "k*", ms=10,
            label="paper: 25.68 cm at 62.5 MHz (its text)")
    rates = np.array([min(62.5, *table.column("chip_rate_mhz")),
                      max(200.0, *table.column("chip_rate_mhz"))])
    ax.plot(rates, PAPER_RESOLUTION_M * 100 * 62.5 / rates, "k:", lw=1.0,
            label="eq. 28 through the paper's point (R ~ 1/f_c)")
    ax.errorbar([200.0], [0.55], yerr=[[0.45], [0.45]], fmt="none", ecolor="k", capsize=4,
                label="paper: millimeter-level at 200 MHz (its text)")
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlabel("chip rate (MHz)")
    ax.set_ylabel("depth resolution 2 sigma (cm)")
    ax.grid(alpha=0.3, which="both")
    ax.legend(fontsize=7)
    save_figure(fig, ctx.out / "fig2d.png")
    s = int(point_settings(ctx.options)["headline_S"])
    row = table.rows[0]
    where = (f"{row['scene']} at {row['distance']:g} m, R = {row['averages']}, "
             f"{row['detector_bandwidth_mhz']:g} MHz detector, S = {s}, "
             f"refinement {row['method']}")

    def ci(rate: float) -> tuple[float | None, float | None]:
        return _at(table, rate, s, "resolution_lo95_m"), _at(table, rate, s, "resolution_hi95_m")

    at200, ci200 = _at(table, 200.0, s, "resolution_2sigma_m"), ci(200.0)
    mm = None if ci200[1] is None else ("reproduced" if ci200[1] < 0.01 else "differs")
    # eq. 28 through the paper's own point: R ~ 1 / (f_c sqrt(N_s SNR))
    scaled = PAPER_RESOLUTION_M * 62.5 / 200.0
    need = (scaled / 0.01) ** 2
    return {
        "resolution_m_at_62_5mhz": entry(
            _at(table, 62.5, s, "resolution_2sigma_m"), PAPER_RESOLUTION_M, "m", ci95=ci(62.5),
            cause=f"{where}; eq. 28 at this SNR "
                  f"{_fmt_cm(_at(table, 62.5, s, 'resolution_eq28_m'))}"),
        "resolution_m_at_200mhz": entry(
            at200, "millimeter-level", "m", ci95=ci200, verdict=mm,
            cause=f"{where}; 'millimeter-level' read as below 1 cm; eq. 28 at this SNR "
                  f"{_fmt_cm(_at(table, 200.0, s, 'resolution_eq28_m'))}; eq. 28 through the "
                  f"paper's own 25.68 cm at 62.5 MHz gives {_fmt_cm(scaled)} at 200 MHz, so "
                  f"below 1 cm needs N_s x SNR {need:.0f} times Fig. 2c's (the paper states "
                  "no such gain: a difference in the paper's claim, not in our run)"),
        "resolution_eq28_paper_scaled_m_at_200mhz": entry(
            scaled, None, "m", derived="eq. 28 through the paper's 25.68 cm at 62.5 MHz, "
            "same N_s x SNR (R ~ 1/f_c)"),
        "resolution_eq28_m_at_62_5mhz": entry(_at(table, 62.5, s, "resolution_eq28_m"), None,
                                              "m", derived="eq. 28 at the pixel's SNR"),
        "resolution_eq28_m_at_200mhz": entry(_at(table, 200.0, s, "resolution_eq28_m"), None,
                                             "m", derived="eq. 28 at the pixel's SNR"),
    }


def _fmt_cm(x: float | None) -> str:
    return "--" if x is None else f"{x * 100:.2f} cm"


STUDY = Study(
    name="fig2d",
    description="depth resolution vs chip rate and sample rate, measured 2 sigma and eq. 28 "
                "(paper Fig. 2d)",
    grid=_grid,
    task=fig2d_task,
    reduce=_reduce,
    settings=(
        Setting("chip_rates_mhz", (31.25, 62.5, 125.0, 200.0, 250.0), "chip rates (MHz)",
                quick=(62.5, 200.0)),
        Setting("S", (2, 4, 8, 16), "samples per chip (sample rate = S x chip rate)",
                quick=(2, 4)),
        Setting("repeats", 1000, "ranges per point", quick=100),
        Setting("distance", 5.0, "wall distance (m)"),
        Setting("headline_S", 4, "the S of the summary's headline numbers"),
        Setting("averages", 10, "code periods R summed"),
        Setting("detector_bandwidth_mhz", 200.0, "the detector's -3 dB bandwidth (MHz; the "
                "paper's APD430C: 400)"),
        Setting("method", "triangle", "sub-sample refinement: none, parabolic, triangle"),
        Setting("point", "default", "default (the settings above) or paper (paper-lab at 10 m, "
                "R = 1, 400 MHz APD, S = 4 and 50, peak index)"),
    ),
    machine_columns=("time_s",),
    version="2",
)
