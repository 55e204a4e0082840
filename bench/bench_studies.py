"""Studies on many workers: does the fig11 sweep keep every worker busy?

Runs the ``fig11`` study (whole receive chain, random delays, the engine's chunks of
trials, points stopped early once decided) on a local Dask cluster of 1, 2 and every
core's worth of single-threaded workers, and prints per worker count the run's time and
its parallel efficiency ``T(1) / (n T(n))`` against the 1-worker run of the same process.
Time is the run's wall time without starting the cluster (``run.json``: ``wall_time_s -
executor_start_s``; the start is printed apart), best of ``CDMA_LIDAR_BENCH_REPEATS``
(default 2) runs interleaved across the worker counts, so a burst of load from other
processes hits one run of each, not all of one. The model columns of every run must be
identical (the engine's promise); a run that differs raises.

On a shared machine other processes take cores from the workers, and the wall
efficiency then measures the load as much as the engine. So each line also gives a
CPU-normalised efficiency. A worker's share of the run's wall time ``n T`` is spent
running (its CPU seconds ``W``, ``run.json`` ``task_cpu_s``), ready but waiting for a
core another process holds (its runqueue wait ``D``, ``task_wait_s``), or idle (``I = n T
- W - D``: no chunk to run, the engine's scheduling loss). On a quiet machine the wait
vanishes and the run takes ``(W + I) / n``, so ``adjusted = (W(1) + I(1)) / (W(n) +
I(n))``: it falls below 100 % when chunking costs CPU (``work``, W(n) / W(1), above
100 %) or workers stand idle (``idle``). The load average before and after is printed.

Targets (issue 23): efficiency >= 90 % on 2 workers and >= 80 % on 16 workers, for the
full fig11 (orders 11 and 13, 1000 trials per point). The default is a smaller version
with the same structure: orders 11 and 13 on the same grids with up to 100 trials per
point (a look at 64), about a third of the full run's CPU (about 1 CPU-minute per run);
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

#: The default (reduced) configuration and the full one of the issue; the grid alone (no
#: refining rounds), the sweep whose efficiency the targets are about.
SMALL = {"channels_order11": tuple(range(25, 251, 25)),
         "channels_order13": tuple(range(100, 1001, 100)), "channels_order15": (),
         "trials": 100, "refine_rounds": 0}
FULL = {"channels_order11": tuple(range(25, 251, 25)),
        "channels_order13": tuple(range(100, 1001, 100)), "channels_order15": (),
        "trials": 1000, "refine_rounds": 0}
#: Efficiency targets by worker count (issue 23).
TARGETS = {2: 0.90, 16: 0.80}


def _model_rows(out: Path) -> list[dict]:
    drop = {c for m in FIG11.machine_columns for c in (m, f"{m}_ci95", f"{m}_best")}
    return [{k: v for k, v in row.items() if k not in drop}
            for row in read_csv(out / "results.csv").rows]


def _run(overrides: dict, workers: int) -> dict:
    """One run: wall seconds without the cluster start, that start, chunks computed, the
    workers' CPU and runqueue-wait seconds, and the model rows."""
    with tempfile.TemporaryDirectory(prefix="bench-studies-") as tmp:
        out = Path(tmp)
        res = run_study(FIG11, out, overrides=overrides, workers=workers, progress=False)
        if res.failures:
            raise RuntimeError(f"fig11 failed: {res.failures[0]}")
        info = json.loads((out / "run.json").read_text())
        return {"t": info["wall_time_s"] - info["executor_start_s"],
                "start": info["executor_start_s"], "chunks": res.computed,
                "cpu": info["task_cpu_s"], "wait": info["task_wait_s"],
                "rows": _model_rows(out)}


def main() -> None:
    full = "--full" in sys.argv or os.environ.get("CDMA_LIDAR_BENCH_FULL") == "1"
    repeats = int(os.environ.get("CDMA_LIDAR_BENCH_REPEATS", "2"))
    overrides = FULL if full else SMALL
    cores = os.cpu_count() or 1
    counts = sorted({1, 2, cores})
    points = sum(len(v) for k, v in overrides.items() if k.startswith("channels"))
    print(f"fig11 {'full' if full else 'reduced'}: {points} points x up to "
          f"{overrides['trials']} trials (orders 11 and 13, S = 50), local Dask workers "
          f"{counts} of {cores} cores, best of {repeats} interleaved; load average "
          f"{os.getloadavg()[0]:.2f}", flush=True)
    best: dict[int, dict] = {}
    reference = None
    t_start = time.monotonic()
    for _ in range(repeats):
        for n in counts:
            run = _run(overrides, n)
            print(f"    run on {n} worker(s): {run['t']:.2f} s, workers' CPU {run['cpu']:.1f} s, "
                  f"runqueue wait {run['wait']:.1f} s; load average {os.getloadavg()[0]:.2f}",
                  flush=True)
            if reference is None:
                reference = run["rows"]
            elif run["rows"] != reference:
                raise AssertionError(f"fig11 on {n} workers gave another table")
            if n not in best or run["t"] < best[n]["t"]:
                best[n] = run
    def idle(run: dict, n: int) -> float:
        return max(0.0, n * run["t"] - run["cpu"] - run["wait"])

    one = best[1]
    for n in counts:
        b = best[n]
        eff = one["t"] / (n * b["t"])
        adjusted = (one["cpu"] + idle(one, 1)) / (b["cpu"] + idle(b, n))
        target = TARGETS.get(n)
        verdict = "" if target is None else \
            f" (target {target:.0%}: {'met' if eff >= target else 'NOT met'}, adjusted " \
            f"{'met' if adjusted >= target else 'NOT met'})"
        print(f"  {n:3d} workers: {b['t']:7.2f} s (+{b['start']:.1f} s cluster start), "
              f"{b['chunks']:4d} chunks, workers' CPU {b['cpu']:7.1f} s (work "
              f"{b['cpu'] / one['cpu']:6.1%}), runqueue wait {b['wait']:6.1f} s, idle "
              f"{idle(b, n):5.1f} s, speed-up "
              f"x{one['t'] / b['t']:5.2f}, efficiency {eff:6.1%}, adjusted {adjusted:6.1%}"
              f"{verdict}")
    for n, target in TARGETS.items():
        if n > cores:
            print(f"  {n:3d} workers: efficiency not measured: this machine has {cores} cores "
                  f"(target {target:.0%})")
    print(f"tables identical across worker counts; load average {os.getloadavg()[0]:.2f} "
          f"after {time.monotonic() - t_start:.0f} s")


if __name__ == "__main__":
    main()
