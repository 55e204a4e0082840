"""Eq. 29 in real time? Code periods per second of the receive chain against the instrument.

The paper's eq. 29 configuration (Shen, Lim and Zhou, "Identity-enabled CDMA LiDAR for
massively parallel ranging with a single-element receiver", Supplementary Note 8):
1 Gchip/s, degree-13 Gold codes (N = 8191), one sample per chip (S = 1), so one code
period every 8.191 us: real time is 1e9 / 8191 = 122,085 periods per second. Each
period is one column here (R = 1, one UID period, 12-bit ADC), correlated over a
64-lag gate and over the whole period, at K = 40, 400 and 1000 channels.

Per row and device: the correlation kernel alone (chip sums in, exact int64 ``raw``
out, host to host) and the whole chain after it (``FastReceiver.frame``: range
check, kernel, peaks, noise floor), periods per second, the real-time factor
(periods per second / 122,085), and the multiply-adds per second real time needs
with a gated product (N K (G + 2) per period). Exactness is checked on a sample of
periods: the GPU kernel (or, without a GPU, its numpy twin ``"xp"``, where the
product is small enough for this machine) against the CPU chain, bit for bit.
The batch of periods per call grows until a call takes about 0.2 s (at most
:data:`MAX_PERIODS`); best of 3. Run: ``.venv/bin/python -m bench realtime``.
"""

from __future__ import annotations

import contextlib
import os
import time

import numpy as np

from cdma_lidar.firmware_model.correlators import base as correlator_base
from cdma_lidar.firmware_model.gold import gold_codes
from cdma_lidar.firmware_model.pairs import preferred_pairs
from cdma_lidar.firmware_model.receiver import FastReceiver, ReceiverConfig, correlator_methods

from .bench_receiver import cpu_only

CHIP_RATE_HZ = 1e9
DEGREE = 13
CHANNELS = (40, 400, 1000)
#: Largest batch of periods per call, and of its (C, K, G + 2) int64 outputs (bytes).
MAX_PERIODS = 1024
MAX_OUTPUT_BYTES = 1 << 30
#: A call is timed on a batch grown until it takes about this long (s).
TARGET_SECONDS = 0.2
#: The numpy twin is checked against the CPU chain only below this many multiply-adds.
XP_CHECK_MACS = 6e9
#: H100 SXM data-sheet peaks for the roofline lines: dense int8 tensor-core operations,
#: float64 tensor-core FLOP/s, HBM3 bytes/s, PCIe 5 x16 bytes/s per direction.
H100_INT8_OPS = 1979e12
H100_FP64_FLOPS = 67e12
H100_HBM_BYTES = 3.35e12
PCIE5_BYTES = 64e9


def _best(fn, repeats: int = 3) -> float:
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return min(times)


def _samples(rng: np.random.Generator, periods: int, ns: int) -> np.ndarray:
    """12-bit ADC codes, noise-like: the kernels' time does not depend on the values."""
    return rng.integers(-2048, 2048, (periods, ns)).astype(np.int16)


