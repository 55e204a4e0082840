"""Receive chain benchmark: the paper frame against the machine's GEMM floor, and per-kernel tables.

1. Paper frame: K = 40 degree-11 Gold codes, S = 4, R = 10, 160 columns, 64-lag gate
   (12-bit ADC). ``FastReceiver(threads=t).frame`` for every thread count t = 1 .. the
   machine's, each interleaved with its GEMM floor: one bare float64 product doing the
   frame's multiply-adds (160 x 2047 x 40 x 66 = 0.865 G; the issue's floor, target <=
   1.5) with BLAS limited to t threads; then, at the machine's thread count, float32
   products switched off (``float32_bits=0``), full-scale data (every sample at an ADC
   rail: chip sums far beyond float32's exact range, so float64 products) and the
   float32 floor; best of 9 each, every ratio within the run. A frame timed after a
   threaded product waits ``SETTLE_S`` first (OpenBLAS's workers spin ~50 ms after one)
   and is then timed twice: once straight after the pause (the table's ``after idle``:
   on this VM a core idle that long takes milliseconds to come back, which the frame
   then pays) and once right after that, warm, as the floor is timed (right
   after the frame) and as a scan's frames follow each other; the ratios use the warm
   time.
   Where the time goes: CPU ms per pass (range check, R-sum, chip sums, float32
   operands and their test, product and scatter, peaks), summed over the column
   threads, at 1 thread and at the machine's count. Also the real-time factor
   against the acquisition time (160 x 10 x 2047 chips / 62.5 Mchip/s = 52.4 ms),
   the plan build, and ``scipy.signal.correlate`` per channel and
   column (circular, on the R-summed period) on 8 columns scaled to the frame, its gated
   values checked equal. Then every registered kernel on the same frame, each checked
   equal to "auto".
2. Per configuration class (short gate / whole period, one column / a frame, 40 /
   400 / 1200 channels, degrees 11-15) and kernel: time per column, peak traced
   memory, the GEMM floor of the same correlation (N K G multiply-adds at this
   run's GEMM rate), the scipy baseline and the ratio of K one-channel calls to one
   K-channel call. Kernels predicted 20x slower than the best, or over 1 GiB, are
   left out.

3. ``--massive`` (alone): one column of issue 40's massively parallel instrument, K =
   1,200 degree-15 Gold codes (N = 32,767), S = 2, R = 4, a 64-lag gate, noise only,
   through ``FastReceiver.column`` (auto's kernel, and the per-lag ``direct`` kernel it
   replaced) against the GEMM floor of the same multiply-adds: a bare (64, N) @ (N, K)
   float32 and float64 product, best of 3 interleaved, on one thread and on the
   machine's; wall and process CPU time (on the shared machine wall times swing with the
   other load). Target (issue 40): the chain within 1.5x the floor of the float type
   its products run in.

The grid of auto's choices is ``bench_kernels``. Run: ``.venv/bin/python -m bench receiver``.
"""

from __future__ import annotations

import contextlib
import gc
import math
import os
import statistics
import sys
import time
import tracemalloc
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from scipy import signal

from cdma_lidar.firmware_model.adc import adc_limits, quantise
from cdma_lidar.firmware_model.correlators import (
    GPUCorrelator,
    register_correlator,
    unregister_correlator,
)
from cdma_lidar.firmware_model.correlators import base as correlator_base
from cdma_lidar.firmware_model.gold import gold_code
from cdma_lidar.firmware_model.pairs import PAPER_PAIR
from cdma_lidar.firmware_model.receiver import FastReceiver, ReceiverConfig, correlator_methods

CHIP_RATE_HZ = 62.5e6
FRAC_BITS = 8


def _codes(pair, k: int) -> np.ndarray:
    return np.stack([gold_code(pair[0], pair[1], i) for i in range(k)])


def _columns(codes: np.ndarray, cfg: ReceiverConfig, columns: int, seed: int) -> np.ndarray:
    """ADC samples of ``columns`` columns: K echoes at random delays and amplitudes plus noise."""
    rng = np.random.default_rng(seed)
    k, n = codes.shape
    s, r = cfg.samples_per_chip, cfg.averages
    ns = n * s
    refs = np.repeat(1 - 2 * codes.astype(np.float64), s, axis=1)
    out = np.empty((columns, r * ns), dtype=np.int16)
    for c in range(columns):
        period = np.zeros(ns)
        delays = rng.integers(0, min(ns, cfg.gate_len), k) + cfg.gate_start
        amps = rng.uniform(5.0, 40.0, k)
        for i in range(k):
            period += amps[i] * np.roll(refs[i], int(delays[i]))
        analog = np.tile(period, r) + rng.normal(0.0, 60.0, r * ns)
        fine = np.floor(analog * (1 << FRAC_BITS) + 0.5).astype(np.int64)
        out[c] = quantise(fine, FRAC_BITS, cfg.adc_bits)
    return out


