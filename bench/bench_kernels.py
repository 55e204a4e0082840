"""Correlation kernels: does ``method="auto"`` pick the fastest exact kernel, everywhere?

For each configuration every registered kernel finishes the same random accumulators
(``FastReceiver.from_accumulators``, the whole chain after the accumulator); the results
must be identical. Per row: each kernel's time per call (best of N) and peak traced
memory (tracemalloc, the prepared kernel plus one call), the kernel ``auto`` chose (the
fixed operation-count constants of ``correlators/costs.py``, on the column threads
``from_accumulators`` splits the row's columns over), the fastest, and
``auto / fastest`` (target <= 1.25); ``mem x`` (auto's memory over the leanest kernel's)
is for information.

Two sets of configurations:

* the kernel grid of docs/firmware.md (``python -m bench kernels``, part of ``make
  bench``): degrees 5/11/13, S 1/4/16, K 1/40, gate 1 lag / 64 lags / whole period, plus
  wide-data, many-column (the virtual board's batches of 4, 16 and 160 paper-scene1
  columns) and many-channel rows; the full grid with ``CDMA_LIDAR_BENCH_FULL=1`` (degrees
  5-20, S 1-64, K 1-2048; long);
* random configurations off that grid, after it (``CDMA_LIDAR_BENCH_RANDOM=N``,
  default 12; ``--random`` runs only them, default 24; ``--grid`` only the grid):
  degree 5-15, S 1-16, K 1-400 (log-uniform), a gate of 1-300 lags or the whole
  period, 1-160 columns, (R, n, b) from three classes, seeded
  (``CDMA_LIDAR_BENCH_SEED``, default 0); every kernel best of 7. To stay short on a
  shared machine a draw is replaced when its accumulators exceed 32 MiB or its best
  prediction 0.3 s (printed as skipped).

A kernel whose *predicted* time is over 20x the best prediction (except auto's choice,
always run), or over 60 s, or whose predicted memory is over 2 GiB (a shared machine),
is not run (``-``); a configuration whose best prediction is over 60 s (random
configurations: 0.3 s), or whose predicted working set is over 6 GiB, is skipped. Kernels'
repeats are interleaved; a row where auto measured over 1.25x the fastest is timed again
up to twice, 2 s apart (on the shared 2-core machine a threaded BLAS call stalls for
10-250 ms whenever another process holds a core).

``--row "d9 S9 K2 Gall R100 n4 b14 C160"`` (a row's label as printed) times that row's
kernels through the chain at 1, 2, 4, ... and all the machine's threads (the
receiver's ``threads``), best of 7 interleaved across kernels and thread counts, and
prints per thread count each kernel's time, auto's choice on those column threads,
the fastest and ``time x``.

``--cpu`` times by process CPU time instead of wall time: with ``CDMA_LIDAR_THREADS=1``
the kernels' own time, which other processes' load barely moves (the constants of
``costs.py`` were fitted that way on the shared 2-core machine).

``--fit`` times each kernel alone (one thread, CPU time, best of 7) on the quick grid up
to degree 13 and K 400 and on random configurations (``CDMA_LIDAR_BENCH_RANDOM``, default
30), and prints the constants of ``costs.py`` and each kernel's ``fixed_calls`` fitted
to them (non-negative least squares on relative errors; ``ram`` from FIT_RAMS), with how
many plans the fitted and the current constants send within 1.25x of the fastest.

Environment: ``CDMA_LIDAR_BENCH_DEGREES=5,8`` runs only those degrees;
``CDMA_LIDAR_BENCH_MAX_SECONDS`` replaces the 60 s limits.
"""

from __future__ import annotations

import copy
import gc
import itertools
import math
import os
import re
import sys
import time
import tracemalloc
from collections.abc import Iterator
from dataclasses import dataclass

import numpy as np

