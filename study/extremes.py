"""The ``extremes`` study: the receive chain at the edges of its ranges, bit-exact or refused.

Each case drives full-scale 16-bit ADC codes (the strongest input there is) through the
receive chain at one corner of the configuration space, once through the streaming
reference model (:class:`cdma_lidar.firmware_model.receiver.ReferenceReceiver`: Python
integers, cannot overflow) and once through every registered fast kernel
(:func:`cdma_lidar.firmware_model.receiver.correlator_methods`, plus ``"auto"``). A case
passes when every kernel's output equals the reference in every field
(``ReceiverOutput.mismatches``): so the fast paths neither overflow nor round
differently. Every rounding mode is its own point.

The input of a column: channel 0's code at full scale (+1 chip -> the top code
2^(b-1)-1, -1 chip -> the bottom code -2^(b-1)) delayed by ``gate_start + 3`` samples,
each sample's sign flipped with probability 0.1 (seeded), the UID period polarity
applied, repeated R times. Channel 1 is another code of the same length.

Cases (``case`` column):

* ``degree-20``: a degree-20 m-sequence (N = 1 048 575 chips) and a cyclic shift of it;
* ``S-64``: 64 samples per chip; ``R-1024``: 1024 repetitions; ``S64-R1024``: both;
* ``sat-8bit``: 8-bit output with no output shift: heavy saturation;
* ``shift-max``: out_shift 62 (the maximum); ``shift-edge``: out_shift = raw width - 1
  (the output is then 0, -1 or +-1 depending on the rounding);
* ``uid-16``: 16 UID periods with a mixed-polarity UID;
* ``all-max``: degree 20, S = 64, R = 1024 at once: 68.7 G samples per column, not
  simulated here; the row reports the derived widths (``status`` "derived") or the
  receiver's refusal.

A configuration the receiver refuses (a derived width too wide for int64) is a row with
``status`` "refused" and its ``reason``, not a failure.

Columns: ``bit_exact`` (all kernels equal the reference), ``mismatches`` (kernel:field,
...), ``saturated_fraction`` of the gate's outputs at the output rails, the derived
``raw_bits`` / ``out_bits_used`` / ``noise_sumsq_bits``, ``samples`` per column and,
measuring the machine, ``fast_time_s`` (method "auto"), ``reference_time_s`` and
``peak_memory_mib`` (tracemalloc, one "auto" column).
"""

from __future__ import annotations

import time
import tracemalloc
from typing import Any

import numpy as np

from cdma_lidar.errors import ConfigError, out_of_range
from cdma_lidar.firmware_model.adc import adc_limits
from cdma_lidar.firmware_model.gold import bipolar, gold_code
from cdma_lidar.firmware_model.lfsr import mseq
from cdma_lidar.firmware_model.pairs import preferred_pairs
from cdma_lidar.firmware_model.receiver import (
    FastReceiver,
    ReceiverConfig,
    ReferenceReceiver,
    correlator_methods,
)
from cdma_lidar.rounding import ROUNDING_MODES
from cdma_lidar.study.engine import RunContext, RunOptions, Setting, Study, Table, headline
from cdma_lidar.study.simulate import smallest_out_shift

__all__ = ["CASES", "STUDY", "extremes_task"]

#: A primitive degree-20 polynomial (x^20 + x^3 + 1): degree 20 has no Gold pairs.
DEGREE_20_POLY = (20, 3)

#: Columns longer than this many samples are not simulated (the row gives derived widths).
MAX_SIMULATED_SAMPLES = 1 << 23