def _scipy_column(codes: np.ndarray, cfg: ReceiverConfig, x: np.ndarray) -> np.ndarray:
    """Baseline: sum the R periods, scipy.signal.correlate per channel (circular: doubled period).

    Output scaling is the bench configs' (out_shift 0), then saturation to out_bits.
    """
    k, n = codes.shape
    ns = n * cfg.samples_per_chip
    avg = x.reshape(cfg.averages, ns).sum(axis=0).astype(np.float64)
    ext = np.concatenate([avg, avg])
    lags = (cfg.gate_start + np.arange(cfg.gate_len)) % ns
    res = np.empty((k, cfg.gate_len), dtype=np.int64)
    for i in range(k):
        ref = np.repeat(1 - 2 * codes[i].astype(np.float64), cfg.samples_per_chip)
        full = signal.correlate(ext, ref, mode="valid")[:ns]  # full[l] = sum ref[i] avg[i + l]
        res[i] = np.rint(full[lags]).astype(np.int64)
    top = (1 << (cfg.out_bits - 1)) - 1
    return np.clip(res, -top - 1, top)


@contextlib.contextmanager
def cpu_only():
    """Receivers built inside choose among the CPU kernels ("gpu" unregistered meanwhile),
    so that "auto" means the CPU chain in a GPU-against-CPU comparison."""
    gpu = "gpu" in correlator_methods()
    if gpu:
        unregister_correlator("gpu")
    try:
        yield
    finally:
        if gpu:
            register_correlator("gpu", GPUCorrelator)


def _time(fn, repeats: int) -> list[float]:
    times = []
    for _ in range(repeats):
        gc.collect()
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return times


def _floor_product(c: int, n: int, width: int) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(0)
    return rng.random((c, n)), rng.random((n, width))


