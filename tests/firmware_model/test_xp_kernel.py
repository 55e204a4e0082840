"""The array-API correlator: the same code on numpy ("xp") here and on CuPy ("gpu") where a
GPU exists, exact against the per-lag definition and the streaming reference.

Every test runs over :data:`METHODS`: "xp" always (array-api-compat is in the test
extra), and "gpu" too on a machine where CuPy found a device.
"""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from cdma_lidar.firmware_model.correlators import (
    GatePlan,
    XPCorrelator,
    choose_correlator,
    correlator_methods,
    estimates,
    make_correlator,
)
from cdma_lidar.firmware_model.correlators import xp as xpmod
from cdma_lidar.firmware_model.receiver import FastReceiver, ReceiverConfig, ReferenceReceiver

METHODS = [m for m in ("xp", "gpu") if m in correlator_methods()]


def test_the_numpy_twin_is_registered_where_the_test_extra_is_installed():
    import array_api_compat  # noqa: F401  (in the test extra: its absence is a failure)

    assert "xp" in correlator_methods()


def _exact(plan: GatePlan, y: np.ndarray) -> np.ndarray:
    """raw[c, k, m] from the definition, in Python integers (any magnitude)."""
    c = y.shape[0]
    out = np.zeros((c, plan.k, plan.count), dtype=object)
    bip = plan.bip.astype(object)
    for m in range(plan.count):
        row = np.roll(y[:, plan.r_m[m], :].astype(object), -(plan.q0 + int(plan.u_m[m])), axis=-1)
        out[:, :, m] = row.dot(bip.T)
    return out


@st.composite
def plans(draw):
    n = draw(st.integers(3, 40))
    s = draw(st.integers(1, 5))
    k = draw(st.integers(1, 4))
    ns = n * s
    count = draw(st.sampled_from([1, 2, ns, ns + 1, draw(st.integers(1, ns + 2))]))
    lag_lo = draw(st.integers(0, ns - 1))
    float_bits = draw(st.sampled_from([53, n.bit_length() + 2, n.bit_length() + 5, 30]))
    float32_bits = draw(st.sampled_from([0, 5, 12, 24]))
    rng = np.random.default_rng(draw(st.integers(0, 2**32 - 1)))
    bip = (1 - 2 * rng.integers(0, 2, (k, n))).astype(np.int8)
    plan = GatePlan(bip, s, lag_lo, count, float_bits=float_bits, float32_bits=float32_bits)
    c = draw(st.integers(1, 4))
    top = draw(st.sampled_from([1, 3, 2**11, 2**24, 2**35]))  # up to |Y| <= S n R 2^(b-1)
    kind = draw(st.sampled_from(["uniform", "extremes", "zero"]))
    if kind == "uniform":
        y = rng.integers(-top, top + 1, (c, s, n))
    elif kind == "extremes":
        y = rng.choice(np.array([-top, top, 0, top - 1]), (c, s, n))
    else:
        y = np.zeros((c, s, n), dtype=np.int64)
    dtype = np.int64 if top > 2**30 else draw(st.sampled_from([np.int32, np.int64]))
    return plan, y.astype(dtype)


@pytest.mark.parametrize("method", METHODS)
@settings(max_examples=120, deadline=None)
@given(case=plans(), block=st.sampled_from([None, 1, 64, 1000]))
def test_kernel_equals_the_definition(method, case, block):
    plan, y = case
    kernel = make_correlator(method, plan)
    if block is not None:  # tiny blocks: one lag and one column at a time
        kernel.block_bytes = block
        kernel.__init__(plan)
    got = kernel(y)
    assert got.dtype == np.int64 and got.shape == (y.shape[0], plan.k, plan.count)
    assert got.tolist() == _exact(plan, y).tolist()


