"""Cost model of the correlation kernels: fixed operation counts, as scipy's ``choose_conv_method``.

Each kernel states its work for a :class:`~.base.GatePlan` in a few machine
primitives (:class:`Coefficients`): float64 multiply-adds of a large matrix product,
bytes streamed through memory, transform points ``L log2 L`` of a real FFT, and
Python-level calls (one numpy/BLAS call each). The seconds per primitive are the
constants :data:`COEFFICIENTS`, fixed in this file (fitted once on the development
machine's kernel grid; a choice within tens of per cent from constants needs no
retuning). Nothing is read from or written to disk, no environment variable and no
module state is consulted: the same plan gets the same kernel on every machine and
in every process.

:func:`choose` is the rule of ``"auto"``: the kernel with the smallest predicted time
(ties to the first registered). Where the constants are not good enough, measure:
``choose_correlator(plan, measure=True)`` times the kernels on the plan itself
(:func:`~.base.measure_correlators`), like ``choose_conv_method(..., measure=True)``.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass

__all__ = [
    "CACHE_BYTES",
    "COEFFICIENTS",
    "HANDOFF",
    "LLC_BYTES",
    "LLC_FACTOR",
    "PACK_BYTES",
    "RAM_FACTOR",
    "SMALL_MACS",
    "SMALL_OUTPUT",
    "TILE_ROWS",
    "Coefficients",
    "Estimate",
    "choose",
    "gemm_seconds",
    "packs",
    "stream_bytes",
    "threaded",
]

@dataclass(frozen=True)
class Coefficients:
    """Seconds per machine primitive (all > 0; the model's are :data:`COEFFICIENTS`).

    ``mac``: one float64 multiply-add inside a matrix product (BLAS on one thread, as
    fitted: the kernels are compared with each other, not with the machine); ``byte``:
    one byte read or written by a memory-bound pass (copies, matrix-vector products,
    casts) on an operand that stays in the cache; ``fft``: one ``L log2 L`` point of a
    batched real FFT (forward or inverse); ``call``: the fixed overhead of one numpy or
    BLAS call from Python; ``ram``: how many times a byte streamed from main memory
    costs more than ``byte`` (a ratio >= 1); ``llc_bytes``: the share of the last-level
    cache one call's operands may hold (:data:`LLC_BYTES` on one thread; the column
    threads share it, :func:`.base.estimates`).
    """

    mac: float
    byte: float
    fft: float
    call: float
    ram: float = 1.0
    llc_bytes: float = 16 << 20  # LLC_BYTES


#: The constants of the model, and the kernels' ``fixed_calls``, fitted to this project's
#: 2-core development machine (Xeon, AVX-512, 2 MiB L2 per core, OpenBLAS 0.3.31, numpy 2)
#: on 2026-11-26: each kernel called alone on random chip sums of 92 plans (the quick
#: grid of ``bench kernels`` up to degree 13 and K 400, and 30 of its random
#: configurations, seed 0), one thread (BLAS limited to 1), process CPU time, best of
#: 7 interleaved across the kernels (CPU time because the machine was shared, load
#: 6-15: wall times swung 2-3x). Non-negative least squares on the relative error of
#: every kernel's time (the fixed costs as one unknown per kernel), with ``ram`` and
#: :data:`CACHE_BYTES` chosen from a small grid (1.8/3/5; 2 or 8 MiB) by the most plans
#: whose predicted-fastest kernel measured within 1.25x of the fastest: 91 of 92 (the
#: constants before: 85), the worst 1.42x (0.40 against 0.28 ms); on 72 plans not
#: fitted (the grid timed again, random configurations of seed 7) 69. ``python -m bench
#: kernels --fit`` does the same (its run afterwards fitted these within 16 %), and
#: ``python -m bench kernels`` checks the choice end to end (docs/firmware.md, 10).
#: Kept when the model stopped charging packing to matrix-vector products, charged it
#: to both operands of a matrix product, counted a last partial block by its columns
#: and the direct kernel's lag-by-lag store by cache lines: on 140 plans' kernel times
#: (--fit's 92, 24 random of seeds 1 and 2) the constants put 136 within 1.25x, refits
#: (--fit's procedure) 135-138.
COEFFICIENTS = Coefficients(mac=6.6e-11, byte=1.24e-11, fft=4.4e-10, call=6.5e-7, ram=3.0)


@dataclass(frozen=True)
class Estimate:
    """A kernel's predicted time (s per call of ``plan.columns`` columns) and peak bytes."""

    seconds: float
    peak_bytes: float


#: Operands up to this size are taken to stay in cache when a kernel reuses them (a
#: core's L2 on the development machine; 8 MiB predicted worse, see COEFFICIENTS).
CACHE_BYTES = 2 << 20