def paper_frame() -> None:
    """The paper frame against the GEMM floor and scipy, interleaved in one run."""
    k, columns = 40, 160
    cfg = ReceiverConfig(adc_bits=12, samples_per_chip=4, averages=10, gate_start=100,
                         gate_len=64)
    codes = _codes(PAPER_PAIR, k)
    n = codes.shape[1]
    x = _columns(codes, cfg, columns, seed=1)
    with cpu_only():  # the CPU chain; the GPU, if any, is compared at the end
        rx = FastReceiver(cfg, codes, columns=columns)
        rx64 = FastReceiver(cfg, codes, columns=columns, float32_bits=0)
        per = FastReceiver(cfg, codes, columns=columns)  # its thread count set per run
    rng = np.random.default_rng(2)
    lo, hi = adc_limits(cfg.adc_bits)
    x_full = np.where(rng.random(x.shape) < 0.5, lo, hi).astype(x.dtype)
    rx.frame(x)  # warm up: buffers, threads (every call keeps to the CPU kernel chosen)
    rx.frame(x)
    rx.frame(x_full)
    rx64.frame(x)
    macs = columns * n * k * (cfg.gate_len + 2)
    # the floor: one bare float64 product doing the frame's multiply-adds (4C x N x K(G+2)/4)
    fa, fb = _floor_product(4 * columns, n, k * (cfg.gate_len + 2) // 4)
    fa32, fb32 = fa.astype(np.float32), fb.astype(np.float32)
    threads = correlator_base.default_threads()
    counts = range(1, threads + 1)
    runs: dict[object, list[float]] = {name: [] for name in ("f64", "full", "floor32")}
    for t in counts:
        runs[t], runs[("floor", t)], runs[("idle", t)] = [], [], []

    def floor_at(t: int) -> None:
        with correlator_base.blas_threads(t):
            fa @ fb

    def settle(warm: Callable[[], object] | None = None) -> None:
        """Wait out BLAS's worker threads: after a threaded product OpenBLAS's workers
        spin for tens of ms (measured: ~50 ms, a core's worth when the machine is
        quiet), and a frame timed meanwhile shares a core with them. ``warm``, if given,
        is then called once untimed (the cores back from idle)."""
        time.sleep(SETTLE_S)
        if warm is not None:
            warm()

    kern = per.kernel_for(columns)
    before = dict(getattr(kern, "products", {}))
    for _ in range(REPEATS):
        for t in counts:
            per.threads = t
            settle()
            runs[("idle", t)] += _time(lambda: per.frame(x), 1)  # straight after the pause
            runs[t] += _time(lambda: per.frame(x), 1)  # warm, as the floor right after it
            runs[("floor", t)] += _time(lambda t=t: floor_at(t), 1)
        settle(lambda: rx64.frame(x))
        runs["f64"] += _time(lambda: rx64.frame(x), 1)
        runs["full"] += _time(lambda: rx.frame(x_full), 1)
        runs["floor32"] += _time(lambda: fa32 @ fb32, 1)
    used = {d: v - before.get(d, 0) for d, v in getattr(kern, "products", {}).items()}
    t_fast = runs[threads]
    with cpu_only():
        t_plan = _time(lambda: FastReceiver(cfg, codes, columns=columns), 3)
    sub = 8
    t_base = _time(lambda: [_scipy_column(codes, cfg, x[c]) for c in range(sub)], 2)
    outs = rx.frame(x)[:sub]
    same = all(
        np.array_equal(o.corr, _scipy_column(codes, cfg, x[c])) for c, o in enumerate(outs)
    )
    acq = columns * cfg.averages * n / CHIP_RATE_HZ
    best, med, floor = min(t_fast), statistics.median(t_fast), min(runs[("floor", threads)])
    floor32 = min(runs["floor32"])
    base_frame = min(t_base) / sub * columns
    print(f"paper frame: K={k} N={n} S=4 R=10 columns={columns} gate=64 "
          f"({x.size / 1e6:.1f} M samples, correlator={rx.correlator_method}), "
          f"best of {REPEATS} interleaved; kernel products in the loop: {used}")
    print(f"  GEMM floor: ({fa.shape[0]}x{n})@({n}x{fb.shape[1]}) float64 = the frame's "
          f"{macs / 1e9:.3f} G multiply-adds, BLAS limited to the same threads "
          "(target: frame / floor <= 1.5 at every thread count)")
    print(f"  {'threads':>7} {'frame ms':>9} {'median':>7} {'floor ms':>9} {'ratio':>6} "
          f"{'GFLOP/s':>8} {'after idle':>10}")
    for t in counts:
        ft, fl = min(runs[t]), min(runs[("floor", t)])
        print(f"  {t:>7} {ft * 1e3:9.1f} {statistics.median(runs[t]) * 1e3:7.1f} "
              f"{fl * 1e3:9.1f} {ft / fl:6.2f} {2 * macs / fl / 1e9:8.0f} "
              f"{min(runs[('idle', t)]) * 1e3:10.1f}")
    print(f"  float64 only    : {min(runs['f64']) * 1e3:8.1f} ms/frame (float32_bits=0), "
          f"{min(runs['f64']) / floor:.2f}x the float64 floor ({threads} threads)")
    print(f"  full-scale data : {min(runs['full']) * 1e3:8.1f} ms/frame (every sample at an "
          f"ADC rail: float64 products), {min(runs['full']) / floor:.2f}x")
    print(f"  float32 floor   : {floor32 * 1e3:8.1f} ms: the frame is {best / floor32:.2f}x it")
    print(f"  plan build      : {min(t_plan) * 1e3:8.1f} ms (once per config; fast() keeps it)")
    print(f"  scipy.correlate : {base_frame * 1e3:8.1f} ms/frame "
          f"(measured on {sub} columns: {min(t_base) / sub * 1e3:.1f} ms/column)")
    print(f"  speed-up vs scipy: {base_frame / best:.0f}x; gated values equal: {same}")
    print(f"  acquisition time {acq * 1e3:.1f} ms -> real-time factor {acq / best:.2f} "
          f"(median {acq / med:.2f})")
    stages(cfg, codes, x, columns, threads)
    want = rx.frame(x)
    for method in correlator_methods()[1:]:
        rxm = FastReceiver(cfg, codes, method=method)
        tm = _time(lambda rxm=rxm: rxm.frame(x), 3)
        equal = all(a.same_as(b) for a, b in zip(rxm.frame(x), want, strict=True))
        print(f"  kernel {method:<8}: {min(tm) * 1e3:8.1f} ms/frame (best of 3, "
              f"{min(tm) / floor:.2f}x the floor), equal to auto: {equal}")
    gpu_vs_cpu(cfg, codes, x, rx)


#: The passes of ``FastReceiver.frame`` timed by :func:`stages` (receiver, then kernel
#: methods; the kernel's product and scatter are ``_run``; ``_float32_operands`` is the
#: float32 operand copies and their exactness test, ``_fill`` every operand copy (the
#: float32 ones are counted inside ``_float32_operands`` too).
STAGES = ("_check_range", "_accumulate_into", "_chip_domain", "_post")
KERNEL_STAGES = ("_float32_operands", "_fill", "_run")


def stages(cfg: ReceiverConfig, codes: np.ndarray, x: np.ndarray, columns: int,
           threads: int) -> None:
    """Where the frame's time goes: CPU seconds per pass (summed over the column threads,
    best of ``REPEATS`` frames each), at 1 thread and at ``threads``, with the frame's
    process CPU and wall time. The passes are timed by wrapping one receiver's methods
    (its own receiver: the frames timed above ran unwrapped)."""
    for t in sorted({1, threads}):
        with cpu_only():
            rx = FastReceiver(cfg, codes, columns=columns, threads=t)
        best = _stage_times(rx, rx.kernel_for(columns), x)
        parts = ", ".join(f"{name.strip('_')} {v * 1e3:.1f}" for name, v in best.items())
        print(f"  stages, {t} thread(s), ms best of {REPEATS}: {parts}")


def _stage_times(rx: FastReceiver, kern: object, x: np.ndarray) -> dict[str, float]:
    import threading

    spent: dict[str, float] = {}
    lock = threading.Lock()

    def timed(name: str, fn):
        def call(*args, **kwargs):
            t0 = time.thread_time()
            try:
                return fn(*args, **kwargs)
            finally:
                with lock:
                    spent[name] = spent.get(name, 0.0) + time.thread_time() - t0
        return call

    wrapped = [(obj, name) for obj, names in ((rx, STAGES), (kern, KERNEL_STAGES))
               for name in names if hasattr(obj, name)]
    for obj, name in wrapped:
        setattr(obj, name, timed(name, getattr(obj, name)))
    try:
        rx.frame(x)
        best: dict[str, float] = {}
        for _ in range(REPEATS):
            time.sleep(SETTLE_S)
            rx.frame(x)  # the cores back from idle, as in the table above
            spent.clear()
            c0, w0 = time.process_time(), time.perf_counter()
            rx.frame(x)
            spent["frame CPU"] = time.process_time() - c0
            spent["frame wall"] = time.perf_counter() - w0
            for name, v in spent.items():
                best[name] = min(best.get(name, math.inf), v)
    finally:
        for obj, name in wrapped:
            del obj.__dict__[name]  # the class's method again
    return best


def gpu_vs_cpu(cfg: ReceiverConfig, codes: np.ndarray, x: np.ndarray,
               cpu: FastReceiver) -> None:
    """The "gpu" kernel against the CPU chain on the same frame, when a GPU exists."""
    if "gpu" not in correlator_methods():
        print("  GPU vs CPU      : no GPU (CuPy not installed, or no CUDA device found)")
        return
    gpu = FastReceiver(cfg, codes, method="gpu", columns=x.shape[0])
    gpu.frame(x)  # compile and warm up
    t_gpu, t_cpu = [], []
    for _ in range(REPEATS):
        t_gpu += _time(lambda: gpu.frame(x), 1)
        t_cpu += _time(lambda: cpu.frame(x), 1)
    equal = all(a.same_as(b) for a, b in zip(gpu.frame(x), cpu.frame(x), strict=True))
    print(f"  GPU vs CPU      : gpu {min(t_gpu) * 1e3:.2f} ms/frame (copies included), "
          f"CPU ({cpu.correlator_method}) {min(t_cpu) * 1e3:.2f} ms: "
          f"{min(t_cpu) / min(t_gpu):.1f}x; equal: {equal}")


REPEATS = 9
#: Pause (s) before a frame timed after a threaded BLAS call (its workers spin meanwhile).
SETTLE_S = 0.15
#: Kernels other than auto's choice predicted to need more memory are not run (shared machine).
MAX_BYTES = 1 << 30


@dataclass(frozen=True)
class Row:
    """One configuration class of the per-kernel tables."""

    label: str
    degree: int
    k: int
    gate: int  # 0: the whole period
    columns: int = 1


#: Configuration classes: short gates and whole periods, one column and frames, many channels.
CLASSES = (
    Row("paper frame, 64-lag gate", 11, 40, 64, 160),
    Row("one column, 64-lag gate", 13, 40, 64),
    Row("one column, whole period", 13, 40, 0),
    Row("one column, whole period", 15, 40, 0),
    Row("many channels, 64-lag gate", 13, 400, 64),
    Row("many channels, whole period", 13, 400, 0),
    Row("many channels, 64-lag gate", 15, 1200, 64),
    Row("many channels, whole period", 15, 1200, 0),
)


def _scipy_channels(codes: np.ndarray, cfg: ReceiverConfig, d: np.ndarray,
                    channels: int) -> float:
    """Best time of scipy.signal.correlate (circular via a doubled period) on ``channels``."""
    ns = d.size
    ext = np.concatenate([d, d]).astype(np.float64)
    lags = (cfg.gate_start + np.arange(cfg.gate_len)) % ns

    def run() -> None:
        for i in range(channels):
            ref = np.repeat(1 - 2 * codes[i].astype(np.float64), cfg.samples_per_chip)
            np.rint(signal.correlate(ext, ref, mode="valid")[:ns][lags])

    return min(_time(run, 2))


def kernel_tables() -> None:
    """Per configuration class and kernel: time per column, memory, GEMM floor, scipy."""
    from cdma_lidar.firmware_model.correlators import estimates

    rng = np.random.default_rng(3)
    fa, fb = _floor_product(512, 2048, 512)
    rate = min(_time(lambda: fa @ fb, 5)) / (512 * 2048 * 512)  # s per multiply-add
    print(f"per-kernel tables (S=4, R=10, 12-bit; GEMM rate this run "
          f"{2 / rate / 1e9:.0f} GFLOP/s; floor = the correlation's N K G multiply-adds "
          "at that rate; scipy: signal.correlate per channel, measured on <= 8 channels "
          "and scaled; '1 ch x K': the same kernel on one channel, times K)")
    print(f"{'class':<30} {'deg':>3} {'K':>5} {'lags':>6} {'C':>4} {'kernel':<7} "
          f"{'ms/column':>10} {'MiB':>7} {'floor ms':>9} {'x floor':>8} {'scipy ms':>9} "
          f"{'x scipy':>8} {'1ch x K':>8}")
    for row in CLASSES:
        n = (1 << row.degree) - 1
        ns = n * 4
        gate = ns if row.gate == 0 else row.gate
        cfg = ReceiverConfig(samples_per_chip=4, averages=10, gate_start=0 if row.gate == 0
                             else 1000, gate_len=gate, out_bits=24)
        codes = rng.integers(0, 2, (row.k, n), dtype=np.uint8)
        acc = rng.integers(-20480, 20471, (row.columns, 1, ns))
        auto = FastReceiver(cfg, codes, columns=row.columns)
        est = estimates(auto.plan)
        best_pred = min(e.seconds for e in est.values())
        floor = rate * n * row.k * gate
        sub = min(8, row.k)
        scipy_col = _scipy_channels(codes, cfg, acc[0, 0], sub) * row.k / sub
        for method, e in est.items():
            if method != auto.correlator_method and (e.seconds > 20 * best_pred
                                                     or e.peak_bytes > MAX_BYTES):
                continue
            tracemalloc.start()
            rx = FastReceiver(cfg, codes, method=method, columns=row.columns)
            rx.from_accumulators(acc)
            peak = tracemalloc.get_traced_memory()[1]
            tracemalloc.stop()
            t = min(_time(lambda rx=rx, a=acc: rx.from_accumulators(a), 3)) / row.columns
            one = FastReceiver(cfg, codes[:1], method=method, columns=row.columns)
            t1 = min(_time(lambda o=one, a=acc: o.from_accumulators(a), 3)) / row.columns
            tag = "*" if method == auto.correlator_method else " "
            print(f"{row.label:<30} {row.degree:>3} {row.k:>5} {gate:>6} {row.columns:>4} "
                  f"{method + tag:<7} {t * 1e3:10.2f} {peak / 2**20:7.1f} {floor * 1e3:9.2f} "
                  f"{t / floor:8.2f} {scipy_col * 1e3:9.1f} {scipy_col / t:8.1f} "
                  f"{t1 * row.k / t:7.1f}x", flush=True)
    print("(* = auto's choice; '1ch x K' > 1: the K-channel call is that much cheaper than "
          "K one-channel calls)")


MASSIVE = {"degree": 15, "k": 1200, "s": 2, "r": 4, "gate": 64}


def massive_column(repeats: int = 3) -> None:
    """``--massive``: one column at K = 1,200, degree 15 against its GEMM floor."""
    from cdma_lidar.firmware_model.gold import gold_codes
    from cdma_lidar.firmware_model.pairs import preferred_pairs

    m = MASSIVE
    pu, pv = preferred_pairs(m["degree"])[0]
    codes = gold_codes(pu, pv, range(m["k"]))
    n = codes.shape[1]
    cfg = ReceiverConfig(samples_per_chip=m["s"], averages=m["r"], gate_start=n,
                         gate_len=m["gate"])
    rng = np.random.default_rng(0)
    fine = np.floor(rng.normal(0.0, 60.0, cfg.column_samples(n)) * (1 << FRAC_BITS) + 0.5)
    x = quantise(fine.astype(np.int64), FRAC_BITS, cfg.adc_bits)
    print(f"massive column: K={m['k']} N={n} S={m['s']} R={m['r']} gate={m['gate']} "
          f"(12-bit noise, sigma 60 LSB); GEMM floor ({m['gate']}x{n})@({n}x{m['k']}) = "
          f"{m['gate'] * n * m['k'] / 1e9:.2f} G multiply-adds; best of {repeats}, "
          f"wall / CPU ms; load average {os.getloadavg()[0]:.2f}")
    floors = {dt: (rng.standard_normal((m["gate"], n)).astype(dt),
                   (1 - 2 * codes.astype(dt)).T) for dt in (np.float32, np.float64)}
    want = None
    for threads in sorted({1, correlator_base.default_threads()}):
        rxs = {name: FastReceiver(cfg, codes, method=name, threads=threads)
               for name in ("auto", "direct")}
        for name, rx in rxs.items():
            got = rx.column(x)  # prepare the kernel; and the same integers from both
            want = got if want is None else want
            if not got.same_as(want):
                raise AssertionError(f"massive column: {name} differs")
        kernel = rxs["auto"].kernel_for(1)
        d = x.reshape(cfg.averages, -1).sum(axis=0, dtype=np.int64)  # one period, uid 1
        single = kernel.plan.float32_certain() or (
            kernel.takes_bound and int(np.abs(d).sum()) < kernel.plan.float32_limit())
        auto, direct = rxs["auto"], rxs["direct"]
        times: dict[str, list[float]] = {}

        def clocked(fn) -> tuple[float, float]:
            w0, c0 = time.perf_counter(), time.process_time()
            fn()
            return time.perf_counter() - w0, time.process_time() - c0

        with correlator_base.blas_threads(threads):
            for i in range(repeats):
                for dt, (a, b) in floors.items():
                    times.setdefault(np.dtype(dt).name, []).append(
                        clocked(lambda a=a, b=b: a @ b))
                times.setdefault("chain", []).append(clocked(lambda rx=auto: rx.column(x)))
                if i == 0:  # the per-lag kernel takes seconds: once
                    times["direct"] = [clocked(lambda rx=direct: rx.column(x))]
        best = {k: (min(w for w, _ in v), min(c for _, c in v)) for k, v in times.items()}
        ch, f32, f64 = best["chain"], best["float32"], best["float64"]
        print(f"  threads {threads}: chain (auto: {kernel.method}) {ch[0] * 1e3:7.1f} / "
              f"{ch[1] * 1e3:7.1f} ms; floor float32 {f32[0] * 1e3:7.1f} / {f32[1] * 1e3:7.1f}"
              f", float64 {f64[0] * 1e3:7.1f} / {f64[1] * 1e3:7.1f}; chain / floor32 "
              f"x{ch[0] / f32[0]:.2f} / x{ch[1] / f32[1]:.2f}, / floor64 x{ch[0] / f64[0]:.2f}"
              f" / x{ch[1] / f64[1]:.2f}; direct {best['direct'][0] * 1e3:7.1f} / "
              f"{best['direct'][1] * 1e3:7.1f} ms (x{best['direct'][1] / ch[1]:.1f} the chain, "
              f"CPU); products in {'float32' if single else 'float64'}")
    print(f"load average {os.getloadavg()[0]:.2f}")


def main() -> None:
    if "--massive" in sys.argv:
        massive_column()
        return
    print(f"cores: {os.cpu_count()} ({correlator_base.machine_threads()} usable, receive chain "
          f"threads {correlator_base.default_threads()}), load average: "
          f"{os.getloadavg()[0]:.2f}")
    paper_frame()
    kernel_tables()


if __name__ == "__main__":
    main()
