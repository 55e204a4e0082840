"""The matrix-product kernel's float32 products: taken exactly when provably exact.

float32 products run when, for every column and phase, ``sum_i |Y_r[i]| <
2^min(float32_bits, float_bits)``; float64 otherwise. Checked against Python-integer
evaluations of ``raw[c, k, m] = sum_j bip_k[j] Y[c, r_m, (j + q0 + u_m) mod N]``, both
sides of the rule (which dtype ran, from the kernel's product counter) and the
boundary: a sum of exactly 2^24 must not go to float32, and 2^24 + 1 would come out
wrong there (float32 cannot hold it).
"""

from __future__ import annotations

import tracemalloc
from unittest import mock

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from cdma_lidar.firmware_model.correlators import (
    DirectCorrelator,
    GatePlan,
    MatmulCorrelator,
    matmul,
)
from cdma_lidar.firmware_model.correlators.matmul import phase_groups
from cdma_lidar.firmware_model.receiver import FastReceiver, ReceiverConfig, reference


def _exact(plan: GatePlan, y: np.ndarray) -> list:
    """The definition in Python integers."""
    bip = plan.bip.tolist()
    rows = y.tolist()
    n = plan.n
    return [[[sum(b[j] * rows[c][int(plan.r_m[m])][(j + plan.q0 + int(plan.u_m[m])) % n]
                  for j in range(n)) for m in range(plan.count)] for b in bip]
            for c in range(len(rows))]


def _float32_allowed(plan: GatePlan, y: np.ndarray) -> bool:
    """The rule, independently: every (column, phase) sum of |Y| below the float32 limit."""
    limit = plan.float32_limit()
    sums = [sum(abs(v) for v in row) for col in y.tolist() for row in col]
    return bool(limit) and max(sums) < limit


