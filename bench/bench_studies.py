"""Studies on many workers: does the fig11 sweep keep every worker busy?

Runs the ``fig11`` study (whole receive chain, random delays, the engine's chunks of
trials) on a local Dask cluster of 1, 2 and every core's worth of single-threaded
workers, and prints per worker count the run's time and its parallel efficiency
``T(1) / (n T(n))`` against the 1-worker run of the same process. Time is the run's
wall time without starting the cluster (``run.json``: ``wall_time_s - executor_start_s``),
best of ``CDMA_LIDAR_BENCH_REPEATS`` (default 2) runs interleaved across the worker
counts, so a burst of load from other processes hits one run of each, not all of one.
The model columns of every run must be identical (the engine's promise); a run that
differs raises.

Targets (issue 23): efficiency >= 90 % on 2 workers and >= 80 % on 16 workers, for the
full fig11 (orders 11 and 13, 1000 trials per point). The full configuration takes about
9 CPU-minutes per run on the 2-core development machine, so the default is a smaller one,
order 11 only with 100 trials per point (the issue compared 1 and 16 workers on order 11
with 200);
``python -m bench studies --full`` (or ``CDMA_LIDAR_BENCH_FULL=1``) runs the full one.
A machine with fewer cores than a target's worker count cannot measure that target:
the line says so.
"""

from __future__ import annotations

import json
import os
import sys
import tempfile
import time
from pathlib import Path

from cdma_lidar.study.engine import read_csv, run_study
from cdma_lidar.study.fig11 import STUDY as FIG11

#: The default (reduced) configuration and the full one of the issue.
SMALL = {"channels_order11": tuple(range(25, 251, 25)), "channels_order13": (),
         "channels_order15": (), "trials": 100}
FULL = {"channels_order11": tuple(range(25, 251, 25)),
        "channels_order13": tuple(range(100, 1001, 100)), "channels_order15": (),
        "trials": 1000}
#: Efficiency targets by worker count (issue 23).
TARGETS = {2: 0.90, 16: 0.80}


def _model_rows(out: Path) -> list[dict]:
    drop = {c for m in FIG11.machine_columns for c in (m, f"{m}_ci95", f"{m}_best")}
    return [{k: v for k, v in row.items() if k not in drop}
            for row in read_csv(out / "results.csv").rows]


def _run(overrides: dict, workers: int) -> tuple[float, int, list[dict]]:
    """(seconds without the cluster start, chunks computed, model rows) of one run."""
    with tempfile.TemporaryDirectory(prefix="bench-studies-") as tmp:
        out = Path(tmp)
        res = run_study(FIG11, out, overrides=overrides, workers=workers, progress=False)
        if res.failures:
            raise RuntimeError(f"fig11 failed: {res.failures[0]}")
        info = json.loads((out / "run.json").read_text())
        return info["wall_time_s"] - info["executor_start_s"], res.computed, _model_rows(out)


def main() -> None:
    full = "--full" in sys.argv or os.environ.get("CDMA_LIDAR_BENCH_FULL") == "1"
    repeats = int(os.environ.get("CDMA_LIDAR_BENCH_REPEATS", "2"))
    overrides = FULL if full else SMALL
    cores = os.cpu_count() or 1
    counts = sorted({1, 2, cores})
    points = sum(len(v) for k, v in overrides.items() if k.startswith("channels"))
    print(f"fig11 {'full' if full else 'reduced'}: {points} points x {overrides['trials']} "
          f"trials (orders {'11 and 13' if full else '11'}, S = 50), local Dask workers "
          f"{counts} of {cores} cores, best of {repeats} interleaved; load average "
          f"{os.getloadavg()[0]:.2f}", flush=True)
    best: dict[int, float] = {}
    chunks: dict[int, int] = {}
    reference = None
    t_start = time.monotonic()
    for _ in range(repeats):
        for n in counts:
            seconds, computed, rows = _run(overrides, n)
            if reference is None:
                reference = rows
            elif rows != reference:
                raise AssertionError(f"fig11 on {n} workers gave another table")
            best[n] = min(best.get(n, float("inf")), seconds)
            chunks[n] = computed
    for n in counts:
        eff = best[1] / (n * best[n])
        target = TARGETS.get(n)
        verdict = "" if target is None else \
            f" (target {target:.0%}: {'met' if eff >= target else 'NOT met'})"
        print(f"  {n:3d} workers: {best[n]:7.2f} s, {chunks[n]:4d} chunks, speed-up "
              f"x{best[1] / best[n]:5.2f}, efficiency {eff:6.1%}{verdict}")
    for n, target in TARGETS.items():
        if n > cores:
            print(f"  {n:3d} workers: efficiency not measured: this machine has {cores} cores "
                  f"(target {target:.0%})")
    print(f"tables identical across worker counts; load average {os.getloadavg()[0]:.2f} "
          f"after {time.monotonic() - t_start:.0f} s")


if __name__ == "__main__":
    main()