from cdma_lidar.firmware_model.correlators import GatePlan, choose_correlator, estimates
from cdma_lidar.firmware_model.correlators.base import (
    _REGISTRY,
    blas_threads,
    column_threads,
    machine_threads,
)
from cdma_lidar.firmware_model.correlators.costs import COEFFICIENTS, Coefficients
from cdma_lidar.firmware_model.receiver import FastReceiver, ReceiverConfig, correlator_methods

SKIP_FACTOR = 20.0
SKIP_SECONDS = float(os.environ.get("CDMA_LIDAR_BENCH_MAX_SECONDS", "60"))
SKIP_BYTES = 2 << 30
#: Random configurations whose best prediction is over this (s) are drawn again.
RANDOM_MAX_SECONDS = 0.3
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


def _best_time(fn, repeats: int, clock=time.perf_counter) -> float:
    t = math.inf
    for _ in range(repeats):
        gc.collect()
        t0 = clock()
        fn()
        t = min(t, clock() - t0)
    return t


def run_case(case: Case, repeats: int, max_pred: float = SKIP_SECONDS,
             clock=time.perf_counter) -> str:
    """Measure every kernel on one grid point; returns the table row. ``clock``:
    ``time.perf_counter`` (wall) or ``time.process_time`` (``--cpu``)."""
    n = (1 << case.degree) - 1
    ns = n * case.s
    gate = ns if case.gate == 0 else min(case.gate, ns)
    chain = 8.0 * case.columns * case.k * (gate + 2) * CHAIN_ARRAYS \
        + 16.0 * case.columns * case.uid_bits * ns
    if chain > ROW_BYTES:
        return f"{case.label()} | skipped: the chain alone needs {chain / 2**30:.0f} GiB"
    cfg, codes, acc = _setup(case)
    plan = FastReceiver(cfg, codes, columns=case.columns, prepare=False).plan
    plan.threads = column_threads(case.columns, acc.size)  # as from_accumulators runs it
    chosen = choose_correlator(plan)  # nothing prepared yet: a kernel may not fit
    est = estimates(plan)
    finite = {m: e for m, e in est.items() if math.isfinite(e.seconds)}
    best_pred = min(e.seconds for e in finite.values())
    if best_pred > max_pred:
        return f"{case.label()} | skipped: best predicted {best_pred:.1f} s"
    run = {m: e for m, e in finite.items()  # auto's choice however slow
           if not ((e.seconds > SKIP_FACTOR * best_pred and m != chosen)
                   or e.seconds > SKIP_SECONDS or e.peak_bytes > SKIP_BYTES
                   or chain + e.peak_bytes > ROW_BYTES)}
    if chosen not in run:
        return f"{case.label()} | skipped: auto's {chosen} predicted over the limits"
    # fast rows: more repeats, interleaved across the kernels (a stall of the shared
    # machine then hits one repeat of each, not all of one kernel's)
    if repeats < 7:
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
            times[m] = _best_time(lambda rx=rx: rx.from_accumulators(acc), repeats, clock)
        del rx

    def measure() -> None:
        for _ in range(repeats):
            for m, rx in kept.items():
                times[m] = min(times.get(m, math.inf),
                               _best_time(lambda rx=rx: rx.from_accumulators(acc), 1,
                                          clock))

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
    ratio = times[chosen] / times[fastest]
    flag = "" if ratio <= 1.25 else "  <-- off target"
    return (f"{case.label()} | {cells} | auto={chosen:<6} fastest={fastest:<6} "
            f"time x{ratio:5.2f} mem x{mems[chosen] / lean:4.2f}{flag}")


