"""The ``eq29`` study: the frame rate at 1 Gchip/s, a degree-13 code and 1000 pixels (eq. 29).

Eq. 29 (Supplementary Note 8): f_frame = omega_c / (N * 1000) with omega_c = 1 GHz and
N = 2^13 - 1 = 8191 chips, about 122 Hz. Measured here on the real code path: a
virtual device (``virtual://flat-wall``) configured at the paper's assumption (chip
rate 1 GHz, degree 13, no coherent averaging, one UID period) scans ``columns``
columns through the serial protocol, and the frame time is read from the
``timestamp_us`` the device stamps on every column (its clock counts chips exactly,
see ``cdma_lidar.virtual.board``). With fewer than ``pixels`` columns (``--quick``)
the frame time is scaled from the columns scanned: T = t(last column) * pixels /
columns. The timestamps are whole microseconds (floored), so the measured rate is
exact to about 1 us per frame.

The configured sampling rate (``samples_per_chip``) does not change the timing; it is
1 by default so the scan is fast. A channel count of 1 likewise: channels are
parallel and share the column time.

Columns: ``frame_rate_hz`` (measured), ``frame_rate_eq29_hz`` (the formula with the
device's own chip rate and code length), ``frame_rate_us_rounded_hz`` (what a clock
that rounds every column to whole microseconds, as the virtual device did before,
gives: 125 Hz), ``column_time_us`` (mean column-to-column step).
"""

from __future__ import annotations

import time
from typing import Any

import numpy as np

import cdma_lidar.virtual  # noqa: F401  (importing it registers the virtual:// URL scheme)
from cdma_lidar.checks import check_int
from cdma_lidar.errors import out_of_range
from cdma_lidar.host.connection import connect
from cdma_lidar.study.engine import RunContext, Setting, Study, Table, grid_product
from cdma_lidar.study.figures import new_figure, save_figure
from cdma_lidar.study.paperlab import check_point, exact

__all__ = ["REPORT_NOTE", "STUDY", "eq29_task", "eq29_url"]

#: Eq. 29's frame rate as printed ("approximately 122 Hz"), Supplementary Note 8.
PAPER_FRAME_RATE_HZ = 122.0

REPORT_NOTE = (
    "Eq. 29 is a formula, and the virtual device now obeys it: its clock counts chips "
    "exactly (R n N per column) and floors only when it writes the microsecond timestamp, "
    "so 1000 columns of 8191 chips at 1 Gchip/s end at 8191 us, 122.08 Hz, against the "
    "paper's 'approximately 122 Hz' (the small ratio above 1 is the paper's rounding of "
    "122.08). Before issue 13 the clock advanced by each column's time rounded to whole "
    "microseconds (8 us instead of 8.191 us), which gave 125 Hz; that definition is "
    "shown as frame_rate_us_rounded_hz for comparison. With --quick fewer columns are "
    "scanned and the frame time is scaled up, which can cost up to 1 us x pixels/columns "
    "of flooring (still 122.1 Hz)."
)


def eq29_url(chip_rate_hz: float, degree: int, columns: int, samples_per_chip: int) -> str:
    """The virtual device at eq. 29's configuration (one channel, a flat wall)."""
    return (f"virtual://flat-wall?seed=1&instrument.chip_rate_hz={chip_rate_hz:.0f}"
            f"&code_degree={degree}&averages=1&instrument.columns={columns}"
            f"&instrument.wavelengths.count=1&instrument.samples_per_chip={samples_per_chip}")


def _grid(options: Any) -> list[dict]:
    check_point(options["point"])
    deg = check_int("degree", options["degree"], 5, 15)
    pixels = check_int("pixels", options["pixels"], 1, 100000)
    cols = check_int("columns", options["columns"], 1, pixels)
    s = check_int("samples_per_chip", options["samples_per_chip"], 1, 16)
    rate = float(options["chip_rate_hz"])
    if not 1e6 <= rate <= 1e10:
        raise out_of_range("chip_rate_hz", "from 1e6 to 1e10 chips/s", rate)
    return grid_product(chip_rate_hz=[rate], degree=[deg], pixels=[pixels], columns=[cols],
                        samples_per_chip=[s])


