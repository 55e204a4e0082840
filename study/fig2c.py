"""The ``fig2c`` study: the histogram of repeated single-point ranges (paper Fig. 2c).

The paper ranges one channel on a fixed target 1000 times and calls twice the standard
deviation the depth resolution (Supp. Note 7, eq. 28: R = 2 sigma). Here: a wall
(``point``, below) with the instrument at 62.5 Mchip/s, degree 11,
one channel lit (channel 20, column 0; the others dark),
``repeats`` independent renderings through the whole receive chain and the host's
sub-sample ranging (:mod:`cdma_lidar.study.pointrange`). One task per replicate; each
task draws its own instrument seed.

Columns: ``resolution_2sigma_m`` (2 x sample std of the ranges), ``precision_sigma_m``,
``precision_eq27_m`` (eq. 27 at the pixel's SNR), ``resolution_eq28_m`` (= 2 x eq. 27),
``mean_error_m`` (mean range - truth: the estimator's bias), ``snr_eq30_db``,
``snr_effective_db`` (eq. 30 x R periods: the SNR eq. 27 uses), ``snr_xc_median_db``,
``time_s`` (machine). The ranges themselves (minus the truth) go to ``ranges.csv``.

Operating point (``point``): ``default`` ranges the toolkit's ``flat-wall`` at
``distance`` with R = ``averages``, S = ``S`` and the ``method`` refinement; ``paper``
stands where the paper stood as far as it says (:mod:`cdma_lidar.study.paperlab`): the
``paper-lab`` instrument (400 MHz APD), one channel so no sequential mixing, and the
assumptions it lists for what the paper leaves out (10 m, R = 1, S = 50, the peak index
without refinement). ``repeats`` applies to both.

The resolution's 95 % interval: a bootstrap of the standard deviation of every range of
every replicate pooled (their tails are heavier than a Gaussian's at low SNR; each
replicate draws its own instrument seed); a range more than half a
chip from the truth is a gross error (``gross_errors``), left out of the histogram. Eq.
28 at the pixel's SNR is a derived quantity beside it.
"""

from __future__ import annotations

import math
import time
from typing import Any

import numpy as np

from cdma_lidar.checks import check_int
from cdma_lidar.errors import out_of_range
from cdma_lidar.fileio import atomic_open
from cdma_lidar.host.ranging import METHODS, sample_range_m
from cdma_lidar.study.engine import (
    RunContext,
    RunOptions,
    Setting,
    Study,
    Table,
    grid_product,
)
from cdma_lidar.study.figures import new_figure, save_figure
from cdma_lidar.study.paperlab import check_point, entry
from cdma_lidar.study.pointrange import repeat_ranges

__all__ = [
    "PAPER_POINT",
    "PAPER_RESOLUTION_M",
    "REPORT_NOTE",
    "STUDY",
    "bootstrap_std_ci",
    "fig2c_task",
    "point_settings",
    "snr_for_resolution_db",
]

#: Paper, main text ("the system attains a depth resolution of 25.68 cm") and Fig. 2c.
PAPER_RESOLUTION_M = 0.2568
#: Paper: the oscilloscope's samples per chip are not given; 50 (Supp. Note 8's simulation,
#: 3.125 GS/s at 62.5 Mchip/s) is assumed where the paper's N_s is needed.
PAPER_SAMPLES_PER_CHIP = 50

#: A range this far from the truth (half a chip at 62.5 Mchip/s, m) is a gross error.
HALF_CHIP_M = sample_range_m(1, 62.5e6) / 2

#: What ``point=paper`` ranges (the assumptions are in cdma_lidar.study.paperlab).
PAPER_POINT = {"scene": "paper-lab", "distance": 10.0, "averages": 1,
               "S": PAPER_SAMPLES_PER_CHIP, "method": "none", "sequential_mixing": False}

REPORT_NOTE = (
    "Both numbers are 2 sigma of repeated single-channel ranges. At the paper's point (the "
    "paper-lab instrument at 10 m, one record per range, 50 samples per chip, the peak "
    "index) the link budget gives an SNR at which eq. 28 itself is near the paper's "
    "number, which the joint calibration fits (so the row is calibrated, not a test); at "
    "the toolkit's default (5 m, R = 10 records summed, S = 4 with sub-sample "
    "refinement) the SNR is much higher and the resolution centimetres. The `cause` "
    "column gives both from this run. Fig. 2c ranges one channel, so nothing is mixed: "
    "Supp. Note 4's sequential-mixing noise does not apply. The paper states neither the "
    "distance, the averaging nor the sample rate of Fig. 2c (assumptions, with sources, in "
    "the operating-point table). Depth resolution (2 sigma, eq. 28) and precision (sigma, "
    "eq. 27) differ by exactly 2."
)


