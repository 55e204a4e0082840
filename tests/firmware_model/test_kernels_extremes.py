"""Every correlation kernel at the extremes of the parameter ranges, and the FFT guard at its edge.

The streaming reference is far too slow at degree 20 or R = 1024, so hypothesis
draws accumulators (``from_accumulators``: everything after the accumulator) at
those extremes (degree up to 20, S up to 64, R up to 1024, n up to 16, 16-bit full
scale, raw words up to 56 bits, 32-bit outputs whose noise sums of squares pass 63
bits) and checks every registered kernel, also with the float limit lowered so the
operands are split into limbs, against an independent int64 evaluation of the
definition ``raw_k[l] = sum_i ref_k[i] d[(i + l) mod NS]`` in the sample domain.
The matrix product also runs with float32 products off and with a float32 limit the
drawn data may straddle (16 bits).
"""

from __future__ import annotations

import math

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from cdma_lidar.firmware_model.correlators import GatePlan
from cdma_lidar.firmware_model.correlators.base import limbs
from cdma_lidar.firmware_model.correlators.fft import FFTCorrelator
from cdma_lidar.firmware_model.receiver import FastReceiver, ReceiverConfig, correlator_methods

LOWERED = {"matmul": lambda n: n.bit_length() + 2, "direct": lambda n: n.bit_length() + 3,
           "fft": lambda n: 45}


def _scale(raw, cfg):
    """out from raw by the definition (Python ints, floor division = arithmetic shift)."""
    s, top = cfg.out_shift, (1 << (cfg.out_bits - 1)) - 1
    out = []
    for v in raw:
        if s == 0:
            r = v
        elif cfg.rounding == "truncate":
            r = v >> s
        elif cfg.rounding == "half_up":
            r = (v + (1 << (s - 1))) >> s
        else:
            q, rem = v >> s, v - ((v >> s) << s)
            r = q + (rem > (1 << (s - 1)) or (rem == (1 << (s - 1)) and q & 1))
        out.append(min(max(r, -top - 1), top))
    return out


