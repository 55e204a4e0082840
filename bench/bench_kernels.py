"""Correlation kernels: does ``method="auto"`` pick the fastest exact kernel, everywhere?

For each configuration of a grid (degree, S, K, gate, R, UID bits, columns per
call) every registered kernel finishes the same random accumulators
(``FastReceiver.from_accumulators``, the whole chain after the accumulator); the
results must be identical. Per row: each kernel's time per call (best of N) and
peak traced memory (tracemalloc, the prepared kernel plus one call), the kernel
``auto`` chose, the fastest, ``auto / fastest`` (target <= 1.25) and ``auto's memory /
leanest`` (target <= 2).

The two targets conflict where the fastest kernel needs more than 2x the leanest's
memory (or 64 MiB more): auto cannot be both. Its rule then takes the fastest kernel
within 1 GiB of the leanest if that is at least 4x faster than the best within the
memory target (``(memory traded: ...)``, the row's memory target is then that 1 GiB),
else the best within the target: ``time x`` is auto over the kernel the rule names,
measured; ``all x`` auto over the fastest of all, printed with ``(fastest needs Nx
memory)`` where that one was not worth its memory. The summary counts both kinds.

A kernel whose *predicted* time is over 20x the best prediction (except auto's choice
and the leanest kernel, always run), or over 60 s, or
whose predicted memory is over 2 GiB (a shared machine), is not run (``-``); a
configuration whose best prediction is over 60 s, or whose predicted working set (the
chain's (C, K, G) arrays, the accumulators and the largest kernel run) is over 6 GiB,
is skipped.

Quick grid (``python -m bench kernels``, part of ``make bench``): degrees 5/11/13,
S 1/4/16, K 1/40, gate 1 lag / 64 lags / whole period, plus wide-data, many-column
and many-channel rows. Full grid: ``CDMA_LIDAR_BENCH_FULL=1 python -m bench kernels``
(degrees 5-20, S 1-64, K 1-2048; long). Rows where auto measured over 1.25x the
fastest are timed again up to twice, 2 s apart, keeping each kernel's best (on the
shared 2-core machine a threaded BLAS call stalls for 10-250 ms whenever another
process holds a core).

Environment: ``CDMA_LIDAR_BENCH_DEGREES=5,8`` runs only those degrees;
``CDMA_LIDAR_BENCH_MAX_SECONDS`` replaces the 60 s limits (e.g. 5 for a full grid
that finishes in about an hour).

The cost model's coefficients are the calibration cache's or the built-in ones
(``python -m cdma_lidar.firmware_model.correlators.costs --show``).
"""

from __future__ import annotations

import gc
import itertools
import math
import os
import time
import tracemalloc
from dataclasses import dataclass

import numpy as np

from cdma_lidar.firmware_model.correlators import choose_correlator, estimates
from cdma_lidar.firmware_model.correlators.costs import (
    MEMORY_FLOOR,
    MEMORY_HEADROOM,
    MEMORY_SLACK,
    TRADE_SPEEDUP,
    cache_path,
    coefficients,
)
from cdma_lidar.firmware_model.receiver import FastReceiver, ReceiverConfig, correlator_methods

SKIP_FACTOR = 20.0
SKIP_SECONDS = float(os.environ.get("CDMA_LIDAR_BENCH_MAX_SECONDS", "60"))
SKIP_BYTES = 2 << 30
#: A row predicted to need more than this in all is skipped (24 GB shared by two users).
ROW_BYTES = 6 << 30
#: A row whose auto kernel measured over 1.25x the fastest is timed again this many
#: times, RETRY_PAUSE s apart, keeping each kernel's best: threaded BLAS calls stall for
#: 10-250 ms while another process holds a core, which no repeat within 50 ms escapes.
RETRIES = 2
RETRY_PAUSE = 2.0
#: (C, K, G + 2) int64 arrays the chain holds at once after the kernel (raw, the output,
#: its magnitudes, the noise squares, the returned gate copy) plus the masks.
CHAIN_ARRAYS = 6


@dataclass(frozen=True)
class Case:
    """One grid point. ``gate``: 1, 64 or 0 (the whole period)."""

    degree: int
    s: int
    k: int
    gate: int
    r: int = 10
    uid_bits: int = 1
    adc_bits: int = 12
    columns: int = 1

    def label(self) -> str:
        g = "all" if self.gate == 0 else str(self.gate)
        return (f"d{self.degree:<2} S{self.s:<2} K{self.k:<4} G{g:<4} R{self.r:<4} "
                f"n{self.uid_bits:<2} b{self.adc_bits:<2} C{self.columns:<3}")