@st.composite
def kernel_cases(draw):
    n = draw(st.sampled_from([3, 7, 31, 97]))
    s = draw(st.sampled_from([1, 2, 3, 4]))
    k = draw(st.integers(1, 3))
    ns = n * s
    count = draw(st.integers(1, min(ns, 40)))
    lag_lo = draw(st.integers(0, ns - 1))
    columns = draw(st.integers(1, 3))
    float32_bits = draw(st.sampled_from([0, 1, 8, 12, 24, 24]))
    rng = np.random.default_rng(draw(st.integers(0, 2**32 - 1)))
    bip = np.where(rng.random((k, n)) < 0.5, -1, 1).astype(np.int8)
    if draw(st.booleans()):
        bip[0] = 1  # an all-(+1) code: partial sums reach the full sum of |Y| (the worst case)
    # magnitudes around the float32 limit: sum |Y| over a row near 2^float32_bits
    target = 1 << draw(st.sampled_from([0, 1, 8, 12, 24, 24, 30])) if float32_bits else 1 << 24
    mag = max(1, target // n + draw(st.integers(-2, 2)))
    y = rng.integers(-mag, mag + 1, (columns, s, n))
    if draw(st.booleans()):
        y = np.abs(y)  # all positive: with an all-(+1) code no cancellation at all
    dtype = draw(st.sampled_from([np.int32, np.int64]))
    plan = GatePlan(bip, s, lag_lo, count, float32_bits=float32_bits)
    return plan, y.astype(dtype)


@settings(max_examples=150, deadline=None)
@given(kernel_cases())
def test_float32_products_exactly_when_the_bound_allows(case):
    plan, y = case
    kern = MatmulCorrelator(plan)
    got = kern(y)
    assert got.dtype == np.int64 and got.tolist() == _exact(plan, y)
    want = "float32" if _float32_allowed(plan, y) else "float64"
    assert set(kern.products) == {want}, (dict(kern.products), want)


def _boundary_case(total: int, s: int = 1) -> tuple[GatePlan, np.ndarray]:
    """N = 97 chips, every row of Y positive with sum |Y| = ``total``; code 0 all +1 so
    the correlation at every lag is ``total`` itself."""
    n = 97  # 2^24 + 1 = 97 * 172961
    rng = np.random.default_rng(total)
    bip = np.ones((2, n), dtype=np.int8)
    bip[1] = np.where(rng.random(n) < 0.5, -1, 1)
    row = np.full(n, total // n, dtype=np.int64)
    row[: total - row.sum()] += 1
    y = np.broadcast_to(rng.permutation(row), (2, s, n)).copy()
    return GatePlan(bip, s, 5, 2 * s + 1), y


def test_the_float32_boundary_at_2_to_the_24():
    for s in (1, 3):
        for total, want in ((2**24 - 1, "float32"), (2**24, "float64"), (2**24 + 1, "float64")):
            plan, y = _boundary_case(total, s)
            kern = MatmulCorrelator(plan)
            got = kern(y)
            assert set(kern.products) == {want}, (total, s)
            assert got.tolist() == _exact(plan, y), (total, s)
            assert (got[:, 0, :] == total).all()
    # the guard matters: 2^24 + 1 has no float32, so a float32 product there is wrong
    plan, y = _boundary_case(2**24 + 1)
    f32 = y[:, 0, :].astype(np.float32) @ plan.bip[0].astype(np.float32)
    assert (f32.astype(np.int64) != 2**24 + 1).all()


def test_float32_bits_zero_and_a_large_y_bound_mean_float64_everywhere():
    plan, y = _boundary_case(1000)
    kern = MatmulCorrelator(plan)
    assert kern(y).tolist() == _exact(plan, y) and set(kern.products) == {"float32"}
    kern = MatmulCorrelator(GatePlan(plan.bip, 1, 5, 3, float32_bits=0))
    assert kern(y).tolist() == _exact(kern.plan, y) and set(kern.products) == {"float64"}
    # y_bound proving float32 for all data: no per-call test, still exact
    certain = GatePlan(plan.bip, 1, 5, 3, y_bound=(1 << 24) // 97 - 1)
    assert certain.float32_certain()
    kern = MatmulCorrelator(certain)
    assert kern(y).tolist() == _exact(certain, y) and set(kern.products) == {"float32"}


def test_phase_groups_merge_while_under_an_eighth_of_the_lags_are_wasted():
    """The paper gate (66 lags over S = 4: 17, 17, 16, 16) runs as one product, 2 lags of 68
    in vain; 7 lags (2, 2, 2, 1: 1 of 8 in vain) as two; equal lengths always as one."""
    bip = np.ones((2, 97), dtype=np.int8)
    assert [len(sel) for sel in GatePlan(bip, 4, 99, 66).sel] == [17, 16, 16, 17]
    assert phase_groups(GatePlan(bip, 4, 99, 66))
    assert not phase_groups(GatePlan(bip, 4, 0, 7))
    assert phase_groups(GatePlan(bip, 4, 0, 8))
    assert phase_groups(GatePlan(bip, 1, 5, 3))


# -- the receiver's bound: sum_i |d_i| per column proves float32 without a look at Y --------


def _phase_sums(cfg: ReceiverConfig, x: np.ndarray) -> int:
    """max over columns and phases of sum_m |Y_r[m]|, from the definition (Python ints)."""
    ns = x.shape[1] // (cfg.averages * cfg.uid_bits)
    s = cfg.samples_per_chip
    worst = 0
    for col in x.tolist():
        acc = [[sum(col[(r * cfg.uid_bits + p) * ns + i] for r in range(cfg.averages))
                for i in range(ns)] for p in range(cfg.uid_bits)]
        d = [sum(-acc[p][i] if (cfg.uid >> p) & 1 else acc[p][i] for p in range(cfg.uid_bits))
             for i in range(ns)]
        w = [sum(d[(i + t) % ns] for t in range(s)) for i in range(ns)]
        worst = max([worst] + [sum(abs(v) for v in w[r::s]) for r in range(s)])
    return worst


@st.composite
def bound_cases(draw):
    """Small frames whose sums of |d| and of |Y| straddle a low float32 limit: random codes,
    alternating signs (|d| large, every window of S samples cancels: the bound fails where
    the per-phase test passes), the ADC rails, and zeros."""
    n = draw(st.sampled_from([3, 7, 13]))
    s = draw(st.integers(1, 4))
    b = draw(st.sampled_from([8, 12, 16]))
    cfg = ReceiverConfig(adc_bits=b, samples_per_chip=s, averages=draw(st.integers(1, 3)),
                         uid_bits=draw(st.integers(1, 2)),
                         gate_start=draw(st.integers(0, n * s - 1)),
                         gate_len=draw(st.integers(s, n * s)))
    uid = draw(st.integers(0, (1 << cfg.uid_bits) - 1))
    cfg = cfg.replace(uid=uid)
    lo, hi = -(1 << (b - 1)), (1 << (b - 1)) - 1
    rng = np.random.default_rng(draw(st.integers(0, 2**32 - 1)))
    c, size = draw(st.integers(1, 3)), cfg.column_samples(n)
    kind = draw(st.sampled_from(["random", "small", "alternate", "rails", "zeros"]))
    if kind == "random":
        x = rng.integers(lo, hi + 1, (c, size))
    elif kind == "small":
        x = rng.integers(-3, 4, (c, size))
    elif kind == "alternate":  # +v, -v, ... per sample (S even: every window of S sums to 0)
        x = np.where(np.arange(size) % 2 == 0, hi, -hi) * np.ones((c, 1), dtype=np.int64)
    elif kind == "rails":
        x = np.where(rng.random((c, size)) < 0.5, lo, hi)
    else:
        x = np.zeros((c, size), dtype=np.int64)
    codes = rng.integers(0, 2, (draw(st.integers(1, 3)), n))
    float32_bits = draw(st.sampled_from([1, 6, 10, 14, 24]))
    dtype = draw(st.sampled_from([np.int16, np.int32, np.int64])) if b <= 16 else np.int64
    return cfg, codes, x.astype(dtype), float32_bits


@settings(max_examples=120, deadline=None)
@given(bound_cases())
def test_receiver_float32_products_by_the_bound_or_the_test_equal_the_reference(case):
    cfg, codes, x, float32_bits = case
    rx = FastReceiver(cfg, codes, method="matmul", float32_bits=float32_bits)
    got = rx.frame(x)
    for col, out in zip(x, got, strict=True):
        assert out.mismatches(reference(cfg, codes, col)) == []
    kern = rx.kernel_for(len(x))
    want = "float32" if _phase_sums(cfg, x) < kern.plan.float32_limit() else "float64"
    assert set(kern.products) == {want}, (dict(kern.products), want)


def test_the_bound_fails_where_every_window_cancels_yet_float32_runs():
    """Alternating full-scale samples, S = 2: sum |d| is far above 2^10, every chip sum is 0.
    The bound cannot prove float32; the per-phase test does, and the result is exact."""
    cfg = ReceiverConfig(adc_bits=12, samples_per_chip=2, averages=1, gate_len=8)
    codes = np.random.default_rng(3).integers(0, 2, (2, 7))
    x = np.where(np.arange(cfg.column_samples(7)) % 2 == 0, 2047, -2047)[None, :]
    rx = FastReceiver(cfg, codes, method="matmul", float32_bits=10)
    out = rx.frame(x)[0]
    assert out.mismatches(reference(cfg, codes, x[0])) == []
    assert set(rx.kernel_for(1).products) == {"float32"}
    assert 14 * 2047 >= rx.plan.float32_limit() and not out.corr.any()


def test_the_bound_sums_in_uint64_where_uint32_could_overflow():
    """N S R 2^(b-1) >= 2^32 (16-bit codes, R = 1024, 248 samples a period): sum |d| in
    uint64; at the rails no float32, between them the bound or the test decides, exact."""
    cfg = ReceiverConfig(adc_bits=16, samples_per_chip=8, averages=1024, gate_len=9)
    rng = np.random.default_rng(11)
    codes = rng.integers(0, 2, (2, 31))
    size = cfg.column_samples(31)
    rails = np.where(rng.random(size) < 0.5, -32768, 32767).astype(np.int16)
    small = rng.integers(-1, 2, size).astype(np.int32)
    for x, want in ((rails, "float64"), (small, "float32")):
        rx = FastReceiver(cfg, codes, method="matmul")
        assert rx._l1_type is np.uint64
        assert rx.frame(x[None, :])[0].mismatches(reference(cfg, codes, x)) == []
        assert set(rx.kernel_for(1).products) == {want}


def test_data_too_large_skips_the_sum_and_hands_the_trivial_bound():
    """When column 0's first 4096 samples already sum |d| past the float32 limit, the chain
    skips its sum |d| pass: the kernel gets the bound type's largest value for every
    column, decides from Y itself (as without a bound) and stays exact."""
    cfg = ReceiverConfig(adc_bits=12, samples_per_chip=4, averages=10, gate_len=16)
    rng = np.random.default_rng(5)
    codes = rng.integers(0, 2, (2, 1023))
    x = np.where(rng.random((3, cfg.column_samples(1023))) < 0.5, -2048, 2047)
    rx = FastReceiver(cfg, codes, method="matmul")
    kernel = rx.kernel_for(len(x))
    seen = []
    call = type(kernel).__call__

    def spy(self, y, bound=None):
        seen.append(None if bound is None else bound.copy())
        return call(self, y, bound)

    with mock.patch.object(type(kernel), "__call__", spy):
        got = rx.frame(x)
    for col, out in zip(x, got, strict=True):
        assert out.mismatches(reference(cfg, codes, col)) == []
    assert seen and all(b is not None and (b == np.iinfo(b.dtype).max).all() for b in seen)
    want = "float32" if _phase_sums(cfg, x) < rx.plan.float32_limit() else "float64"
    assert set(kernel.products) == {want}
    small = rng.integers(-2, 3, x.shape)  # the same chain on small data: the real sums
    seen.clear()
    with mock.patch.object(type(kernel), "__call__", spy):
        rx.frame(small)
    assert seen and all((b < rx.plan.float32_limit()).all() for b in seen)


# -- Hankel blocks beyond HANKEL_BYTES: built per call in chunks of channels ---------------


@settings(max_examples=80, deadline=None)
@given(kernel_cases(), st.integers(1, 3))
def test_hankel_blocks_in_chunks_of_channels_give_the_same_integers(case, per_chunk):
    """With the blocks' budget shrunk to ``per_chunk`` channels' float32 blocks (a chunk
    then holds one channel or a few), the chunks are built on the call: the same exact
    integers, and the same float type as the rule says."""
    plan, y = case
    whole = MatmulCorrelator(plan)(y)
    budget = 4 * matmul._hankel_width(plan) * plan.n * per_chunk
    with mock.patch.object(matmul, "HANKEL_BYTES", budget):
        if plan.k > per_chunk:
            assert not matmul._cached(plan, 4)
        kern = MatmulCorrelator(plan)
        got = kern(y)
        assert got.tolist() == whole.tolist() == _exact(plan, y)
        assert not kern._hankels or plan.k <= per_chunk
        want = "float32" if _float32_allowed(plan, y) else "float64"
        assert set(kern.products) == {want}


def test_a_large_plan_holds_a_chunk_of_its_hankel_blocks_not_all():
    """Degree 13 (N = 8191), 400 channels, a 64-lag gate at S = 2: 0.84 GB of float64 Hankel
    blocks if kept whole; in chunks the call's peak stays under 4 chunks of HANKEL_BYTES / 8
    (and the same integers as the direct kernel)."""
    rng = np.random.default_rng(5)
    n, k = 8191, 400
    bip = np.where(rng.random((k, n)) < 0.5, -1, 1).astype(np.int8)
    plan = GatePlan(bip, 2, 1000, 64)
    assert 4 * k * 32 * n > matmul.HANKEL_BYTES  # float32 too: 0.4 GB
    y = rng.integers(-2000, 2001, (1, 2, n))
    tracemalloc.start()
    kern = MatmulCorrelator(plan)
    got = kern(y)
    peak = tracemalloc.get_traced_memory()[1]
    tracemalloc.stop()
    assert not kern._hankels
    assert peak < 4 * matmul.HANKEL_BYTES / 8, peak
    assert np.array_equal(got, DirectCorrelator(plan)(y))