def snr_for_resolution_db(resolution_m: float, chip_rate_hz: float,
                          samples_per_symbol: int) -> float:
    """The per-sample SNR (dB) at which eq. 28 gives ``resolution_m``."""
    d_r = sample_range_m(1, chip_rate_hz)  # c / (2 f_chip): the range of one chip
    root = math.sqrt(6.0 / samples_per_symbol) / math.pi * d_r / resolution_m
    return 20 * math.log10(root)


def bootstrap_std_ci(values: np.ndarray, seed: int, resamples: int = 2000
                     ) -> tuple[float, float]:
    """95 % bootstrap (percentile) interval of the standard deviation of ``values``.

    The ranges' tails are heavier than a Gaussian's at low SNR (a peak a sample or two
    off), so the chi-square interval would be too narrow. ``seed``: the run's seed.
    """
    rng = np.random.default_rng([seed, values.size])
    idx = rng.integers(0, values.size, (resamples, values.size))
    stds = np.std(values[idx], axis=1, ddof=1)
    lo, hi = np.percentile(stds, [2.5, 97.5])
    return float(lo), float(hi)


def point_settings(options: RunOptions) -> dict[str, Any]:
    """The ranged configuration: the settings, or :data:`PAPER_POINT` at ``point=paper``."""
    if check_point(options["point"]) == "paper":
        return dict(PAPER_POINT)
    return {"scene": "flat-wall", "distance": options["distance"],
            "averages": options["averages"], "S": options["S"], "method": options["method"],
            "sequential_mixing": False}


def _grid(options: RunOptions) -> list[dict]:
    p = point_settings(options)
    if p["method"] not in METHODS:
        raise out_of_range("method", "one of " + ", ".join(METHODS), p["method"])
    dist = float(p["distance"])
    if not 0.5 <= dist <= 1000.0:
        raise out_of_range("distance", "0.5..1000 m", dist)
    return grid_product(scene=[p["scene"]], distance=[dist],
                        repeats=[check_int("repeats", options["repeats"], 3, 100_000)],
                        averages=[check_int("averages", p["averages"], 1, 1024)],
                        S=[check_int("S", p["S"], 1, 64)],
                        method=[p["method"]], sequential_mixing=[bool(p["sequential_mixing"])])


def _overrides(params: dict) -> dict[str, Any]:
    return {"distance": float(params["distance"]),
            "instrument.averages": int(params["averages"]),
            "instrument.samples_per_chip": int(params["S"]),
            "instrument.sequential_mixing": bool(params["sequential_mixing"])}


def fig2c_task(params: dict, seed: np.random.SeedSequence) -> dict[str, Any]:
    """``repeats`` ranges of one pixel; the ranges themselves as ``ranges_m`` (a JSON list)."""
    t0 = time.perf_counter()
    r = repeat_ranges(str(params["scene"]), _overrides(params), int(params["repeats"]),
                      int(seed.generate_state(1)[0]), method=str(params["method"]))
    err = r.range_m - r.truth_m
    gross = np.abs(err) > HALF_CHIP_M
    resolution = 2 * float(np.std(err[~gross], ddof=1))
    return {"resolution_2sigma_m": resolution, "precision_sigma_m": resolution / 2,
            "gross_errors": int(gross.sum()),
            "precision_eq27_m": r.precision_eq27_m,
            "resolution_eq28_m": 2 * r.precision_eq27_m,
            "mean_error_m": float(np.mean(r.range_m) - r.truth_m),
            "snr_eq30_db": r.snr_eq30_db, "snr_effective_db": r.snr_effective_db,
            "snr_xc_median_db": r.snr_xc_median_db,
            "ranges_m": " ".join(f"{x - r.truth_m:.6f}" for x in r.range_m),
            "time_s": time.perf_counter() - t0}