def _setup(case: Case) -> tuple[ReceiverConfig, np.ndarray, np.ndarray]:
    n = (1 << case.degree) - 1
    ns = n * case.s
    gate = ns if case.gate == 0 else min(case.gate, ns)
    cfg = ReceiverConfig(adc_bits=case.adc_bits, samples_per_chip=case.s, averages=case.r,
                         uid_bits=case.uid_bits, gate_start=ns // 3 if gate < ns else 0,
                         gate_len=gate, out_bits=32)
    rng = np.random.default_rng(case.degree * 1000 + case.s)
    codes = rng.integers(0, 2, (case.k, n), dtype=np.uint8)
    lo, hi = -(1 << (case.adc_bits - 1)), (1 << (case.adc_bits - 1)) - 1
    acc = rng.integers(case.r * lo, case.r * hi + 1, (case.columns, case.uid_bits, ns),
                       dtype=np.int64)
    return cfg, codes, acc


def _best_time(fn, repeats: int) -> float:
    t = math.inf
    for _ in range(repeats):
        gc.collect()
        t0 = time.perf_counter()
        fn()
        t = min(t, time.perf_counter() - t0)
    return t


def run_case(case: Case, repeats: int) -> str:
    """Measure every kernel on one grid point; returns the table row."""
    n = (1 << case.degree) - 1
    ns = n * case.s
    gate = ns if case.gate == 0 else min(case.gate, ns)
    chain = 8.0 * case.columns * case.k * (gate + 2) * CHAIN_ARRAYS \
        + 16.0 * case.columns * case.uid_bits * ns
    if chain > ROW_BYTES:
        return f"{case.label()} | skipped: the chain alone needs {chain / 2**30:.0f} GiB"
    cfg, codes, acc = _setup(case)
    plan = FastReceiver(cfg, codes, columns=case.columns, prepare=False).plan
    chosen = choose_correlator(plan)  # nothing prepared yet: a kernel may not fit
    est = estimates(plan)
    finite = {m: e for m, e in est.items() if math.isfinite(e.seconds)}
    best_pred = min(e.seconds for e in finite.values())
    if best_pred > SKIP_SECONDS:
        return f"{case.label()} | skipped: best predicted {best_pred:.0f} s"
    leanest = min(finite, key=lambda m: finite[m].peak_bytes)
    run = {m: e for m, e in finite.items()  # auto's choice and the leanest however slow
           if not ((e.seconds > SKIP_FACTOR * best_pred and m not in (chosen, leanest))
                   or e.seconds > SKIP_SECONDS or e.peak_bytes > SKIP_BYTES
                   or chain + e.peak_bytes > ROW_BYTES)}
    if chosen not in run:
        return f"{case.label()} | skipped: auto's {chosen} predicted over the limits"
    # fast rows: more repeats, interleaved across the kernels (a stall of the shared
    # machine then hits one repeat of each, not all of one kernel's)
    repeats = 7 if best_pred < 0.05 else repeats if best_pred < 1.0 else min(repeats, 2)
    together = chain + sum(run[m].peak_bytes for m in run) <= ROW_BYTES
    times: dict[str, float] = {}
    mems: dict[str, float] = {}
    kept: dict[str, FastReceiver] = {}
    want = None
    for m in run:
        gc.collect()
        tracemalloc.start()
        rx = FastReceiver(cfg, codes, method=m, columns=case.columns)
        got = rx.from_accumulators(acc)
        mems[m] = tracemalloc.get_traced_memory()[1]
        tracemalloc.stop()
        if want is None:
            want = got
        elif not all(a.same_as(b) for a, b in zip(got, want, strict=True)):
            raise AssertionError(f"{case.label()}: kernel {m} differs")
        if together:
            kept[m] = rx
        else:
            times[m] = _best_time(lambda rx=rx: rx.from_accumulators(acc), repeats)
        del rx

    def measure() -> None:
        for _ in range(repeats):
            for m, rx in kept.items():
                times[m] = min(times.get(m, math.inf),
                               _best_time(lambda rx=rx: rx.from_accumulators(acc), 1))

    measure()
    for _ in range(RETRIES):  # a stall of the shared machine passes; a wrong choice stays
        if not kept or times[chosen] <= 1.25 * min(times.values()):
            break
        time.sleep(RETRY_PAUSE)
        measure()
    kept.clear()
    fastest = min(times, key=times.__getitem__)
    cells = " ".join(
        f"{m}={times[m] * 1e3:9.2f}ms/{mems.get(m, math.nan) / 2**20:6.1f}MiB" if m in times
        else f"{m}={'-':>9}  {'':>9}" for m in correlator_methods()[1:])
    lean = min(mems.values())
    cap = max(MEMORY_SLACK * lean, lean + MEMORY_FLOOR)
    feasible = [m for m in times if mems[m] <= cap]
    best = min(feasible, key=times.__getitem__)
    # auto's rule on the measured figures: memory is traded for a 4x speed-up within 1 GiB
    roomy = [m for m in times if mems[m] <= lean + MEMORY_HEADROOM]
    trade = min(roomy, key=times.__getitem__)
    traded = trade != best and times[trade] * TRADE_SPEEDUP <= times[best]
    speedup = times[best] / times[trade]
    if traded:
        best = trade
    ratio = times[chosen] / times[best]
    ratio_all = times[chosen] / times[fastest]
    mem_ratio = mems[chosen] / lean
    mem_ok = mems[chosen] <= (lean + MEMORY_HEADROOM if traded else cap)
    flag = "" if ratio <= 1.25 and mem_ok else "  <-- off target"
    note = (f" (memory traded: {best} x{mems[best] / lean:.1f} the leanest, "
            f"+{(mems[best] - lean) / 2**20:.0f} MiB, for x{speedup:.0f} speed)" if traded
            else "" if best == fastest else
            f" (fastest {fastest} needs {mems[fastest] / lean:.1f}x memory)")
    return (f"{case.label()} | {cells} | auto={chosen:<6} best={best:<6} "
            f"time x{ratio:5.2f} mem x{mem_ratio:4.2f} all x{ratio_all:5.2f}{note}{flag}")


