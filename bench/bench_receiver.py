"""Receive chain benchmark: the paper's frame against scipy.signal.correlate, and long codes.

1. Paper frame: K = 40 degree-11 Gold codes, S = 4, R = 10, 160 columns, 64-lag
   gate (12-bit ADC). Fast path time per frame, real-time factor against the
   instrument's acquisition time (160 x 10 x 2047 chips / 62.5 Mchip/s = 52.4 ms),
   and the ratio against ``scipy.signal.correlate`` applied per channel and
   column (circular, on the R-averaged period) measured in the same run on a
   subset of columns and scaled to the frame. The baseline's gated values are
   checked equal to the fast path's. Then every registered correlation kernel
   (``correlator_methods()``) on the same frame, each checked equal to "auto".
2. Degrees 13 and 15 with the whole period as the gate (FFT path): time per
   column and peak traced memory (tracemalloc), with the scipy baseline beside.

Run: ``.venv/bin/python -m bench receiver``.
"""

from __future__ import annotations

import gc
import os
import statistics
import time
import tracemalloc

import numpy as np
from scipy import signal

from cdma_lidar.firmware_model.adc import quantise
from cdma_lidar.firmware_model.gold import gold_code
from cdma_lidar.firmware_model.pairs import PAPER_PAIR, preferred_pairs
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


def _time(fn, repeats: int) -> list[float]:
    times = []
    for _ in range(repeats):
        gc.collect()
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return times


def paper_frame() -> None:
    k, columns = 40, 160
    cfg = ReceiverConfig(adc_bits=12, samples_per_chip=4, averages=10, gate_start=100,
                         gate_len=64)
    codes = _codes(PAPER_PAIR, k)
    n = codes.shape[1]
    x = _columns(codes, cfg, columns, seed=1)
    rx = FastReceiver(cfg, codes)
    rx.frame(x[:2])  # warm up BLAS threads
    t_fast = _time(lambda: rx.frame(x), 7)
    t_plan = _time(lambda: FastReceiver(cfg, codes), 3)
    sub = 8
    t_base = _time(lambda: [_scipy_column(codes, cfg, x[c]) for c in range(sub)], 2)
    outs = rx.frame(x[:sub])
    same = all(
        np.array_equal(o.corr, _scipy_column(codes, cfg, x[c])) for c, o in enumerate(outs)
    )
    acq = columns * cfg.averages * n / CHIP_RATE_HZ
    best, med = min(t_fast), statistics.median(t_fast)
    base_frame = min(t_base) / sub * columns
    print(f"paper frame: K={k} N={n} S=4 R=10 columns={columns} gate=64 "
          f"({x.size / 1e6:.1f} M samples, correlator={rx.correlator_method})")
    print(f"  fast path       : {best * 1e3:8.1f} ms/frame (median {med * 1e3:.1f} ms over 7)")
    print(f"  plan build      : {min(t_plan) * 1e3:8.1f} ms (once per config)")
    print(f"  scipy.correlate : {base_frame * 1e3:8.1f} ms/frame "
          f"(measured on {sub} columns: {min(t_base) / sub * 1e3:.1f} ms/column)")
    print(f"  speed-up vs scipy: {base_frame / best:.0f}x; gated values equal: {same}")
    print(f"  acquisition time {acq * 1e3:.1f} ms -> real-time factor {acq / best:.2f} "
          f"(median {acq / med:.2f})")
    want = rx.frame(x)
    for method in correlator_methods()[1:]:
        rxm = FastReceiver(cfg, codes, method=method)
        tm = _time(lambda rxm=rxm: rxm.frame(x), 3)
        equal = all(a.same_as(b) for a, b in zip(rxm.frame(x), want, strict=True))
        print(f"  kernel {method:<8}: {min(tm) * 1e3:8.1f} ms/frame (best of 3), "
              f"equal to auto: {equal}")


def long_codes() -> None:
    for degree in (13, 15):
        pair = preferred_pairs(degree)[0]
        k = 40
        codes = _codes(pair, k)
        n = codes.shape[1]
        base = ReceiverConfig(adc_bits=12, samples_per_chip=4, averages=10, gate_start=0,
                              gate_len=n * 4)
        cfg = next(base.replace(out_bits=ob) for ob in range(32, 7, -1)
                   if _fits(base.replace(out_bits=ob), n))
        x = _columns(codes, cfg, 1, seed=degree)
        tracemalloc.start()
        rx = FastReceiver(cfg, codes)
        out = rx.column(x[0])
        _, peak = tracemalloc.get_traced_memory()
        tracemalloc.stop()
        t = _time(lambda rx=rx, x=x: rx.column(x[0]), 3)
        tb = _time(lambda codes=codes, cfg=cfg, x=x: _scipy_column(codes, cfg, x[0]), 1)
        same = np.array_equal(out.corr, _scipy_column(codes, cfg, x[0]))
        acq = cfg.averages * n / CHIP_RATE_HZ
        print(f"degree {degree}: K={k} N={n} S=4 R=10 gate = whole period ({n * 4} lags), "
              f"out_bits={cfg.out_bits}, correlator={rx.correlator_method}")
        print(f"  fast path {min(t) * 1e3:8.1f} ms/column, peak traced memory "
              f"{peak / 2**20:.0f} MiB; scipy.correlate {min(tb) * 1e3:.1f} ms/column "
              f"(ratio {min(tb) / min(t):.1f}x, equal: {same}); acquisition "
              f"{acq * 1e3:.2f} ms/column")


def _fits(cfg: ReceiverConfig, n: int) -> bool:
    try:
        cfg.widths(n)
    except ValueError:
        return False
    return True


def blas_rate() -> None:
    """Same-run calibration: float64 GEMM throughput of the paper frame's shape."""
    rng = np.random.default_rng(0)
    a, b = rng.random((640, 2047)), rng.random((2047, 660))
    t = min(_time(lambda: a @ b, 5))
    rate = 2 * a.size * 660 / t / 1e9
    print(f"dgemm (640x2047)@(2047x660): {t * 1e3:.1f} ms = {rate:.0f} GFLOP/s "
          "(the frame's correlation is 4 such products over 1/4 of the rows each)")


def main() -> None:
    print(f"cores: {os.cpu_count()}, load average: {os.getloadavg()[0]:.2f}")
    blas_rate()
    paper_frame()
    long_codes()


if __name__ == "__main__":
    main()