@st.composite
def frames(draw):
    n = draw(st.integers(3, 19))
    s = draw(st.integers(1, 4))
    ns = n * s
    uid_bits = draw(st.sampled_from([1, 2, 3]))
    gate_len = draw(st.sampled_from([1, ns, draw(st.integers(1, ns))]))
    cfg = ReceiverConfig(adc_bits=draw(st.integers(8, 16)), samples_per_chip=s,
                         averages=draw(st.integers(1, 3)), uid_bits=uid_bits,
                         uid=draw(st.integers(0, (1 << uid_bits) - 1)),
                         gate_start=draw(st.integers(0, ns - 1)), gate_len=gate_len,
                         peak_exclude=draw(st.integers(0, 3)), peaks=draw(st.integers(1, 2)),
                         out_shift=draw(st.integers(0, 6)), out_bits=draw(st.integers(8, 32)),
                         rounding=draw(st.sampled_from(["truncate", "half_up", "convergent"])))
    rng = np.random.default_rng(draw(st.integers(0, 2**32 - 1)))
    codes = rng.integers(0, 2, (draw(st.integers(1, 3)), n), dtype=np.uint8)
    lo, hi = -(1 << (cfg.adc_bits - 1)), (1 << (cfg.adc_bits - 1)) - 1
    columns = draw(st.integers(1, 3))
    shape = (columns, cfg.column_samples(n))
    kind = draw(st.sampled_from(["uniform", "rails", "tiny"]))
    if kind == "uniform":
        x = rng.integers(lo, hi + 1, shape)
    elif kind == "rails":
        x = rng.choice([lo, hi], shape)
    else:
        x = rng.integers(-1, 2, shape)
    cuts = sorted(draw(st.lists(st.integers(0, shape[1]), max_size=5)))
    return cfg, codes, x.astype(np.int32), cuts


@pytest.mark.parametrize("method", METHODS)
@settings(max_examples=60, deadline=None)
@given(frames())
def test_frames_equal_the_chunked_streaming_reference(method, case):
    cfg, codes, x, cuts = case
    rx = FastReceiver(cfg, codes, method=method, columns=x.shape[0])
    got = rx.frame(x)
    from_acc = rx.from_accumulators(rx.accumulate(x))
    for col, out, out_acc in zip(x, got, from_acc, strict=True):
        ref = ReferenceReceiver(cfg, codes)
        for chunk in np.split(col, cuts):
            ref.feed(chunk)
        want = ref.finish()
        assert out.mismatches(want) == [] and out_acc.mismatches(want) == []


@pytest.mark.parametrize("method", METHODS)
def test_the_kernel_is_called_once_per_frame_with_every_column(method, monkeypatch):
    calls = []
    real = XPCorrelator.__call__

    def spy(self, y):
        calls.append(y.shape)
        return real(self, y)

    monkeypatch.setattr(XPCorrelator, "__call__", spy)
    rng = np.random.default_rng(5)
    codes = rng.integers(0, 2, (3, 127))
    cfg = ReceiverConfig(samples_per_chip=4, averages=64, gate_start=300, gate_len=20)
    x = rng.integers(-2048, 2048, (12, cfg.column_samples(127))).astype(np.int16)
    rx = FastReceiver(cfg, codes, method=method, threads=3)  # 2^18 samples and more: threads
    outs = rx.frame(x)
    assert calls == [(12, 4, 127)]
    cpu = FastReceiver(cfg, codes, method="matmul", threads=3).frame(x)
    assert all(a.same_as(b) for a, b in zip(outs, cpu, strict=True))


def test_auto_never_takes_the_numpy_twin():
    rng = np.random.default_rng(6)
    bip = (1 - 2 * rng.integers(0, 2, (40, 2047))).astype(np.int8)
    for count, columns in ((66, 160), (66, 1), (8188, 1)):
        plan = GatePlan(bip, 4, 99, count, columns=columns, y_bound=81920)
        assert estimates(plan)["xp"].seconds == float("inf")
        assert choose_correlator(plan) != "xp"


def test_gpu_estimate_counts_copies_and_products():
    rng = np.random.default_rng(7)
    bip = (1 - 2 * rng.integers(0, 2, (40, 2047))).astype(np.int8)
    small = xpmod.GPUCorrelator.estimate(GatePlan(bip, 4, 99, 66, columns=1), None)
    frame = xpmod.GPUCorrelator.estimate(GatePlan(bip, 4, 99, 66, columns=160), None)
    assert 0 < small.seconds < frame.seconds < float("inf")
    assert frame.peak_bytes == 160 * small.peak_bytes


def test_no_gpu_kernel_with_tf32_or_without_cupy(monkeypatch):
    monkeypatch.setattr(xpmod.importlib.util, "find_spec", lambda name: None)
    assert xpmod.gpu_available() is False
    monkeypatch.setattr(xpmod.importlib.util, "find_spec", lambda name: object())
    monkeypatch.setenv("CUPY_TF32", "1")  # refused before CuPy is even imported
    assert xpmod.gpu_available() is False