def quick_grid() -> list[Case]:
    cases = [Case(d, s, k, g) for d, s, k, g in itertools.product(
        (5, 11, 13), (1, 4, 16), (1, 40), (1, 64, 0))]
    cases += [
        Case(11, 4, 40, 64, r=1024, uid_bits=16, adc_bits=16),  # wide data: limbs
        Case(13, 4, 40, 0, r=1024, uid_bits=16, adc_bits=16),
        Case(11, 4, 40, 64, columns=160),  # the paper frame's class
        Case(11, 16, 40, 1024, columns=32),
        Case(13, 4, 400, 64), Case(13, 4, 400, 0),  # many channels
        Case(15, 4, 1200, 64),
        Case(18, 64, 1, 64), Case(18, 64, 4, 64), Case(18, 16, 4, 64),  # the cases
    ]
    return cases


def full_grid() -> list[Case]:
    cases = []
    rs = itertools.cycle([(10, 1, 12), (1024, 16, 16), (100, 4, 14)])
    for d, s, k, g in itertools.product((5, 8, 11, 13, 15, 18, 20), (1, 4, 16, 64),
                                        (1, 40, 400, 2048), (1, 64, 0)):
        r, n, b = next(rs)
        cases.append(Case(d, s, k, g, r=r, uid_bits=n, adc_bits=b))
    return cases


def main() -> None:
    full = os.environ.get("CDMA_LIDAR_BENCH_FULL") == "1"
    src = cache_path() if cache_path().is_file() else "built-in defaults"
    print(f"kernel grid ({'full' if full else 'quick'}); cost coefficients {coefficients()} "
          f"from {src}; load average {os.getloadavg()[0]:.2f}")
    print("times per call (from_accumulators: despread .. peaks), best of 3 interleaved across "
          "the kernels (7 when the best prediction is under 50 ms, 2 when over 1 s); memory: "
          "tracemalloc peak of preparing the kernel plus one "
          f"call; kernels predicted over {SKIP_SECONDS:g} s not run")
    worst, worst_mem, worst_all, n_rows, conflicts, traded, off = 0.0, 0.0, 0.0, 0, 0, 0, 0
    only = os.environ.get("CDMA_LIDAR_BENCH_DEGREES")
    degrees = {int(d) for d in only.split(",")} if only else None
    for case in full_grid() if full else quick_grid():
        if degrees is not None and case.degree not in degrees:
            continue
        row = run_case(case, repeats=3)
        print(row, flush=True)
        if "time x" in row:
            n_rows += 1
            worst = max(worst, float(row.split("time x")[1].split()[0]))
            worst_mem = max(worst_mem, float(row.split("mem x")[1].split()[0]))
            worst_all = max(worst_all, float(row.split("all x")[1].split()[0]))
            conflicts += "needs" in row
            traded += "traded" in row
            off += "off target" in row
    print(f"{n_rows} rows measured, {off} off target: worst auto / best kernel by the rule "
          f"x{worst:.2f} (target 1.25), worst auto / leanest memory x{worst_mem:.2f} "
          f"(target 2, or within 64 MiB; traded for a 4x speed-up within 1 GiB on {traded} "
          f"rows); {conflicts} rows where the fastest kernel needs over 2x the leanest memory "
          f"and is under 4x faster (auto / that fastest: worst x{worst_all:.2f})")


if __name__ == "__main__":
    main()
