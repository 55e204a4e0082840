"""Code generator benchmark: Gold families, m-sequences and jump-ahead against in-run baselines.

Targets (issue 2): the whole degree-11 family (2049 x 2047 chips) in < 50 ms and
the degree-15 family (32769 x 32767 chips, 1.07 GB) in < 5 s.

Baselines, measured in the same run:
* family: a per-member loop of ``gold_code`` (what a caller without
  ``gold_family`` would write); at degree 15 it is timed over the first 2048
  members and scaled to 32769 (labelled "scaled").
* m-sequence: the chip-by-chip Fibonacci model ``FibonacciLFSR.clock_many`` and
  ``scipy.signal.max_len_seq`` (compiled) for the same chips.
* jump-ahead: clocking the register k times chip by chip.
* a device's code set (``gold_codes``, K members of one pair, as the scene and the
  receiver build it): the same per-member ``gold_code`` loop.
* issue 40's code set, K = 1,200 members of degree 15: ``gold_codes``, the per-member
  ``gold_code`` loop (members from one shared pair of m-sequences) and, as the
  baseline, one Fibonacci recurrence per member (``gold_code`` before it shared them:
  v's register jumped ahead by (N - k) mod N clocks), timed on 100 members and scaled.

Run: ``.venv/bin/python -m bench codes``.
"""

from __future__ import annotations

import time
from collections.abc import Callable

import numpy as np
import scipy.signal

from cdma_lidar.firmware_model.gold import gold_code, gold_codes, gold_family
from cdma_lidar.firmware_model.lfsr import FibonacciLFSR, jump, mseq, scipy_arguments
from cdma_lidar.firmware_model.pairs import PAPER_PAIR, preferred_pairs


def timings(fn: Callable[[], object], repeat: int) -> list[float]:
    """Wall times of ``repeat`` calls, in s (the result is dropped before the next call)."""
    times = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return times


def best_of(fn: Callable[[], object], repeat: int) -> float:
    """Best wall time of ``repeat`` calls, in s."""
    return min(timings(fn, repeat))


def per_member_loop(pu, pv, members: int) -> np.ndarray:
    n = (1 << pu[0]) - 1
    return np.stack([gold_code(pu, pv, k) for k in range(min(members, n + 2))])


def bench_family(pu, pv, repeat: int, target_s: float, baseline_members: int | None) -> None:
    m = pu[0]
    n = (1 << m) - 1
    times = timings(lambda: gold_family(pu, pv), repeat)
    t_fast, t_worst = min(times), max(times)
    fam = gold_family(pu, pv)  # spot check against the baseline definition
    rows = np.random.default_rng(0).integers(0, n + 2, 16)
    assert all(np.array_equal(fam[k], gold_code(pu, pv, int(k))) for k in rows)
    del fam
    members = n + 2 if baseline_members is None else baseline_members
    t_base = best_of(lambda: per_member_loop(pu, pv, members), 1)
    label = ""
    if members < n + 2:
        t_base *= (n + 2) / members
        label = f" (scaled from {members} members)"
    verdict = "OK" if t_worst < target_s else "MISSED"
    print(f"gold_family degree {m} ({n + 2} x {n} chips): best {t_fast * 1e3:8.1f} ms, "
          f"worst of {repeat} {t_worst * 1e3:8.1f} ms (first call pays the page faults) "
          f"[target < {target_s * 1e3:.0f} ms: {verdict}]")
    print(f"  baseline per-member gold_code loop{label}: {t_base * 1e3:9.1f} ms  "
          f"-> speed-up x{t_base / t_fast:.0f} (best), x{t_base / t_worst:.0f} (worst)")


def bench_members(pu, pv, k: int) -> None:
    indices = tuple(range(k))
    gold_codes(pu, pv, indices)  # first call generates and caches u and v
    t_fast = best_of(lambda: gold_codes(pu, pv, indices), 7)
    t_base = best_of(lambda: per_member_loop(pu, pv, k), 3)
    assert np.array_equal(gold_codes(pu, pv, indices), per_member_loop(pu, pv, k))
    print(f"gold_codes {k} members of degree {pu[0]}: {t_fast * 1e3:8.2f} ms; per-member "
          f"gold_code loop {t_base * 1e3:8.1f} ms (x{t_base / t_fast:.0f})")


def recurrence_member(pu, pv, k: int) -> np.ndarray:
    """Member k by one recurrence of its own (the baseline: gold_code before it shared
    the m-sequences)."""
    n = (1 << pu[0]) - 1
    return mseq(pu) ^ mseq(pv, jump(pv, None, (n - k) % n))


def bench_code_set(pu, pv, k: int, sample: int = 100) -> None:
    indices = tuple(range(k))
    t_set = best_of(lambda: gold_codes(pu, pv, indices), 3)
    t_loop = best_of(lambda: np.stack([gold_code(pu, pv, i) for i in indices]), 3)
    t_rec = best_of(lambda: [recurrence_member(pu, pv, i) for i in range(sample)], 1) \
        * k / sample
    assert all(np.array_equal(gold_code(pu, pv, i), recurrence_member(pu, pv, i))
               for i in (0, 1, k - 1))
    print(f"code set of {k} members of degree {pu[0]}: gold_codes {t_set * 1e3:8.1f} ms, "
          f"gold_code loop {t_loop * 1e3:8.1f} ms; one recurrence per member (scaled from "
          f"{sample} members) {t_rec * 1e3:8.1f} ms (x{t_rec / t_loop:.0f} the loop)")


def bench_mseq(poly, chips: int) -> None:
    t_fast = best_of(lambda: mseq(poly, chips=chips), 3)
    reg_time = best_of(lambda: FibonacciLFSR(poly).clock_many(chips), 1)
    kw = scipy_arguments(poly)
    t_scipy = best_of(lambda: scipy.signal.max_len_seq(**kw, length=chips), 3)
    assert np.array_equal(scipy.signal.max_len_seq(**kw, length=chips)[0].astype(np.uint8),
                          mseq(poly, chips=chips))
    print(f"mseq {poly} {chips} chips: {t_fast * 1e3:8.2f} ms; chip-by-chip Python "
          f"{reg_time * 1e3:8.1f} ms (x{reg_time / t_fast:.0f}); scipy max_len_seq "
          f"{t_scipy * 1e3:8.2f} ms (x{t_scipy / t_fast:.1f})")


def bench_jump(poly, k: int) -> None:
    t_jump = best_of(lambda: jump(poly, None, k), 5)
    reg = FibonacciLFSR(poly)
    t_clock = best_of(lambda: reg.clock_many(k), 1)
    assert np.array_equal(reg.state, jump(poly, None, k))
    print(f"jump {poly} by {k} clocks: {t_jump * 1e3:8.3f} ms; clocking "
          f"{t_clock * 1e3:8.1f} ms (x{t_clock / t_jump:.0f})")


def main() -> None:
    bench_family(*PAPER_PAIR, repeat=7, target_s=0.050, baseline_members=None)
    bench_family(*preferred_pairs(15)[0], repeat=3, target_s=5.0, baseline_members=2048)
    bench_members(*PAPER_PAIR, 40)
    bench_code_set(*preferred_pairs(15)[0], 1200)
    bench_mseq((20, 3), (1 << 20) - 1)
    bench_mseq((11, 2), 2047)
    bench_jump((20, 3), 1_000_000)
    bench_jump((32, 22, 2, 1), 1_000_000)


if __name__ == "__main__":
    main()