#: The cases: receiver parameters; ``out_shift`` "fit" is the smallest that fits int64,
#: "edge" the raw width - 1, an int is used as it is.
CASES: dict[str, dict[str, Any]] = {
    "degree-20": {"degree": 20, "S": 1, "R": 1, "out_bits": 32, "out_shift": "fit",
                  "gate_len": 8, "uid_bits": 1},
    "S-64": {"degree": 7, "S": 64, "R": 8, "out_bits": 32, "out_shift": "fit",
             "gate_len": 64, "uid_bits": 1},
    "R-1024": {"degree": 5, "S": 4, "R": 1024, "out_bits": 32, "out_shift": "fit",
               "gate_len": 64, "uid_bits": 1},
    "S64-R1024": {"degree": 5, "S": 64, "R": 1024, "out_bits": 32, "out_shift": "fit",
                  "gate_len": 64, "uid_bits": 1},
    "sat-8bit": {"degree": 7, "S": 4, "R": 64, "out_bits": 8, "out_shift": 0,
                 "gate_len": 64, "uid_bits": 1},
    "shift-max": {"degree": 7, "S": 4, "R": 64, "out_bits": 8, "out_shift": 62,
                  "gate_len": 64, "uid_bits": 1},
    "shift-edge": {"degree": 7, "S": 4, "R": 64, "out_bits": 32, "out_shift": "edge",
                   "gate_len": 64, "uid_bits": 1},
    "uid-16": {"degree": 5, "S": 2, "R": 2, "out_bits": 32, "out_shift": "fit",
               "gate_len": 32, "uid_bits": 16},
    "all-max": {"degree": 20, "S": 64, "R": 1024, "out_bits": 8, "out_shift": "fit",
                "gate_len": 64, "uid_bits": 1},
}

#: The UID of the ``uid-16`` case (mixed polarity).
UID_16 = 0xB5A3

ADC_BITS = 16

MACHINE_COLUMNS = ("fast_time_s", "reference_time_s", "peak_memory_mib")


def _grid(options: RunOptions) -> list[dict]:
    for c in options["cases"]:
        if c not in CASES:
            raise out_of_range("cases", "names from " + ", ".join(CASES), c)
    for r in options["rounding"]:
        if r not in ROUNDING_MODES:
            raise out_of_range("rounding", "one of " + ", ".join(ROUNDING_MODES), r)
    return [{"case": c, **CASES[c], "rounding": r}
            for c in options["cases"] for r in options["rounding"]]


def _codes(degree: int) -> np.ndarray:
    """Two channels' chip bits (2, N): Gold members 0 and 1, or two shifts of an m-sequence."""
    if degree == 20:
        m = mseq(DEGREE_20_POLY)
        return np.stack([m, np.roll(m, 12345)])
    u, v = preferred_pairs(degree)[0]
    return np.stack([gold_code(u, v, 0), gold_code(u, v, 1)])


def _config(params: dict, n_chips: int) -> ReceiverConfig:
    uid = UID_16 if params["uid_bits"] == 16 else 0
    shift = params["out_shift"]
    cfg = ReceiverConfig(adc_bits=ADC_BITS, samples_per_chip=params["S"], averages=params["R"],
                         uid_bits=params["uid_bits"], uid=uid, gate_start=5,
                         gate_len=params["gate_len"], peak_exclude=params["S"],
                         out_bits=params["out_bits"], rounding=params["rounding"],
                         out_shift=shift if isinstance(shift, int) else 0)
    if shift == "fit":
        return smallest_out_shift(cfg, n_chips)
    if shift == "edge":  # the raw width does not depend on the shift: take it from any that fits
        raw = smallest_out_shift(cfg, n_chips).widths(n_chips).raw
        return cfg.replace(out_shift=raw - 1)
    return cfg