def eq29_task(params: dict, seed: np.random.SeedSequence) -> dict[str, Any]:
    """Scan ``columns`` columns on a fresh virtual device and time them by its clock."""
    del seed  # the timing is deterministic; the device's noise seed is fixed in the URL
    rate, m = float(params["chip_rate_hz"]), int(params["degree"])
    pixels, cols = int(params["pixels"]), int(params["columns"])
    t0 = time.perf_counter()
    with connect(eq29_url(rate, m, cols, int(params["samples_per_chip"]))) as dev:
        n = dev.code_length
        chips = int(dev.config["averages"]) * int(dev.config["uid_bits"]) * n
        device_rate = float(dev.info.chip_rate_hz)
        stamps = np.array([c.timestamp_us for c in dev.link.scan(
            first_column=0, columns=cols, frames=1, frame=1)], dtype=np.int64)
    if stamps.size != cols or np.any(np.diff(stamps) < 0):
        raise RuntimeError(f"expected {cols} increasing timestamps, got {stamps.size}")
    frame_s = float(stamps[-1]) * 1e-6 * pixels / cols     # the clock starts at 0 at power-up
    column_us = chips / device_rate * 1e6
    return {"frame_rate_hz": 1.0 / frame_s,
            "frame_rate_eq29_hz": device_rate / (chips * pixels),
            "frame_rate_us_rounded_hz": 1e6 / (round(column_us) * pixels),
            "column_time_us": float(np.mean(np.diff(stamps))) if cols > 1 else float(stamps[0]),
            "column_time_exact_us": column_us,
            "code_length_chips": n,
            "wall_time_s": time.perf_counter() - t0}


def _reduce(table: Table, ctx: RunContext) -> dict[str, Any]:
    row = table.rows[0]
    fig, ax = new_figure(6, 3.6)
    labels = ["eq. 29 (paper, ~122)", "eq. 29 formula", "virtual device clock",
              "whole-us column clock (old)"]
    values = [PAPER_FRAME_RATE_HZ, row["frame_rate_eq29_hz"], row["frame_rate_hz"],
              row["frame_rate_us_rounded_hz"]]
    bars = ax.barh(labels, values, color=["0.6", "C0", "C2", "C3"])
    for b, v in zip(bars, values, strict=True):
        ax.text(v, b.get_y() + b.get_height() / 2, f" {v:.2f} Hz", va="center", fontsize=8)
    ax.set_xlim(100, 135)
    ax.set_xlabel("frame rate (Hz)")
    ax.set_title(f"{row['chip_rate_hz'] / 1e9:g} Gchip/s, N = {int(row['code_length_chips'])}, "
                 f"{int(row['pixels'])} pixels")
    save_figure(fig, ctx.out / "eq29.png")
    # Paper: Supplementary Note 8, eq. 29, "approximately 122 Hz".
    return {"frame_rate_hz": exact(row["frame_rate_hz"], PAPER_FRAME_RATE_HZ, "Hz")}


STUDY = Study(
    name="eq29",
    description="frame rate at 1 Gchip/s, degree 13, 1000 pixels from the virtual device's clock "
                "(eq. 29)",
    grid=_grid, task=eq29_task, reduce=_reduce,
    settings=(
        Setting("chip_rate_hz", 1e9, "chip rate omega_c (chips/s)"),
        Setting("degree", 13, "code degree m (N = 2^m - 1)"),
        Setting("pixels", 1000, "pixels (columns) per frame in eq. 29"),
        Setting("columns", 1000, "columns actually scanned (the frame time is scaled to "
                "'pixels')", quick=250),
        Setting("samples_per_chip", 1, "samples per chip of the scan (does not change timing)"),
        Setting("point", "default", "default or paper: one point here, the paper's own"),
    ),
    machine_columns=("wall_time_s",),
    version="1",
)
