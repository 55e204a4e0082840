"""Cost model of the correlation kernels: predicted time and peak memory, calibrated per machine.

Each kernel describes its work for a :class:`~.base.GatePlan` in a few machine
primitives (:class:`Coefficients`): float64 multiply-adds of a large matrix product,
bytes streamed through memory, transform points ``L log2 L`` of a real FFT, and
Python-level calls (one numpy/BLAS call each). The seconds per primitive are
measured once per machine by :func:`calibrate` (about 2 s of micro-benchmarks) and
cached as JSON in :func:`cache_path`:

* ``$CDMA_LIDAR_KERNEL_COSTS`` if set (a file path), else
* ``$XDG_CACHE_HOME/cdma-lidar/kernel-costs.json``, else
* ``~/.cache/cdma-lidar/kernel-costs.json``.

Rerun the calibration with ``python -m cdma_lidar.firmware_model.correlators.costs
--calibrate`` (``--show`` prints the table in use). Without a cache the built-in
:data:`DEFAULT_COEFFICIENTS` apply (fitted on the 2-core development machine); a
cache that cannot be read is logged and ignored. Nothing here runs a benchmark
implicitly: the choice of ``method="auto"`` never depends on the machine's load at
the moment a receiver is built.

`choose` is the rule of ``"auto"``: among the kernels with a finite cost, those
whose peak memory is within 2x of the leanest kernel's (or at most 64 MiB above it),
the fastest predicted one (ties to the first registered).
"""

from __future__ import annotations

import argparse
import json
import logging
import math
import os
import sys
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import asdict, dataclass, fields
from pathlib import Path

import numpy as np

from cdma_lidar.errors import ConfigError
from cdma_lidar.fileio import atomic_write_text

__all__ = [
    "CACHE_BYTES",
    "COSTS_ENV",
    "DEFAULT_COEFFICIENTS",
    "MEMORY_FLOOR",
    "MEMORY_HEADROOM",
    "MEMORY_SLACK",
    "RAM_FACTOR",
    "SMALL_ROWS",
    "TRADE_SPEEDUP",
    "Coefficients",
    "Estimate",
    "cache_path",
    "calibrate",
    "choose",
    "coefficients",
    "gemm_seconds",
    "main",
    "set_coefficients",
    "stream_bytes",
]

log = logging.getLogger(__name__)

#: Environment variable naming the calibration file (overrides the default location).
COSTS_ENV = "CDMA_LIDAR_KERNEL_COSTS"

#: "auto" only considers kernels whose peak memory is at most this times the leanest's ...
MEMORY_SLACK = 2.0
#: ... or at most this many bytes above it (a few MiB more is no reason to run 20x slower).
MEMORY_FLOOR = 64 << 20
#: A kernel at least TRADE_SPEEDUP times faster than the best within that cap is taken
#: anyway when it needs at most MEMORY_HEADROOM bytes more than the leanest: on one-lag
#: gates with many channels the lean FFT runs 30-200x slower than the direct product,
#: which needs 2-3.5x its memory but only 0.1-0.7 GiB more (docs/firmware.md).
TRADE_SPEEDUP = 4.0
MEMORY_HEADROOM = 1 << 30

_FORMAT = 2  # version of the JSON layout (2: the ram ratio)


@dataclass(frozen=True)
class Coefficients:
    """Seconds per machine primitive (all > 0).

    ``mac``: one float64 multiply-add inside a large matrix product (BLAS, all
    threads); ``byte``: one byte read or written by a memory-bound pass (copies,
    matrix-vector products, casts) on an operand that stays in the cache; ``fft``: one
    ``L log2 L`` point of a batched real FFT (forward or inverse); ``call``: the fixed
    overhead of one numpy or BLAS call from Python; ``ram``: how many times a byte
    streamed from main memory costs more than ``byte`` (a ratio >= 1).
    """

    mac: float
    byte: float
    fft: float
    call: float
    ram: float = 4.0

    def __post_init__(self) -> None:
        for f in fields(self):
            v = getattr(self, f.name)
            if not (isinstance(v, float | int) and math.isfinite(v) and v > 0):
                raise ConfigError(f"kernel cost coefficient {f.name} must be a positive number, "
                                  f"got {v!r}", field=f.name)
        if self.ram < 1:
            raise ConfigError(f"kernel cost coefficient ram must be >= 1, got {self.ram!r}",
                              field="ram")


#: Fitted on the development machine (2 cores, OpenBLAS): the kernel grid of
#: ``python -m bench kernels`` with the seconds-per-primitive ratios that chose best there.
DEFAULT_COEFFICIENTS = Coefficients(mac=2e-11, byte=1e-11, fft=3e-11, call=5e-7)