@st.composite
def extreme_cases(draw):
    degree = draw(st.sampled_from([2, 3, 7, 12, 16, 20]))
    n = (1 << degree) - 1
    s = draw(st.sampled_from([1, 2, 64] if degree <= 12 else [1, 2]))
    ns = n * s
    k = draw(st.integers(1, 3))
    b = draw(st.sampled_from([8, 16, 16]))
    r = draw(st.sampled_from([1, 1024, 1024, 37]))
    n_uid = draw(st.sampled_from([1, 16, 3]))
    gate_len = draw(st.sampled_from([1, 2, 5]))
    gate_start = draw(st.sampled_from([0, ns - 1, ns // 2, ns - gate_len]))
    cfg = ReceiverConfig(adc_bits=b, samples_per_chip=s, averages=r, uid_bits=n_uid,
                         uid=draw(st.integers(0, (1 << n_uid) - 1)), gate_start=gate_start,
                         gate_len=gate_len, peak_exclude=0, out_bits=32,
                         out_shift=draw(st.sampled_from([0, 0, 9, 24])),
                         rounding=draw(st.sampled_from(["truncate", "half_up", "convergent"])),
                         peaks=draw(st.integers(1, 2)))
    seed = draw(st.integers(0, 2**32 - 1))
    kind = draw(st.sampled_from(["full", "echo", "uniform"]))
    rng = np.random.default_rng(seed)
    codes = rng.integers(0, 2, (k, n), dtype=np.uint8)
    lo, hi = r * -(1 << (b - 1)), r * ((1 << (b - 1)) - 1)
    if kind == "uniform":
        acc = rng.integers(lo, hi + 1, (1, n_uid, ns))
    elif kind == "full":  # every accumulator at an end of its range
        acc = np.where(rng.random((1, n_uid, ns)) < 0.5, lo, hi)
    else:  # a full-scale echo of channel 0, despread-aligned, some chips flipped
        ref = np.repeat(1 - 2 * codes[0].astype(np.int64), s)
        echo = np.roll(ref, int(rng.integers(0, ns))) * np.where(rng.random(ns) < 0.05, -1, 1)
        pol = np.array([-1 if (cfg.uid >> p) & 1 else 1 for p in range(n_uid)])
        acc = np.where(pol[:, None] * echo[None, :] > 0, hi, lo)[None]
    return cfg, codes, acc.astype(np.int64)


# A quarter of the profile's examples (each is up to a 2^20-chip column): 12 by default,
# 250 with HYPOTHESIS_PROFILE=thorough (about 3 minutes).
@settings(max_examples=max(12, settings.default.max_examples // 4), deadline=None)
@given(extreme_cases())
def test_every_kernel_is_exact_at_the_extremes(case):
    cfg, codes, acc = case
    k, n = codes.shape
    s = cfg.samples_per_chip
    ns = n * s
    despread = np.array([-1 if (cfg.uid >> p) & 1 else 1 for p in range(cfg.uid_bits)])
    d = (despread[:, None] * acc[0]).sum(axis=0)  # |d| <= 2^29: int64 dots below are exact
    ref = np.repeat(1 - 2 * codes.astype(np.int64), s, axis=1)
    lags = [(cfg.gate_start + j) % ns for j in range(cfg.gate_len)]
    raw = [[int(np.dot(ref[i], np.roll(d, -lag))) for lag in lags] for i in range(k)]
    want = np.array([_scale(row, cfg) for row in raw], dtype=np.int64)
    first = None
    for method in correlator_methods():
        variants = [(53, 24)] + ([(LOWERED[method](n), 24)] if method in LOWERED else [])
        if method == "matmul":  # float64 only; float32 at a limit the data may straddle
            variants += [(53, 0), (53, 16)]
        for fb, fb32 in variants:
            got = FastReceiver(cfg, codes, method=method, float_bits=fb,
                               float32_bits=fb32).from_accumulators(acc)[0]
            assert got.corr.tolist() == want.tolist(), (method, fb, fb32)
            if first is None:
                first = got
            assert got.mismatches(first) == [], (method, fb)


def _fft_plan(n=31, k=2, s=1, float_bits=53):
    rng = np.random.default_rng(n)
    bip = (1 - 2 * rng.integers(0, 2, (k, n))).astype(np.int8)
    return GatePlan(bip, s, 0, n * s, float_bits=float_bits)


def _exact(bip, y):
    """raw[c, k, m] = sum_j bip_k[j] y[c, 0, (j + m) mod N] with Python-int-safe int64."""
    n = bip.shape[1]
    return np.array([[[int(np.dot(b.astype(np.int64), np.roll(yc[0], -m))) for m in range(n)]
                      for b in bip] for yc in y])


def test_fft_guard_at_its_edge():
    """Just under the guard one limb is exact; just over it the kernel splits, still exact,
    and the rigorous bound really bounds the float error at the edge."""
    from scipy import fft as sfft

    for float_bits in (53, 44):
        plan = _fft_plan(float_bits=float_bits)
        kern = FFTCorrelator(plan)
        guard = 0.25 * 2.0 ** (float_bits - 53)
        unit = kern._bound(np.ones((1, plan.n), dtype=np.int64))  # bound of |y| = 1 rows
        edge = guard / unit  # the largest constant magnitude one limb may carry
        rng = np.random.default_rng(float_bits)
        signs = np.where(rng.random(plan.n) < 0.5, -1, 1)
        for mag, want_parts in ((math.floor(edge * 0.999), 1), (math.ceil(edge * 1.001), 2)):
            y = (signs * mag).astype(np.int64)[None, None, :]
            parts = limbs(y[0], lambda v, k=kern, g=guard: k._bound(v) < g, kern.limb_width())
            assert len(parts) == want_parts, (float_bits, mag)
            assert kern(y).tolist() == _exact(plan.bip, y).tolist()
        # the float error of one unsplit transform at the edge stays under the bound
        y = (signs * math.floor(edge * 0.999)).astype(np.int64)
        big = kern.fft_len
        spec = sfft.rfft(np.concatenate([y, y]).astype(np.float64), big)
        a = np.conj(sfft.rfft(plan.bip.astype(np.float64), big, axis=1))
        x = sfft.irfft(a * spec[None, :], big, axis=1)[:, : plan.n]
        err = np.abs(x - _exact(plan.bip, y[None, None, :])[0]).max()
        assert err <= kern._bound(y[None, :]) < 0.5


def test_fft_guard_rejects_a_float_budget_too_small_for_any_limb():
    from cdma_lidar.errors import ConfigError

    plan = _fft_plan(n=2**12 - 1, float_bits=14)
    kern = FFTCorrelator(plan)
    try:
        kern.limb_width()
    except ConfigError as exc:
        assert exc.field == "float_bits"
    else:
        raise AssertionError("float_bits = 14 cannot carry a 4095-chip FFT exactly")


def test_noise_sumsq_at_the_int64_boundary_and_beyond():
    """Width 63 stays int64; width 64 switches to exact Python integers; both paths agree."""
    n, s = 7, 2
    codes = np.array([[0, 0, 1, 0, 1, 1, 1]], dtype=np.uint8)
    for gate_len, wide in ((7, False), (8, True)):
        # out = +-2^30 (saturated, 31-bit output): 2 * 31 - 2 + bitlen(G) = 63 or 64 bits
        cfg = ReceiverConfig(adc_bits=16, samples_per_chip=s, averages=1024, uid_bits=16,
                             gate_len=gate_len, peak_exclude=0, out_bits=31)
        w = cfg.widths(n)
        assert w.wide_sumsq == wide and w.noise_sumsq == 60 + gate_len.bit_length()
        acc = np.full((1, 16, n * s), 1024 * ((1 << 15) - 1), dtype=np.int64)
        outs = [FastReceiver(cfg, codes, method=m).from_accumulators(acc)[0]
                for m in correlator_methods()]
        corr = [int(v) for v in outs[0].corr[0].tolist()]
        sq = sum(v * v for j, v in enumerate(corr) if j != int(np.argmax(np.abs(corr))))
        for o in outs:
            assert o.noise_sumsq.dtype == (object if wide else np.int64)
            assert int(o.noise_sumsq[0]) == sq and o.mismatches(outs[0]) == []