def _input(cfg: ReceiverConfig, codes: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """One column of full-scale ADC codes (see the module docstring)."""
    s = cfg.samples_per_chip
    echo = np.roll(np.repeat(bipolar(codes[0]), s), cfg.gate_start + 3)
    pol = np.array([-1 if (cfg.uid >> p) & 1 else 1 for p in range(cfg.uid_bits)], np.int8)
    signs = np.tile((pol[:, None] * echo[None, :]).reshape(-1), cfg.averages)
    signs[rng.random(signs.size) < 0.1] *= -1
    lo, hi = adc_limits(cfg.adc_bits)
    return np.where(signs > 0, hi, lo).astype(np.int16)


def extremes_task(params: dict, seed: np.random.SeedSequence) -> dict[str, Any]:
    """One case at one rounding mode; see the module docstring."""
    codes = _codes(int(params["degree"]))
    n = codes.shape[1]
    try:
        cfg = _config(params, n)
        w = cfg.widths(n)
    except ConfigError as exc:
        return {"status": "refused", "reason": str(exc)}
    derived = {"out_shift_used": cfg.out_shift, "raw_bits": w.raw, "out_bits_used": w.out,
               "noise_sumsq_bits": w.noise_sumsq, "samples": cfg.column_samples(n)}
    if cfg.column_samples(n) > MAX_SIMULATED_SAMPLES:
        return {"status": "derived", "reason": f"{cfg.column_samples(n)} samples per column: "
                f"widths derived, not simulated (limit {MAX_SIMULATED_SAMPLES})", **derived}
    x = _input(cfg, codes, np.random.default_rng(seed))
    try:
        tracemalloc.start()
        try:
            t0 = time.perf_counter()
            auto = FastReceiver(cfg, codes).column(x)
            t_fast = time.perf_counter() - t0
            _, peak = tracemalloc.get_traced_memory()
        finally:
            tracemalloc.stop()
        outs = {m: FastReceiver(cfg, codes, method=m).column(x)
                for m in correlator_methods() if m != "auto"}
    except ConfigError as exc:
        return {"status": "refused", "reason": str(exc), **derived}
    t0 = time.perf_counter()
    ref = ReferenceReceiver(cfg, codes)
    ref.feed(x)
    want = ref.finish()
    t_ref = time.perf_counter() - t0
    bad = [f"auto:{f}" for f in auto.mismatches(want)]
    bad += [f"{m}:{f}" for m, out in outs.items() for f in out.mismatches(want)]
    top = (1 << (cfg.out_bits - 1)) - 1
    return {"status": "ok", "reason": "", **derived,
            "kernels": ",".join(outs), "bit_exact": not bad, "mismatches": ";".join(bad),
            "saturated_fraction": float(np.mean((want.corr >= top) | (want.corr <= -top - 1))),
            "peak_lag_ch0": int(want.peak_lag[0]),
            "fast_time_s": t_fast, "reference_time_s": t_ref, "peak_memory_mib": peak / 2**20}


def _reduce(table: Table, ctx: RunContext) -> dict[str, Any]:
    status = table.column("status")
    ok = np.array([s == "ok" for s in status])
    exact = np.array([r.get("bit_exact") is True for r in table.rows])
    (ctx.out / "extremes.md").write_text(
        "# Receive chain at the extremes: fast kernels against the streaming reference\n\n"
        + table.to_markdown(["case", "rounding", "status", "bit_exact", "out_shift_used",
                             "raw_bits", "saturated_fraction", "samples", "fast_time_s",
                             "reference_time_s", "peak_memory_mib", "reason"]))
    return {"points_bit_exact": headline(int(exact.sum()), None, "points"),
            "points_simulated": headline(int(ok.sum()), None, "points"),
            "points_not_bit_exact": headline(int((ok & ~exact).sum()), None, "points"),
            "points_refused": headline(int(sum(s == "refused" for s in status)), None,
                                       "points"),
            "points_derived_only": headline(int(sum(s == "derived" for s in status)), None,
                                            "points")}


STUDY = Study(
    name="extremes",
    description="receive chain at degree 20, S 64, R 1024, full-scale 16-bit ADC, 8-bit "
                "saturation, maximum out_shift, every rounding: bit-exact vs the reference",
    grid=_grid,
    task=extremes_task,
    reduce=_reduce,
    settings=(
        Setting("cases", tuple(CASES), "case names",
                quick=("R-1024", "sat-8bit", "shift-max", "shift-edge", "uid-16", "all-max")),
        Setting("rounding", ROUNDING_MODES, "rounding modes"),
    ),
    machine_columns=MACHINE_COLUMNS,
)