#: :data:`COEFFICIENTS`' ``ram``: a byte streamed from main memory costs this many
#: cache bytes.
RAM_FACTOR = COEFFICIENTS.ram

#: An operand reused within a call up to this size stays in the last-level cache (half
#: the 32 MiB L3 of the 2-core machine, which other processes share), where a byte
#: costs LLC_FACTOR of a byte from main memory (1.2 cache bytes). (Charging main memory
#: beyond the 2 MiB L2 priced the direct kernel's per-lag products over 2-5 MB of codes
#: at 1.3-2.6x their time, and sent 5 of 50 one-column plans of ``bench kernels
#: --wide`` seeds 41 and 43 to matmul at 1.3-3.4x direct's time: d11 S2 K168 G53,
#: d12 S5 K158 G21.)
LLC_BYTES = COEFFICIENTS.llc_bytes
LLC_FACTOR = 0.4

#: A matrix product's micro-kernel computes this many rows of the first operand at a
#: time: a product of fewer rows (a column's few phases) pays for the whole tile. And
#: packing its operands costs PACK_BYTES cache bytes per element, float32 or float64
#: alike. Measured on the 2-core machine (OpenBLAS 0.3.31, one thread, CPU time): an
#: (m, 1023) @ (1023, p) product took 0.6-0.8 ns per element of the second operand for
#: m = 2..8, in float64 and in float32 alike (float32 1.0-1.2x float64's time, not the
#: half the model charged), and reached the multiply-add rate only from m = 16 (float32
#: 0.6-0.7x float64). Charging 16 bytes of packing per element and halving every
#: float32 term sent a degree-11, 168-channel column (a (2, 2047) @ (2047, 4536)
#: product over 74 MB) to matmul at 3.4x direct's time.
TILE_ROWS = 4
PACK_BYTES = 32.0


def stream_bytes(size: float, uses: float, ram: float = RAM_FACTOR,
                 llc_bytes: float = LLC_BYTES) -> float:
    """Cache-byte equivalents of ``uses`` reads of a ``size``-byte operand: every read
    costs its bytes from the cache when it fits :data:`CACHE_BYTES`, from the shared
    last-level cache when it fits ``llc_bytes`` (``Coefficients.llc_bytes``;
    :data:`LLC_FACTOR` of ``ram`` each), else streams it from main memory (``ram`` cache bytes each,
    ``Coefficients.ram``). Both tiers beyond a core's own cache are shared by the cores,
    so both scale with ``ram`` (:func:`threaded` does not overlap them). (Counting the
    re-reads of a cached operand as free made 66 one-row products over 2.6 MB of codes
    look 2x cheaper than they measured.)"""
    factor = 1.0 if size <= CACHE_BYTES else LLC_FACTOR * ram if size <= llc_bytes else ram
    return size * uses * factor


#: A float product (m, n) @ (n, p) of at most SMALL_MACS multiply-adds and SMALL_OUTPUT
#: output elements runs BLAS's small-matrix kernel, which packs nothing (OpenBLAS's
#: ``gemm_small_kernel_permit`` for the transposed operand numpy hands it: ``M N K <=
#: 100^3`` and ``M N <= 1200``). Measured on the 2-core machine (OpenBLAS, one thread, CPU
#: time): (4, 1023) @ (1023, 173) took 34 us, (4, 1023) @ (1023, 240) 47 us (48 ps per
#: multiply-add, no tile), (2, 255) @ (255, 600) 20 us; (2, 255) @ (255, 620), 1,240
#: outputs, 69 us and (8, 1023) @ (1023, 173) 163 us: packed. Charging the packing to the
#: small ones priced the windows kernel's products of a few lags at 2-3x their time and
#: sent degree-10, 173-channel and degree-8, 20-channel columns to kernels 1.2-1.4x slower
#: (``bench kernels --fit --wide``, seed 100).
SMALL_MACS = 100.0**3
SMALL_OUTPUT = 1200.0


def packs(m: float, n: float, p: float) -> bool:
    """Whether a float64 product (m, n) @ (n, p) packs its operands into blocks and panels.

    Only a true matrix product does: one row (m = 1) or one output column (p = 1) is a
    matrix-vector product, which BLAS (gemv) streams without a copy, and a product of at
    most :data:`SMALL_MACS` multiply-adds and :data:`SMALL_OUTPUT` outputs runs the
    small-matrix kernel, which reads its operands in place. (Charging the packing to the
    direct kernel's 95 per-lag (2, 16383) @ (16383, 1) products of a one-channel pair of
    columns predicted them level with matmul's one (2, 16383) @ (16383, 95) product,
    where direct measured 0.4-0.7x matmul's time, kernel alone: ``bench kernels``'
    random row d14 S1 K1 G93 R1024 n16 b16 C2, auto off target.)
    """
    return m > 1 and p > 1 and (m * n * p > SMALL_MACS or m * p > SMALL_OUTPUT)