def _batch(rx: FastReceiver, x_one: np.ndarray) -> int:
    """Periods per call so that a call takes about TARGET_SECONDS (1 .. MAX_PERIODS, and
    outputs within MAX_OUTPUT_BYTES)."""
    rx.frame(x_one)  # first use: buffers, thread pool
    t1 = _best(lambda: rx.frame(x_one), 2)
    most = min(MAX_PERIODS, max(1, MAX_OUTPUT_BYTES // (8 * rx.plan.k * rx.plan.count)))
    return int(np.clip(TARGET_SECONDS / max(t1, 1e-6), 1, most))


def _row(codes: np.ndarray, gate: int, method: str,
         rng: np.random.Generator) -> tuple[float, float, int, str]:
    """(kernel periods/s, chain periods/s, periods per call, kernel name) of one device."""
    n = codes.shape[1]
    cfg = ReceiverConfig(adc_bits=12, samples_per_chip=1, averages=1, gate_start=0 if gate == n
                         else 1000, gate_len=gate, out_bits=32)
    with cpu_only() if method == "auto" else contextlib.nullcontext():
        rx = FastReceiver(cfg, codes, method=method)
        periods = _batch(rx, _samples(rng, 1, n))
        rx = FastReceiver(cfg, codes, method=method, columns=periods)
    x = _samples(rng, periods, n)
    kernel = rx.kernel_for(periods)
    y = x.astype(np.int32).reshape(periods, 1, n)  # S = 1, R = 1, n = 1: Y is the samples
    t_kernel = _best(lambda: kernel(y))
    t_chain = _best(lambda: rx.frame(x))
    return periods / t_kernel, periods / t_chain, periods, kernel.method


def _exact(codes: np.ndarray, gate: int, method: str, rng: np.random.Generator) -> bool:
    """``method`` against the CPU chain ("auto" among the CPU kernels) on 2 periods."""
    n = codes.shape[1]
    cfg = ReceiverConfig(adc_bits=12, samples_per_chip=1, averages=1, gate_start=0 if gate == n
                         else 1000, gate_len=gate, out_bits=32)
    x = _samples(rng, 2, n)
    x[1, ::7] = 2047  # rails on a few samples: larger sums
    with cpu_only():
        cpu = FastReceiver(cfg, codes).frame(x)
    other = FastReceiver(cfg, codes, method=method).frame(x)
    return all(a.same_as(b) for a, b in zip(cpu, other, strict=True))


def main() -> None:
    rng = np.random.default_rng(29)
    u, v = preferred_pairs(DEGREE)[0]
    n = (1 << DEGREE) - 1
    needed = CHIP_RATE_HZ / n
    gpu = "gpu" in correlator_methods()
    print(f"cores: {os.cpu_count()} (receive chain threads "
          f"{correlator_base.default_threads()}), load average: {os.getloadavg()[0]:.2f}; "
          f"GPU: {'yes' if gpu else 'no GPU (CuPy not installed, or no CUDA device found)'}")
    print(f"eq. 29: {CHIP_RATE_HZ / 1e9:g} Gchip/s, degree {DEGREE} (N = {n}), S = 1, R = 1: "
          f"real time = {needed:,.0f} code periods per second")
    print(f"{'device':<6} {'K':>5} {'lags':>5} {'kernel':<7} {'batch':>5} "
          f"{'kernel per/s':>12} {'x real':>8} {'chain per/s':>11} {'x real':>8} "
          f"{'needed MAC/s':>12} {'exact':>6}")
    for k in CHANNELS:
        codes = gold_codes(u, v, range(k))
        for gate in (64, n):
            macs = float(n) * k * (gate + 2) * needed  # gated product, per second
            devices = [("cpu", "auto")] + ([("gpu", "gpu")] if gpu else [])
            for device, method in devices:
                kps, cps, periods, name = _row(codes, gate, method, rng)
                if device == "gpu":
                    exact = str(_exact(codes, gate, "gpu", rng))
                elif n * k * (gate + 2) * 2 <= XP_CHECK_MACS:
                    exact = str(_exact(codes, gate, "xp", rng)) + "*"
                else:
                    exact = "-"
                print(f"{device:<6} {k:>5} {gate:>5} {name:<7} {periods:>5} {kps:12.1f} "
                      f"{kps / needed:8.5f} {cps:11.1f} {cps / needed:8.5f} "
                      f"{macs:12.3g} {exact:>6}", flush=True)
    print("(exact: the GPU kernel against the CPU chain on 2 periods; '*': the numpy twin "
          "'xp' of the GPU code instead, no GPU here; '-': too large to check on this CPU)")
    roofline(n, needed)


def roofline(n: int, needed: float) -> None:
    """What one H100 must sustain for eq. 29, from its data-sheet peaks (not measured)."""
    print("roofline on one H100 SXM (data-sheet peaks; not a measurement):")
    for k in CHANNELS:
        gated = float(n) * k * 66 * needed  # multiply-adds per second, 64-lag gate + 2
        int8 = 2 * gated * 2  # two int8 limbs of the 12-bit samples, 2 ops per multiply-add
        out_bytes = 8.0 * k * 66 * needed  # raw int64 back to the host, per second
        print(f"  K={k:>4}, 64-lag gate: {gated / 1e12:6.1f} T multiply-adds/s; int8 tensor "
              f"cores (2 limbs) {H100_INT8_OPS / int8:5.1f}x real time at peak, float64 "
              f"{H100_FP64_FLOPS / (2 * gated):5.2f}x; raw int64 to the host "
              f"{out_bytes / 1e9:5.1f} GB/s (PCIe 5: {PCIE5_BYTES / 1e9:.0f})")
    whole = float(n) * n * 40 * needed
    fft_bytes = 41 * (1 << 14) * 16.0 * 2 * needed  # K + 1 complex128 transforms in and out
    print(f"  K=  40, whole period: direct {whole / 1e12:6.0f} T multiply-adds/s (int8, 2 "
          f"limbs: {H100_INT8_OPS / (4 * whole):.2f}x at peak); float64 FFT streams "
          f">= {fft_bytes / 1e12:.1f} TB/s of spectra (HBM3: {H100_HBM_BYTES / 1e12:.2f})")


if __name__ == "__main__":
    main()