def _reduce(table: Table, ctx: RunContext) -> dict[str, Any]:
    # every replicate's ranges (a string of numbers per task, also in replicates.csv; the
    # engine joins several replicates' with ';'), one per line in ranges.csv
    cells = [str(row.get("ranges_m", "")) for row in table.rows]
    errs = np.array([float(x) for cell in cells
                     for x in cell.replace(";", " ").replace("\"", " ").split()])
    for row in table.rows:
        row["ranges_m"] = "ranges.csv"
    with atomic_open(ctx.out / "ranges.csv", "w") as fh:
        fh.write("range_error_m\n" + "".join(f"{e:.6f}\n" for e in errs))
    # a range more than half a chip from the truth is a gross error (the receiver locked
    # on a side peak: the error of Figs. 2e, 2f and 11), counted apart from the histogram
    gross = np.abs(errs) > HALF_CHIP_M
    all_errs, errs = errs, errs[~gross]
    sigma = float(np.std(errs, ddof=1))
    mean = float(np.mean(errs))
    eq27 = float(np.mean(table.column("precision_eq27_m")))
    fig, ax = new_figure(6, 4)
    ax.hist(errs * 100, bins=40, density=True, color="tab:blue", alpha=0.6,
            label=f"{errs.size} ranges")
    x = np.linspace(errs.min(), errs.max(), 200)
    ax.plot(x * 100, np.exp(-0.5 * ((x - mean) / sigma) ** 2) / (sigma * math.sqrt(2 * math.pi))
            / 100, color="tab:red", label="Gaussian fit")
    for sgn in (-1, 1):
        ax.axvline((mean + sgn * sigma) * 100, color="k", ls="--", lw=0.8)
    # the paper's histogram is not in its text: its stated 2 sigma drawn as a Gaussian
    sp = PAPER_RESOLUTION_M / 2
    xp = np.linspace(-3 * sp, 3 * sp, 200)
    ax.plot(xp * 100, np.exp(-0.5 * (xp / sp) ** 2) / (sp * math.sqrt(2 * math.pi)) / 100,
            color="k", lw=1.0, ls=":", label=f"paper: Gaussian, 2 sigma = "
            f"{PAPER_RESOLUTION_M * 100:.2f} cm (its text; histogram not digitised)")
    ax.set_xlabel("range - truth (cm)")
    ax.set_ylabel("density (1/cm)")
    ax.set_title(f"2 sigma = {2 * sigma * 100:.2f} cm (eq. 28: {2 * eq27 * 100:.2f} cm; "
                 f"paper {PAPER_RESOLUTION_M * 100:.2f} cm)", fontsize=9)
    ax.legend(fontsize=6)
    save_figure(fig, ctx.out / "fig2c.png")
    chip_rate = 62.5e6
    row = table.rows[0]
    # every range of every replicate pooled: a bootstrap of their standard deviation (not a
    # t over a handful of replicates' 2 sigma, whose few degrees of freedom widen it)
    lo, hi = bootstrap_std_ci(errs, ctx.options.seed)
    snr_eff = float(np.mean(table.column("snr_effective_db")))
    where = (f"{row['scene']} at {row['distance']:g} m, R = {row['averages']}, "
             f"S = {row['S']}, refinement {row['method']}")
    needed = snr_for_resolution_db(PAPER_RESOLUTION_M, chip_rate, 2047 * int(row["S"]))
    return {
        "resolution_2sigma_m": entry(
            2 * sigma, PAPER_RESOLUTION_M, "m", ci95=(2 * lo, 2 * hi),
            cause=f"{where}: {2 * sigma * 100:.2f} cm measured, eq. 28 at this pixel's SNR "
                  f"({snr_eff:.1f} dB per sample after R) {2 * eq27 * 100:.2f} cm"),
        "precision_eq27_m": entry(eq27, None, "m", derived="eq. 27 at the pixel's SNR"),
        "gross_errors": entry(int(gross.sum()), None, "ranges",
                              derived=f"of {all_errs.size}: more than half a chip off, "
                                      "left out of the histogram"),
        "resolution_eq28_m": entry(2 * eq27, None, "m", derived="eq. 28 at the pixel's SNR"),
        "snr_for_paper_resolution_db": entry(
            snr_eff, None, "dB",
            derived=f"our effective per-sample SNR; eq. 28 gives the paper's 25.68 cm at "
                    f"{needed:.1f} dB with N_s = 2047 x {row['S']}"),
    }


STUDY = Study(
    name="fig2c",
    description="histogram of repeated single-point ranges, resolution = 2 sigma vs eq. 28 "
                "(paper Fig. 2c)",
    grid=_grid,
    task=fig2c_task,
    reduce=_reduce,
    settings=(
        Setting("repeats", 1000, "ranges per replicate (the paper's 1000)"),
        Setting("distance", 5.0, "wall distance (m)"),
        Setting("averages", 10, "code periods R summed (the paper instrument's 10)"),
        Setting("S", 4, "samples per chip"),
        Setting("method", "triangle", "sub-sample refinement: none, parabolic, triangle"),
        Setting("point", "default", "default (the settings above) or paper (the paper's "
                "point: paper-lab at 10 m, R = 1, S = 50, peak index)"),
    ),
    machine_columns=("time_s",),
    version="2",
)
