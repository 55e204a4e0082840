"""Run a study and read its table: detection rate against per-sample SNR.

    python examples/study_table.py [--quick] [--out out/examples/detection]

A study is a grid of parameters, each point simulated; its result is a tidy table (also
``results.csv`` in the folder) whose columns come out as numpy arrays.
"""

from __future__ import annotations

import argparse

import numpy as np

import cdma_lidar


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="the study's small grid")
    parser.add_argument("--out", default="out/examples/detection", help="study folder")
    args = parser.parse_args()

    result = cdma_lidar.run_study("detection", args.out, quick=args.quick)
    table = result.table
    print(f"{len(table)} rows, columns: {', '.join(table.columns)}")
    snr = table.column("snr_db")
    rate = table.column("detection_rate")
    for s in np.unique(snr):
        print(f"per-sample SNR {s:+6.1f} dB: mean detection rate {rate[snr == s].mean():.2f}")
    print(table.where(S=1).to_markdown(["degree", "snr_db", "detection_rate",
                                        "snr_xc_median_db"]), end="")
    print(f"files in {result.out}: results.csv, summary.json, figures")


if __name__ == "__main__":
    main()
