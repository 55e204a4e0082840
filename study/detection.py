"""The ``detection`` study: how often the receiver's peak lag is the true delay, vs SNR.

One channel, a Gold code of degree ``degree`` (N = 2^m - 1 chips) sampled S times per
chip, an echo of amplitude A delayed by a random whole number of samples d (uniform in
0..N*S-1), white Gaussian noise of RMS sigma added per sample, quantised by a
``adc_bits`` ADC and run through the bit-exact receive chain with the gate over the
whole period. Per-sample SNR = A^2 / sigma^2 (dB in the grid). A trial is detected
when the reported peak lag equals d.

Columns: ``detection_rate`` (fraction of ``trials`` per task), ``snr_xc_median_db``
(median SNR_XC of eq. 44 as the receiver reports it), ``snr_xc_expected_db`` (the
processing gain N*S*SNR in dB) and, measuring the machine, ``time_per_trial_s``.

It is small on purpose: the engine's tests run it on every executor.
"""

from __future__ import annotations

import time
from typing import Any

import numpy as np

from cdma_lidar.checks import check_int
from cdma_lidar.firmware_model.adc import adc_limits
from cdma_lidar.firmware_model.gold import bipolar, gold_code
from cdma_lidar.firmware_model.pairs import preferred_pairs
from cdma_lidar.firmware_model.receiver import FastReceiver, ReceiverConfig
from cdma_lidar.study.engine import RunContext, Setting, Study, Table, grid_product, headline
from cdma_lidar.study.figures import new_figure, save_figure

__all__ = ["STUDY", "detection_task"]

#: Echo amplitude in ADC LSB (well inside an 8-bit ADC so clipping never matters).
AMPLITUDE_LSB = 8.0


def _grid(options: Any) -> list[dict]:
    degrees = [check_int("degree", d, 5, 11) for d in options["degrees"]]
    spc = [check_int("S", s, 1, 16) for s in options["S"]]
    check_int("trials", options["trials"], 1, 100000)
    return grid_product(degree=degrees, S=spc, snr_db=[float(x) for x in options["snr_db"]],
                        trials=[options["trials"]])


def detection_task(params: dict, seed: np.random.SeedSequence) -> dict[str, Any]:
    """``trials`` random delays at one (degree, S, snr_db); see the module docstring."""
    rng = np.random.default_rng(seed)
    m, s, trials = int(params["degree"]), int(params["S"]), int(params["trials"])
    u, v = preferred_pairs(m)[0]
    code = gold_code(u, v, 0)
    ns = code.size * s
    ref = np.repeat(bipolar(code).astype(np.float64), s)
    sigma = AMPLITUDE_LSB / 10 ** (float(params["snr_db"]) / 20)
    delays = rng.integers(0, ns, trials)
    idx = (np.arange(ns)[None, :] - delays[:, None]) % ns
    analog = AMPLITUDE_LSB * ref[idx] + rng.normal(0.0, sigma, (trials, ns))
    lo, hi = adc_limits(8)
    samples = np.clip(np.floor(analog + 0.5), lo, hi).astype(np.int16)
    cfg = ReceiverConfig(adc_bits=8, samples_per_chip=s, averages=1, gate_start=0, gate_len=ns,
                         peak_exclude=s)
    t0 = time.perf_counter()
    outs = FastReceiver(cfg, code[None, :]).frame(samples)
    elapsed = time.perf_counter() - t0
    lags = np.array([int(o.peak_lag[0]) for o in outs])
    snr = np.array([float(o.snr_db()[0]) for o in outs], dtype=np.float64)
    return {"detection_rate": float(np.mean(lags == delays)),
            "snr_xc_median_db": float(np.median(snr)),
            "snr_xc_expected_db": float(params["snr_db"]) + 10 * np.log10(ns),
            "time_per_trial_s": elapsed / trials}


def _reduce(table: Table, ctx: RunContext) -> dict[str, Any]:
    fig, ax = new_figure(6, 4)
    for m in sorted(set(table.column("degree").astype(int))):
        for s in sorted(set(table.column("S").astype(int))):
            t = table.where(degree=m, S=s)
            ax.plot(t.column("snr_db"), t.column("detection_rate"), marker="o",
                    label=f"degree {m}, S={s}")
    ax.set_xlabel("per-sample SNR (dB)")
    ax.set_ylabel("detection rate")
    ax.set_ylim(-0.02, 1.02)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    save_figure(fig, ctx.out / "detection.png")
    rate = table.column("detection_rate")
    snr = table.column("snr_db")
    ok = rate >= 0.99
    return {"lowest_snr_99pct_detection_db": headline(float(snr[ok].min()) if ok.any() else None,
                                                      None, "dB"),
            "mean_detection_rate": headline(float(np.mean(rate)), None, "1")}


STUDY = Study(
    name="detection",
    description="probability that the peak lag is the true delay vs per-sample SNR, S, degree "
                "(one channel; small, the engine's own check)",
    grid=_grid,
    task=detection_task,
    reduce=_reduce,
    settings=(
        Setting("degrees", (5, 7), "code degrees m (5..11)", quick=(5,)),
        Setting("S", (1, 2, 4), "samples per chip (1..16)", quick=(1, 2)),
        Setting("snr_db", (-30.0, -25.0, -20.0, -15.0, -10.0), "per-sample SNR values (dB)",
                quick=(-25.0, -15.0)),
        Setting("trials", 200, "random delays per task", quick=50),
    ),
    machine_columns=("time_per_trial_s",),
)