def gemm_seconds(m: float, n: float, p: float, co: Coefficients, item: float = 8.0) -> float:
    """Predicted time of a product (m, n) @ (n, p) of ``item``-byte floats (8: float64,
    4: float32): compute plus streaming its operands.

    Thin products (p or m small) are memory-bound: the byte term dominates them. A
    product of several rows and several columns also packs both operands (BLAS copies
    them into blocks and panels: :data:`PACK_BYTES` per element, :func:`packs`) and
    computes whole tiles of :data:`TILE_ROWS` rows; float32 halves the multiply-adds
    and the bytes streamed, not the packing.
    (A product of a few rows streams its second operand about once: charging it once
    per row, as this model did, sent a degree-13, 40-channel column to a kernel
    1.5-1.7x slower than matmul, whose (4, 8191) @ (8191, 680) product measured one
    pass over its 44.6 MB operand. Charging the packing of the second operand only
    left the direct kernel's per-lag products, which pack a window of the chip sums
    on every lag, predicted 1.2x matmul on a degree-10, 116-channel, 160-column plan
    where they measured 1.9x its time, kernel alone.)
    """
    moved = sum(stream_bytes(item * size, 1, co.ram, co.llc_bytes)
                for size in (m * n, n * p, m * p))
    rows = m
    if packs(m, n, p):
        moved += PACK_BYTES * (m * n + n * p)
        rows = -(-m // TILE_ROWS) * TILE_ROWS
    return co.mac * item / 8.0 * rows * n * p + co.byte * moved + co.call


#: Seconds of each numpy/BLAS call's GIL-free work that no other column thread overlaps:
#: the call gives the GIL back to whichever thread holds it only at that thread's next
#: call, then waits for it (a futex wake-up). On the 2-core development machine
#: (2026-11-26, each kernel alone on 2 column threads of BLAS 1 against one thread,
#: best of 7, load 0.1-0.6): calls of 2-12 us of work each (the FFT kernel's
#: per-column transforms of a degree-9 to 11 code and a few channels; the direct
#: kernel's 4601 per-lag (80, 511) @ (511, 2) products) took 0.6-1.0x their
#: one-thread time on two threads, calls of 20-30 us 1.15-1.6x, of 75 us and more
#: 1.8-1.96x (matmul's few large products, the FFT kernel's transforms of 40
#: channels). On the 37 plans of ``bench kernels``' grid and random seeds 0-2 (32
#: each) that the chain splits over 2 column threads, this rule put all 37 within
#: 1.25x of the fastest kernel alone on 2 threads, the one-thread rule 36 (d9 S9 K2
#: Gall C160: fft at 2.6x matmul); it changed that one choice only.
HANDOFF = 1e-5


def threaded(seconds: float, serial: float, calls: float, threads: int) -> float:
    """Predicted time of ``threads`` column threads each running one call of a kernel.

    ``seconds``: one thread's call alone (its share of the columns), of which ``serial``
    cannot overlap another thread's: the GIL-held Python (the ``Coefficients.call``
    terms) and the bytes streamed from main memory (the ``ram`` share of
    :func:`stream_bytes`: the cores share its bandwidth). The rest runs in ``calls``
    numpy/BLAS calls that release the GIL; of those, :data:`HANDOFF` seconds per call
    run one thread at a time too, the remainder overlaps across the threads (each its
    own core)::

        overlap = max(0, seconds - serial - calls HANDOFF)
        time    = threads (seconds - overlap) + overlap

    So a kernel of a few large products on cached operands (matmul on many columns)
    gains nearly ``threads``x; one of many microsecond calls (small FFTs per column,
    thin products per lag) or of streams from main memory (a lone column's products with
    a large Hankel block) gains little or nothing.
    """
    overlap = max(0.0, seconds - serial - max(0.0, calls) * HANDOFF)
    return threads * (seconds - overlap) + overlap


def choose(estimates: Mapping[str, Estimate]) -> str:
    """The rule of ``"auto"``: the kernel with the smallest predicted time.

    ``estimates`` maps kernel names (registration order) to their estimates; infinite
    times are skipped, ties go to the first. Returns "" when none is finite.
    """
    best, best_t = "", math.inf
    for name, e in estimates.items():
        if e.seconds < best_t:
            best, best_t = name, e.seconds
    return best