def quick_grid() -> list[Case]:
    cases = [Case(d, s, k, g) for d, s, k, g in itertools.product(
        (5, 11, 13), (1, 4, 16), (1, 40), (1, 64, 0))]
    cases += [
        Case(11, 4, 40, 64, r=1024, uid_bits=16, adc_bits=16),  # wide data: limbs
        Case(13, 4, 40, 0, r=1024, uid_bits=16, adc_bits=16),
        Case(11, 4, 40, 64, columns=160),  # the paper frame's class
        Case(11, 4, 40, 64, columns=4), Case(11, 4, 40, 64, columns=16),  # the board's batches
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


#: Random configurations whose accumulators exceed this are drawn again (a shared machine).
RANDOM_ACC_BYTES = 32 << 20


def random_cases(seed: int) -> Iterator[Case]:
    """Configurations off the grid, drawn from ``seed`` (accumulators at most 32 MiB)."""
    rng = np.random.default_rng(seed)
    classes = [(10, 1, 12), (1024, 16, 16), (100, 4, 14)]
    while True:
        degree = int(rng.integers(5, 16))
        r, n, b = classes[int(rng.integers(0, 3))]
        gate = 0 if rng.random() < 0.25 else int(rng.integers(1, 301))
        case = Case(degree, int(rng.integers(1, 17)), int(np.exp(rng.uniform(0, math.log(400)))),
                    gate, r=r, uid_bits=n, adc_bits=b,
                    columns=int(rng.choice([1, 2, 3, 8, 20, 64, 160])))
        if 8 * case.columns * n * ((1 << degree) - 1) * case.s <= RANDOM_ACC_BYTES:
            yield case


#: ``--wide``: the ranges of issue 40's target (degrees, S, K, gate lags, R), the seed
#: (one the constants were never fitted on: --fit used 0, 1, 2, 5 and 7, --fit --wide
#: 100; seeds 44 and 45 are other such checks), and a
#: configuration whose best prediction is over WIDE_MAX_SECONDS is drawn again (printed).
WIDE_DEGREES, WIDE_S, WIDE_K, WIDE_GATES, WIDE_R = (6, 15), (1, 16), (1, 1200), (16, 1024), \
    (1, 10)
WIDE_SEED = 40
WIDE_MAX_SECONDS = 0.5
#: ``--wide``: a kernel predicted over this many times the best prediction is not timed.
WIDE_SKIP_FACTOR = 50.0


def wide_cases(seed: int) -> Iterator[Case]:
    """One-column configurations over issue 40's ranges, drawn from ``seed``: degree and
    S and R uniform, K and the gate log-uniform (the gate at most N*S), 12-bit ADC, n 1."""
    rng = np.random.default_rng(seed)

    def log_uniform(lo: int, hi: int) -> int:
        return round(math.exp(rng.uniform(math.log(lo), math.log(hi))))

    while True:
        degree = int(rng.integers(WIDE_DEGREES[0], WIDE_DEGREES[1] + 1))
        s = int(rng.integers(WIDE_S[0], WIDE_S[1] + 1))
        k = log_uniform(*WIDE_K)
        gate = min(log_uniform(*WIDE_GATES), ((1 << degree) - 1) * s)
        r = int(rng.integers(WIDE_R[0], WIDE_R[1] + 1))
        yield Case(degree, s, k, gate, r=r)


def wide_row(case: Case, repeats: int) -> tuple[str, float | None]:
    """``--wide``: every kernel worth timing through the chain (``from_accumulators``) on
    one thread (BLAS 1: the kernels' own cost, which the model predicts), process CPU
    time (on the shared 2-core machine wall times swing 2-5x with the other load), best
    of ``repeats`` interleaved; the row and auto / fastest (None: skipped)."""
    cfg, codes, acc = _setup(case)
    plan = FastReceiver(cfg, codes, columns=1, threads=1, prepare=False).plan
    chosen = choose_correlator(plan)
    est = {m: e for m, e in estimates(plan).items() if math.isfinite(e.seconds)
           and not _REGISTRY[m].whole_frame and m != "xp"}
    best = min(e.seconds for e in est.values())
    if best > WIDE_MAX_SECONDS:
        return f"{case.label()} | skipped: best predicted {best:.2f} s", None
    run = [m for m, e in est.items() if m == chosen or (
        e.seconds <= WIDE_SKIP_FACTOR * best and e.peak_bytes <= SKIP_BYTES)]
    rxs = {m: FastReceiver(cfg, codes, method=m, columns=1, threads=1) for m in run}
    want = None
    for m, rx in rxs.items():
        got = rx.from_accumulators(acc)  # warm up; and the same integers from each
        if want is None:
            want = got
        elif not all(a.same_as(b) for a, b in zip(got, want, strict=True)):
            raise AssertionError(f"{case.label()}: kernel {m} differs")
    times = dict.fromkeys(rxs, math.inf)
    for _ in range(repeats):
        for m, rx in rxs.items():
            times[m] = min(times[m], _best_time(lambda rx=rx: rx.from_accumulators(acc), 1,
                                                time.process_time))
    fastest = min(times, key=times.__getitem__)
    ratio = times[chosen] / times[fastest]
    cells = " ".join(f"{m}={times[m] * 1e3:8.2f}ms" if m in times else f"{m}={'-':>8}  "
                     for m in est)
    flag = "" if ratio <= 1.25 else "  <-- off target"
    return (f"{case.label()} | {cells} | auto={chosen:<6} fastest={fastest:<6} "
            f"auto/fastest x{ratio:5.2f}{flag}"), ratio


def run_wide(seed: int, count: int, repeats: int = 5) -> None:
    """``--wide``: ``count`` configurations of :func:`wide_cases`, a row each, then the
    worst and median auto / fastest."""
    print(f"--wide: {count} one-column configurations of seed {seed} over degrees "
          f"{WIDE_DEGREES}, S {WIDE_S}, K {WIDE_K}, gates {WIDE_GATES} lags, R {WIDE_R}; "
          f"one thread, CPU time, best of {repeats} interleaved through the chain; cost constants "
          f"{COEFFICIENTS}; load average {os.getloadavg()[0]:.2f}", flush=True)
    ratios: list[tuple[float, str]] = []
    skipped = 0
    with blas_threads(1):
        for case in wide_cases(seed):
            if len(ratios) >= count:
                break
            row, ratio = wide_row(case, repeats)
            print(row, flush=True)
            if ratio is None:
                skipped += 1
            else:
                ratios.append((ratio, case.label()))
    values = sorted(r for r, _ in ratios)
    worst = max(ratios)
    off = sum(r > 1.25 for r in values)
    print(f"--wide seed {seed}: {len(values)} rows, {skipped} drawn again (best prediction "
          f"over {WIDE_MAX_SECONDS:g} s), {off} off target; auto / fastest worst "
          f"x{worst[0]:.2f} ({' '.join(worst[1].split())}), median "
          f"x{float(np.median(values)):.2f}; load average {os.getloadavg()[0]:.2f}",
          flush=True)


#: ``--fit``: the ``ram`` ratios tried, and the largest best prediction of a plan timed.
FIT_RAMS = (1.8, 3.0, 5.0)
FIT_MAX_SECONDS = 0.3


def kernel_times(plan: GatePlan, repeats: int = 7) -> dict[str, float]:
    """Each kernel with a finite estimate within 30x of the best, called alone on random
    chip sums of the plan's shape: process CPU time on one thread (BLAS limited to 1),
    best of ``repeats`` interleaved across the kernels."""
    est = {m: e.seconds for m, e in estimates(plan).items() if math.isfinite(e.seconds)}
    best = min(est.values())
    bound = plan.y_bound if plan.y_bound is not None else 1 << 11
    y = np.random.default_rng(0).integers(-bound, bound + 1, (plan.columns, plan.s, plan.n))
    kernels = {m: _REGISTRY[m](plan) for m, t in est.items() if t <= 30 * best}
    times = dict.fromkeys(kernels, math.inf)
    with blas_threads(1):
        for kernel in kernels.values():
            kernel(y)  # warm up
        for _ in range(repeats):
            for m, kernel in kernels.items():
                times[m] = min(times[m], _best_time(lambda k=kernel: k(y), 1, time.process_time))
    return times


def _features(plan: GatePlan, ram: float) -> dict[str, np.ndarray]:
    """Per kernel: its estimate's seconds per unit of mac, byte, fft and call (its own
    fixed calls taken out), then one column per kernel for its fixed cost."""
    units = [Coefficients(1, 0, 0, 0, ram), Coefficients(0, 1, 0, 0, ram),
             Coefficients(0, 0, 1, 0, ram), Coefficients(0, 0, 0, 1, ram)]
    per = [estimates(plan, u) for u in units]
    names = list(_REGISTRY)
    out = {}
    for m in per[0]:
        row = [e[m].seconds for e in per]
        row[3] -= _REGISTRY[m].fixed_calls
        out[m] = np.array(row + [float(m == k) for k in names])
    return out


def fit(seed: int, random_n: int, wide: bool = False) -> None:
    """``--fit``: time the kernels on the quick grid (degree <= 13, K <= 400) and
    ``random_n`` random configurations, then fit :data:`.costs.COEFFICIENTS` and each
    kernel's ``fixed_calls`` (non-negative least squares on the relative errors, the
    ``ram`` of FIT_RAMS that puts the most plans within 1.25x) and print them.
    ``wide``: ``random_n`` configurations of :func:`wide_cases` of ``seed`` instead (one
    column, one thread: the plans ``--wide`` checks; fit on one seed, check on another)."""
    from scipy.optimize import nnls

    if wide:
        draws = wide_cases(seed)
        cases = [next(draws) for _ in range(random_n)]
        what = f"{random_n} --wide configurations of seed {seed}"
    else:
        cases = [c for c in quick_grid() if c.degree <= 13 and c.k <= 400]
        draws = random_cases(seed)
        cases += [next(draws) for _ in range(random_n)]
        what = f"quick grid, {random_n} random of seed {seed}"
    print(f"--fit: {len(cases)} plans ({what}); load average {os.getloadavg()[0]:.2f}",
          flush=True)
    data = []
    for case in cases:
        cfg, codes, _ = _setup(case)
        plan = FastReceiver(cfg, codes, columns=case.columns, prepare=False,
                            **({"threads": 1} if wide else {})).plan
        if min(e.seconds for e in estimates(plan).values()) > FIT_MAX_SECONDS:
            continue
        times = kernel_times(plan)
        data.append((plan, times))
        print(f"{case.label()} | " + " ".join(f"{m}={t * 1e3:.3f}ms" for m, t in times.items()),
              flush=True)
    names = list(_REGISTRY)

    def within(pick) -> tuple[int, float]:
        ratios = [times[pick(plan, times)] / min(times.values()) for plan, times in data]
        return sum(r <= 1.25 for r in ratios), max(ratios)

    best = None
    for ram in FIT_RAMS:
        feats = [_features(plan, ram) for plan, _ in data]
        a = np.array([f[m] / t for f, (_, times) in zip(feats, data, strict=True)
                      for m, t in times.items()])
        coef, _ = nnls(a, np.ones(len(a)))
        table = dict(zip((id(plan) for plan, _ in data), feats, strict=True))

        def pick(plan, times, coef=coef, table=table):
            return min(times, key=lambda name: float(table[id(plan)][name] @ coef))

        score = within(pick)
        print(f"ram {ram}: mac={coef[0]:.3g} byte={coef[1]:.3g} fft={coef[2]:.3g} "
              f"call={coef[3]:.3g}, fixed s " + " ".join(
                  f"{k}={c:.3g}" for k, c in zip(names, coef[4:], strict=True))
              + f": {score[0]} of {len(data)} within 1.25x, worst x{score[1]:.2f}")
        if best is None or score[0] > best[0][0]:
            best = (score, ram, coef)
    now = within(lambda plan, times: min(times, key=lambda m: estimates(plan)[m].seconds))
    (score, ram, coef) = best
    call = coef[3]
    print(f"fitted: Coefficients(mac={coef[0]:.2g}, byte={coef[1]:.3g}, fft={coef[2]:.2g}, "
          f"call={call:.2g}, ram={ram}); fixed_calls " + ", ".join(
              f"{k}={c / call:.0f}" for k, c in zip(names, coef[4:], strict=True) if c)
          + f"; {score[0]} of {len(data)} plans within 1.25x (worst x{score[1]:.2f}); the "
          f"constants in the code: {now[0]} (worst x{now[1]:.2f}); load average "
          f"{os.getloadavg()[0]:.2f}")



LABEL_RE = re.compile(r"d(\d+) S(\d+) K(\d+) G(all|\d+) R(\d+) n(\d+) b(\d+) C(\d+)")


def parse_case(label: str) -> Case | None:
    """The Case of a row's label (``Case.label()``, spacing free), or None."""
    m = LABEL_RE.fullmatch(" ".join(label.split()))
    if m is None:
        return None
    d, s, k, g, r, n, b, c = m.groups()
    return Case(int(d), int(s), int(k), 0 if g == "all" else int(g), r=int(r),
                uid_bits=int(n), adc_bits=int(b), columns=int(c))


def run_row_threads(case: Case, repeats: int = 7) -> None:
    """``--row``: one row's kernels through the chain (``from_accumulators``) at 1, 2, 4,
    ... and all the machine's threads, best of ``repeats`` interleaved; per thread count
    auto's choice on the column threads the chain splits the row's columns over."""
    cfg, codes, acc = _setup(case)
    top = machine_threads()
    counts = sorted({1, top, *(1 << i for i in range(top.bit_length()) if 1 << i <= top)})
    plan = FastReceiver(cfg, codes, columns=case.columns, prepare=False).plan
    plans = {}
    for t in counts:
        plans[t] = copy.copy(plan)
        plans[t].threads = column_threads(case.columns, acc.size, t)
    est = {m: e.seconds for m, e in estimates(plan).items()
           if math.isfinite(e.seconds) and not _REGISTRY[m].whole_frame}
    chosen = {t: choose_correlator(p) for t, p in plans.items()}
    best = min(est.values())
    methods = [m for m in est if est[m] <= SKIP_FACTOR * best or m in chosen.values()]
    print(f"{case.label()}: kernels through the chain (from_accumulators) at {counts} "
          f"threads, best of {repeats} interleaved; load average {os.getloadavg()[0]:.2f}")
    rxs = {(m, t): FastReceiver(cfg, codes, method=m, columns=case.columns, threads=t)
           for t in counts for m in methods}
    want = None
    for key, rx in rxs.items():
        got = rx.from_accumulators(acc)  # warm up, and the same integers from each
        if want is None:
            want = got
        elif not all(a.same_as(b) for a, b in zip(got, want, strict=True)):
            raise AssertionError(f"{case.label()}: {key} differs")
    times = dict.fromkeys(rxs, math.inf)
    for _ in range(repeats):
        for key, rx in rxs.items():
            times[key] = min(times[key], _best_time(lambda rx=rx: rx.from_accumulators(acc), 1))
    for t in counts:
        row = {m: times[m, t] for m in methods}
        fastest = min(row, key=row.__getitem__)
        ratio = row[chosen[t]] / row[fastest]
        print(f"threads {t:<3} column threads {plans[t].threads:<3} | "
              + " ".join(f"{m}={row[m] * 1e3:9.2f}ms" for m in methods)
              + f" | auto={chosen[t]:<6} fastest={fastest:<6} time x{ratio:5.2f}"
              + ("" if ratio <= 1.25 else "  <-- off target"))
    print(f"load average {os.getloadavg()[0]:.2f}")


def run_set(cases, label: str, repeats: int, max_pred: float, want: int | None,
            clock) -> None:
    """Measure ``cases`` (at most ``want`` rows) and print the rows and a summary line."""
    print(f"kernels on the {label}; cost constants {COEFFICIENTS}; load average "
          f"{os.getloadavg()[0]:.2f}")
    print(f"times per call (from_accumulators: despread .. peaks), best of {repeats} "
          "interleaved across the kernels"
          + ("" if repeats == 7 else " (7 when the best prediction is under 50 ms, 2 when "
             "over 1 s)") + "; memory: tracemalloc peak of preparing the kernel plus one "
          f"call; kernels predicted over {SKIP_SECONDS:g} s not run")
    worst, worst_case, n_rows, off = 0.0, "", 0, 0
    only = os.environ.get("CDMA_LIDAR_BENCH_DEGREES")
    degrees = {int(d) for d in only.split(",")} if only else None
    for case in cases:
        if want is not None and n_rows >= want:
            break
        if degrees is not None and case.degree not in degrees:
            continue
        row = run_case(case, repeats, max_pred, clock)
        print(row, flush=True)
        if "time x" in row:
            n_rows += 1
            ratio = float(row.split("time x")[1].split()[0])
            if ratio > worst:
                worst, worst_case = ratio, case.label()
            off += "off target" in row
    print(f"{label}: {n_rows} rows measured, {off} off target (auto over 1.25x the fastest); "
          f"worst auto / fastest x{worst:.2f} ({worst_case.strip()}); load average "
          f"{os.getloadavg()[0]:.2f}", flush=True)


def main() -> None:
    """The grid, random configurations off it, then issue 40's check: ``--wide`` 40 on
    :data:`WIDE_SEED`, which no constant was fitted on (``--grid``, ``--random``: one
    only; ``--wide [N]``: the check alone)."""
    full = os.environ.get("CDMA_LIDAR_BENCH_FULL") == "1"
    only_random = "--random" in sys.argv
    random_n = int(os.environ.get("CDMA_LIDAR_BENCH_RANDOM", "24" if only_random else "12"))
    seed = int(os.environ.get("CDMA_LIDAR_BENCH_SEED", "0"))
    if "--row" in sys.argv:
        at = sys.argv.index("--row") + 1
        case = parse_case(sys.argv[at]) if at < len(sys.argv) else None
        if case is None:
            print("bench kernels: --row takes a row's label, e.g. \"d9 S9 K2 Gall R100 n4 "
                  "b14 C160\"", file=sys.stderr)
            sys.exit(2)
        run_row_threads(case)
        return
    if "--fit" in sys.argv:
        fit(seed, int(os.environ.get("CDMA_LIDAR_BENCH_RANDOM", "30")), "--wide" in sys.argv)
        return
    if "--wide" in sys.argv:
        at = sys.argv.index("--wide") + 1
        count = int(sys.argv[at]) if at < len(sys.argv) and sys.argv[at].isdigit() else 40
        run_wide(int(os.environ.get("CDMA_LIDAR_BENCH_SEED", str(WIDE_SEED))), count)
        return
    clock = time.process_time if "--cpu" in sys.argv else time.perf_counter
    if "--cpu" in sys.argv:
        print("--cpu: process CPU time (run with CDMA_LIDAR_THREADS=1: the kernels' own "
              "time, which another process's load barely moves)")
    if not only_random:
        run_set(full_grid() if full else quick_grid(), "full grid" if full else "quick grid",
                3, SKIP_SECONDS, None, clock)
    if "--grid" not in sys.argv and random_n > 0:
        run_set(random_cases(seed), f"{random_n} random configurations (seed {seed})", 7,
                RANDOM_MAX_SECONDS, random_n, clock)
    if "--grid" not in sys.argv and not only_random:
        run_wide(WIDE_SEED, 40)


if __name__ == "__main__":
    main()