@dataclass(frozen=True)
class Estimate:
    """A kernel's predicted time (s per call of ``plan.columns`` columns) and peak bytes."""

    seconds: float
    peak_bytes: float


#: Operands up to this size are taken to stay in cache when a kernel reuses them.
CACHE_BYTES = 8 << 20


#: The built-in ``Coefficients.ram``: a byte streamed from main memory costs this many
#: cache bytes (the calibration measures it: 2.2 on the development machine).
RAM_FACTOR = 4.0


def stream_bytes(size: float, uses: float, ram: float = RAM_FACTOR) -> float:
    """Cache-byte equivalents of ``uses`` reads of a ``size``-byte operand: every read
    costs its bytes from the cache when it fits :data:`CACHE_BYTES`, else streams it
    from main memory (``ram`` cache bytes each, ``Coefficients.ram``). (Counting the
    re-reads of a cached operand as free made 66 one-row products over 2.6 MB of
    codes look 2x cheaper than they measured.)"""
    return size * uses * (1.0 if size <= CACHE_BYTES else ram)


#: Products of fewer rows than this measured no faster than that many one-row products
#: (OpenBLAS, 2 threads: (3, 2047) @ (2047, 400) took 1.7x three (1, 2047) products).
SMALL_ROWS = 8


def gemm_seconds(m: float, n: float, p: float, co: Coefficients) -> float:
    """Predicted time of a float64 product (m, n) @ (n, p): compute plus streaming its operands.

    Thin products (p or m small) are memory-bound: the byte term dominates them. A
    product of several rows also packs its second operand (BLAS copies it into panels:
    one more read and a write), which a one-row product (a matrix-vector product) does
    not: measured 1.7x slower for (3, 2047) @ (2047, 400) than three one-row products.
    """
    moved = sum(stream_bytes(8.0 * size, 1, co.ram) for size in (m * n, n * p, m * p))
    if m > 1:
        moved += 16.0 * n * p
    if 1 < m < SMALL_ROWS:  # no faster than m one-row products: B streamed once per row
        moved += (m - 1) * stream_bytes(8.0 * n * p, 1, co.ram)
    return co.mac * m * n * p + co.byte * moved + co.call


def cache_path() -> Path:
    """Where the calibration is cached (see the module docstring for the order)."""
    env = os.environ.get(COSTS_ENV)
    if env:
        return Path(env)
    base = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return Path(base) / "cdma-lidar" / "kernel-costs.json"


_ACTIVE: Coefficients | None = None
_ACTIVE_FROM: Path | None = None


def coefficients() -> Coefficients:
    """The coefficients in use: set by :func:`set_coefficients`, else the cache, else defaults."""
    global _ACTIVE, _ACTIVE_FROM
    path = cache_path()
    if _ACTIVE is not None and (_ACTIVE_FROM is None or _ACTIVE_FROM == path):
        return _ACTIVE
    co = DEFAULT_COEFFICIENTS
    if path.is_file():
        try:
            data = json.loads(path.read_text())
            if data.get("format") != _FORMAT:
                raise ValueError(f"format {data.get('format')!r}, expected {_FORMAT}")
            co = Coefficients(**{f.name: float(data["coefficients"][f.name])
                                 for f in fields(Coefficients)})
        except (OSError, ValueError, KeyError, TypeError, ConfigError) as exc:
            log.warning("ignoring kernel cost calibration %s (%s); rerun "
                        "python -m cdma_lidar.firmware_model.correlators.costs --calibrate",
                        path, exc)
            co = DEFAULT_COEFFICIENTS
    _ACTIVE, _ACTIVE_FROM = co, path
    return co


def set_coefficients(co: Coefficients | None) -> None:
    """Use ``co`` for every later choice (None: back to the cache or the defaults)."""
    global _ACTIVE, _ACTIVE_FROM
    _ACTIVE, _ACTIVE_FROM = co, None


def choose(estimates: Mapping[str, Estimate], shared: float = 0.0) -> str:
    """The rule of ``"auto"``: the fastest of the kernels within 2x of the leanest's memory
    (or within :data:`MEMORY_FLOOR`, 64 MiB, of it), unless a kernel at most
    :data:`MEMORY_HEADROOM` (1 GiB) above the leanest is :data:`TRADE_SPEEDUP` (4) times
    faster still: then that one (memory is traded for time only when both are worth it).

    ``estimates`` maps kernel names (registration order) to their estimates; infinite
    times are skipped. ``shared``: bytes the rest of the chain holds at its peak
    whatever the kernel (the memory compared is the whole call's). Ties go to the
    first. Returns "" when none is finite.
    """
    finite = {k: e for k, e in estimates.items() if math.isfinite(e.seconds)}
    if not finite:
        return ""
    lean = min(e.peak_bytes for e in finite.values()) + shared
    cap = max(MEMORY_SLACK * lean, lean + MEMORY_FLOOR)
    best, best_t = "", math.inf
    trade, trade_t = "", math.inf
    for name, e in finite.items():
        mem = e.peak_bytes + shared
        if mem <= cap and e.seconds < best_t:
            best, best_t = name, e.seconds
        if mem <= lean + MEMORY_HEADROOM and e.seconds < trade_t:
            trade, trade_t = name, e.seconds
    return trade if trade_t * TRADE_SPEEDUP <= best_t else best


# -- calibration -------------------------------------------------------------------------


def _best(fn: Callable[[], object], repeats: int) -> float:
    fn()  # warm up (threads, caches, plans)
    t = math.inf
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        t = min(t, time.perf_counter() - t0)
    return t


def calibrate(repeats: int = 5) -> Coefficients:
    """Measure the primitives on this machine (best of ``repeats``; about 2 s in all)."""
    rng = np.random.default_rng(0)
    # call: the kernels' inner loops on tiny operands (slice, product, strided store),
    # dominated by the Python -> numpy/BLAS overhead; per statement
    y2, bt, dst = rng.random((2, 16)), rng.random((8, 3)), np.empty((2, 3, 50))

    def loop() -> None:
        for m in range(50):
            o = y2[:, m % 8 : m % 8 + 8] @ bt
            dst[:, :, m] = o

    call = _best(loop, repeats) / 150
    # byte: matrix-vector products over a matrix that stays in the cache (4 MiB); ram:
    # the same over one well beyond the caches (128 MiB), per byte, over that
    vec = rng.random((2048, 1))
    small = rng.random((256, 2048))
    byte = _best(lambda: small @ vec, 4 * repeats) / (8.0 * small.size)
    big = rng.random((8192, 2048))
    ram = max(1.0, _best(lambda: big @ vec, repeats) / (8.0 * big.size) / byte)
    # mac: a large square-ish product (compute-bound, all BLAS threads)
    m = 768
    a, b = rng.random((m, m)), rng.random((m, m))
    t_mm = _best(lambda: a @ b, repeats)
    mac = t_mm / float(m) ** 3
    # fft: a batch of real transforms and their inverses, per L log2 L point
    big_l, rows = 1 << 15, 16
    x = rng.random((rows, big_l))

    from scipy import fft as sfft  # deferred: 130 ms at start-up, used only here

    def fwd_inv() -> None:
        sfft.irfft(sfft.rfft(x, axis=1), big_l, axis=1)

    t_fft = _best(fwd_inv, repeats)
    fft_pt = t_fft / (2 * rows * big_l * math.log2(big_l))
    co = Coefficients(mac=mac, byte=byte, fft=fft_pt, call=call, ram=ram)
    log.info("kernel cost calibration: %s", co)
    return co


def save(co: Coefficients, path: Path | None = None) -> Path:
    """Write ``co`` to the cache (atomically) and use it from now on; returns the path."""
    path = cache_path() if path is None else path
    path.parent.mkdir(parents=True, exist_ok=True)
    data = {"format": _FORMAT, "coefficients": asdict(co),
            "note": "seconds per primitive; python -m "
                    "cdma_lidar.firmware_model.correlators.costs --calibrate rewrites it"}
    atomic_write_text(path, json.dumps(data, indent=2) + "\n")
    set_coefficients(None)
    return path


def main(argv: Sequence[str] | None = None) -> int:
    """``python -m cdma_lidar.firmware_model.correlators.costs [--calibrate] [--show]``."""
    p = argparse.ArgumentParser(
        prog="python -m cdma_lidar.firmware_model.correlators.costs",
        description="Calibrate the correlation kernels' cost model on this machine.")
    p.add_argument("--calibrate", action="store_true",
                   help=f"measure and write the cache ({cache_path()})")
    p.add_argument("--show", action="store_true", help="print the coefficients in use")
    args = p.parse_args(argv)
    if args.calibrate:
        path = save(calibrate())
        sys.stdout.write(f"wrote {path}\n")
    if args.show or not args.calibrate:
        src = cache_path() if cache_path().is_file() else "built-in defaults"
        sys.stdout.write(f"{coefficients()} ({src})\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
