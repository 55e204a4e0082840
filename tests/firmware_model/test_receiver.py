"""Receive chain: the fast paths are bit-identical to the streaming reference.

Hypothesis draws whole configurations (ADC width, S, R, UID bits and value, K, N,
gate incl. wrapping and whole period, shift, rounding, output width, ghost
windows, several peaks) and signals (uniform, tiny alphabets that force ties,
full scale, delayed echoes), feeds the reference in random chunks, and compares
every output field of every fast variant: every registered correlation kernel
(``correlator_methods()``: auto, matrix product, FFT, and any kernel registered
since), and the float kernels with the float limit lowered so the operands are
split into limbs. A toy kernel registered here becomes usable by name.
"""

from __future__ import annotations

import contextlib

import numpy as np
import pytest
from hypothesis import assume, given, settings
from hypothesis import strategies as st

from cdma_lidar.errors import ConfigError
from cdma_lidar.firmware_model.correlators import (
    Correlator,
    GatePlan,
    register_correlator,
    unregister_correlator,
)
from cdma_lidar.firmware_model.lfsr import mseq
from cdma_lidar.firmware_model.receiver import (
    FastReceiver,
    ReceiverConfig,
    ReferenceReceiver,
    correlator_methods,
    fast,
    fast_frame,
    fast_from_accumulators,
    reference,
)


@st.composite
def cases(draw):
    n = draw(st.integers(3, 23))
    s = draw(st.integers(1, 4))
    k = draw(st.integers(1, 3))
    ns = n * s
    gate_kind = draw(st.sampled_from(["any", "full", "one", "wrap"]))
    if gate_kind == "full":
        gs, gl = draw(st.integers(0, ns - 1)), ns
    elif gate_kind == "one":
        gs, gl = draw(st.integers(0, ns - 1)), 1
    elif gate_kind == "wrap":
        gs = draw(st.integers(max(0, ns - 6), ns - 1))
        gl = draw(st.integers(min(ns, ns - gs + 1), ns))
    else:
        gs, gl = draw(st.integers(0, ns - 1)), draw(st.integers(1, ns))
    uid_bits = draw(st.sampled_from((1, 2, 3, 1, 2, 3, 16)))  # 16: the largest UID, 1 in 7
    ghosts = draw(
        st.lists(st.tuples(st.integers(0, ns - 1), st.integers(1, max(1, ns // 3))), max_size=2)
    )
    b = draw(st.integers(8, 16))
    cfg = ReceiverConfig(
        adc_bits=b,
        samples_per_chip=s,
        averages=draw(st.integers(1, 3)),
        uid_bits=uid_bits,
        uid=draw(st.integers(0, (1 << uid_bits) - 1)),
        gate_start=gs,
        gate_len=gl,
        peak_exclude=draw(st.integers(0, 4)),
        ghost_windows=tuple(ghosts),
        out_shift=draw(st.integers(0, 12)),
        rounding=draw(st.sampled_from(["truncate", "half_up", "convergent"])),
        out_bits=draw(st.integers(8, 32)),
        peaks=draw(st.integers(1, 3)),
    )
    try:
        cfg.widths(n)
    except ConfigError:
        assume(False)
    seed = draw(st.integers(0, 2**32 - 1))
    kind = draw(st.sampled_from(["uniform", "tiny", "full", "echo"]))
    rng = np.random.default_rng(seed)
    codes = rng.integers(0, 2, (k, n), dtype=np.uint8)
    lo, hi = -(1 << (b - 1)), (1 << (b - 1)) - 1
    total = cfg.column_samples(n)
    if kind == "uniform":
        x = rng.integers(lo, hi + 1, total)
    elif kind == "tiny":
        x = rng.integers(-1, 2, total)
    elif kind == "full":
        x = rng.choice([lo, hi], total)
    else:  # delayed, UID-modulated echoes of each channel plus noise, clipped like an ADC
        period = np.zeros(ns, dtype=np.int64)
        for row in codes:
            ref = np.repeat(1 - 2 * row.astype(np.int64), s)
            period += int(rng.integers(-40, 41)) * np.roll(ref, int(rng.integers(0, ns)))
        pol = [(-1) ** ((cfg.uid >> p) & 1) for p in range(uid_bits)]
        one = np.concatenate([q * period for q in pol])
        x = np.tile(one, cfg.averages) + rng.integers(-3, 4, total)
        x = np.clip(x, lo, hi)
    dtype = draw(st.sampled_from([np.int16, np.int32, np.int64]))
    cuts = sorted(draw(st.lists(st.integers(0, total), max_size=6)))
    return cfg, codes, x.astype(dtype), cuts


class PerLagCorrelator(Correlator):
    """Toy kernel: one int64 dot product per channel, lag and column, straight from
    ``raw[c, k, m] = sum_j bip_k[j] Y[c, r_m, (j + q0 + u_m) mod N]`` (slow, obviously exact)."""

    def __call__(self, y):
        plan = self.plan
        bip = plan.bip.astype(np.int64)
        out = np.zeros((y.shape[0], plan.k, plan.count), dtype=np.int64)
        for m in range(plan.count):
            row = np.roll(y[:, plan.r_m[m], :], -(plan.q0 + int(plan.u_m[m])), axis=-1)
            out[:, :, m] = row @ bip.T
        return out


@contextlib.contextmanager
def toy_kernel():
    """Register the toy kernel as "perlag" for the duration (hypothesis-safe: per example)."""
    register_correlator("perlag", PerLagCorrelator)
    try:
        yield "perlag"
    finally:
        unregister_correlator("perlag")


#: Float limits low enough that the float kernels split their operands into limbs.
LIMB_FLOAT_BITS = {"matmul": lambda n: n.bit_length() + 2, "fft": lambda n: 30,
                   "direct": lambda n: n.bit_length() + 3}


def _fast_variants(cfg, codes):
    n = codes.shape[1]
    for method in correlator_methods():
        yield FastReceiver(cfg, codes, method=method)
        if method in LIMB_FLOAT_BITS:
            yield FastReceiver(cfg, codes, method=method, float_bits=LIMB_FLOAT_BITS[method](n))
        if method == "matmul":  # float64 products only, and a float32 limit the data straddles
            for bits in (0, 10):
                yield FastReceiver(cfg, codes, method=method, float32_bits=bits)


def _chunked_reference(cfg, codes, x, cuts):
    rx = ReferenceReceiver(cfg, codes)
    for chunk in np.split(x, cuts):
        rx.feed(chunk)
    assert rx.samples_needed == 0
    want = rx.finish()
    assert want.corr.shape == (codes.shape[0], cfg.gate_len)
    return want


@settings(max_examples=150)
@given(cases())
def test_fast_paths_equal_chunked_reference(case):
    cfg, codes, x, cuts = case
    want = _chunked_reference(cfg, codes, x, cuts)
    seen = set()
    for fr in _fast_variants(cfg, codes):
        got = fr.column(x)
        assert got.mismatches(want) == [], (fr.method, fr.correlator_method, fr.float_bits)
        seen.add(fr.method)
    assert seen == set(correlator_methods())


def test_every_method_is_listed_auto_first():
    methods = correlator_methods()
    assert methods[0] == "auto"
    assert {"matmul", "fft", "direct"} <= set(methods[1:])


@settings(max_examples=40)
@given(cases())
def test_a_registered_kernel_is_usable_by_name(case):
    cfg, codes, x, cuts = case
    want = _chunked_reference(cfg, codes, x, cuts)
    with toy_kernel() as name:
        assert name in correlator_methods()
        # the parametrised equality check of every registered method includes it
        for fr in _fast_variants(cfg, codes):
            assert fr.column(x).mismatches(want) == [], fr.method
        for got in (
            fast(cfg, codes, x, method=name),
            fast_frame(cfg, codes, x[None, :], method=name)[0],
        ):
            assert got.mismatches(want) == []
        rx = FastReceiver(cfg, codes, method=name)
        assert rx.correlator_method == name
        # its cost is the default (infinite): "auto" never picks a kernel that did not ask
        assert FastReceiver(cfg, codes).correlator_method in ("matmul", "fft", "direct",
                                                              "windows")
        acc = rx.accumulate(x[None, :])
        assert fast_from_accumulators(cfg, codes, acc, method=name)[0].same_as(want)
    assert name not in correlator_methods()
    with pytest.raises(ConfigError, match="method"):
        FastReceiver(cfg, codes, method=name)
    with pytest.raises(ConfigError, match="method"):  # not served from fast()'s kept receivers
        fast(cfg, codes, x, method=name)


def test_registration_rejects_taken_and_reserved_names():
    with toy_kernel() as name, pytest.raises(ConfigError, match="already registered"):
        register_correlator(name, PerLagCorrelator)
    with pytest.raises(ConfigError, match="name"):
        register_correlator("auto", PerLagCorrelator)
    with pytest.raises(ConfigError, match="factory"):
        register_correlator("other", lambda plan: None)


@pytest.mark.parametrize("run", ["class", "fast", "fast_frame", "fast_from_accumulators"])
def test_unknown_method_is_a_config_error_listing_the_methods(run):
    cfg = ReceiverConfig(samples_per_chip=1, averages=1, gate_len=3)
    codes = np.zeros((1, 7), np.uint8)
    x = np.zeros(7, np.int16)
    calls = {
        "class": lambda: FastReceiver(cfg, codes, method="gpu"),
        "fast": lambda: fast(cfg, codes, x, method="gpu"),
        "fast_frame": lambda: fast_frame(cfg, codes, x[None, :], method="gpu"),
        "fast_from_accumulators": lambda: fast_from_accumulators(
            cfg, codes, np.zeros((1, 1, 7), np.int64), method="gpu"),
    }
    with pytest.raises(ConfigError, match="method") as err:
        calls[run]()
    assert err.value.field == "method"
    for name in correlator_methods():
        assert name in str(err.value)


def test_auto_choice_follows_the_cost_estimates():
    """"auto" is the kernel with the smallest predicted time (ties to the first)."""
    from cdma_lidar.firmware_model.correlators import choose_correlator, estimates

    rng = np.random.default_rng(5)
    for n, k, s, count in [(2047, 40, 4, 66), (511, 5, 2, 1024), (31, 3, 1, 31), (8191, 40, 4,
                                                                                   32766)]:
        plan = GatePlan((1 - 2 * rng.integers(0, 2, (k, n))).astype(np.int8), s, 0, count)
        est = estimates(plan)
        _, _, want = min((e.seconds, i, name) for i, (name, e) in enumerate(est.items()))
        assert choose_correlator(plan) == want


@settings(max_examples=15)
@given(cases(), st.integers(2, 4))
def test_fast_frame_equals_columns(case, columns):
    cfg, codes, x, _ = case
    rng = np.random.default_rng(len(x))
    lo, hi = -(1 << (cfg.adc_bits - 1)), (1 << (cfg.adc_bits - 1)) - 1
    frame = np.stack([x] + [rng.integers(lo, hi + 1, len(x)) for _ in range(columns - 1)])
    outs = fast_frame(cfg, codes, frame)
    assert len(outs) == columns
    for col, out in zip(frame, outs, strict=True):
        assert out.same_as(reference(cfg, codes, col))


def test_hand_computed_example():
    # code 0,0,1 -> ref +1,+1,-1 (S=1); an impulse of 5 at sample 0:
    # raw[l] = ref[(-l) mod 3] * 5 = [5, -5, 5]; ties on |out| go to the lowest j.
    cfg = ReceiverConfig(samples_per_chip=1, averages=1, gate_len=3, peak_exclude=0)
    codes = np.array([[0, 0, 1]])
    x = np.array([5, 0, 0])
    for run in (reference, fast):
        out = run(cfg, codes, x)
        assert out.corr.tolist() == [[5, -5, 5]]
        assert out.peak_lag.tolist() == [0]
        assert out.peak.tolist() == [5]
        assert out.neighbours.tolist() == [[5, -5]]  # lags 2 and 1
        assert (out.noise_count[0], out.noise_sum[0], out.noise_sumsq[0]) == (2, 0, 50)
        assert out.uid_signs.tolist() == [[1]] and out.uid_match.tolist() == [True]


@pytest.mark.parametrize("delay", [0, 1, 7, 37, 79])
def test_echo_delayed_by_d_samples_peaks_at_lag_d(delay):
    rng = np.random.default_rng(delay)
    codes = rng.integers(0, 2, (2, 20))
    s = 4
    cfg = ReceiverConfig(samples_per_chip=s, averages=2, gate_start=0, gate_len=80)
    echo = np.roll(np.repeat(1 - 2 * codes[1], s), delay) * 100
    x = np.tile(echo, 2)
    for run in (reference, fast):
        out = run(cfg, codes, x)
        assert out.peak_lag[1] == delay
        assert out.peak[1] == 2 * 100 * 80


def test_uid_decoding_and_mismatch():
    rng = np.random.default_rng(3)
    codes = rng.integers(0, 2, (1, 15))
    s, n_uid, uid = 2, 3, 0b101
    ref = np.repeat(1 - 2 * codes[0], s)
    echo = np.roll(ref, 5) * 50
    frame = np.concatenate([(-1) ** ((uid >> p) & 1) * echo for p in range(n_uid)])
    x = np.tile(frame, 2)
    ours = ReceiverConfig(samples_per_chip=s, averages=2, uid_bits=n_uid, uid=uid, gate_len=30)
    other = ours.replace(uid=0b011)
    for run in (reference, fast):
        a = run(ours, codes, x)
        assert a.uid_signs.tolist() == [[-1, 1, -1]]
        assert a.uid_observed.tolist() == [uid] and a.uid_match.tolist() == [True]
        assert a.peak_lag.tolist() == [5] and a.peak.tolist() == [3 * 2 * 50 * 30]
        b = run(other, codes, x)  # despread with the wrong UID: periods partly cancel
        assert not b.uid_match[0]
        assert abs(b.peak[0]) < abs(a.peak[0])


def test_no_eligible_lag_reports_minus_one():
    codes = np.array([[0, 1, 1, 0, 1]])
    cfg = ReceiverConfig(samples_per_chip=1, averages=1, gate_start=1, gate_len=3, peaks=2,
                         ghost_windows=((0, 5),))
    x = np.arange(5) * 3
    for run in (reference, fast):
        out = run(cfg, codes, x)
        assert out.peak_lag.tolist() == [-1] and out.peak.tolist() == [0]
        assert out.neighbours.tolist() == [[0, 0]]
        assert out.noise_count.tolist() == [0]
        assert out.extra_lag.tolist() == [[-1]]
        assert out.uid_signs.tolist() == [[0]] and not out.uid_match[0]


def test_second_peak_respects_exclusion_and_is_missing_when_nothing_is_left():
    codes = np.array([[0, 1, 1, 1, 0, 1, 0]])
    cfg = ReceiverConfig(samples_per_chip=1, averages=1, gate_len=7, peak_exclude=3, peaks=3)
    x = np.roll(1 - 2 * codes[0], 2) * 10
    for run in (reference, fast):
        out = run(cfg, codes, x)
        assert out.peak_lag[0] == 2
        # lags 0..6, exclusion |j - 2| <= 3 leaves j = 6 only, then nothing
        assert out.extra_lag.tolist() == [[6, -1]]
        assert out.noise_count.tolist() == [0]


def test_config_validation_names_the_field():
    with pytest.raises(ConfigError, match="adc_bits"):
        ReceiverConfig(adc_bits=17)
    with pytest.raises(ConfigError, match="rounding"):
        ReceiverConfig(rounding="nearest")
    with pytest.raises(ConfigError, match="uid"):
        ReceiverConfig(uid_bits=2, uid=4)
    with pytest.raises(ConfigError, match="ghost_windows"):
        ReceiverConfig(ghost_windows=((1,),))
    with pytest.raises(ConfigError, match="ghost_windows"):
        ReceiverConfig(ghost_windows=((1.5, 2),))  # not silently truncated to 1
    assert ReceiverConfig(ghost_windows=[[np.int64(3), 4]]).ghost_windows == ((3, 4),)
    codes = np.zeros((1, 7), dtype=np.uint8)
    with pytest.raises(ConfigError, match="gate_start"):
        reference(ReceiverConfig(samples_per_chip=1, gate_start=7), codes, np.zeros(70))
    with pytest.raises(ConfigError, match="gate_len"):
        fast(ReceiverConfig(samples_per_chip=1, gate_len=8), codes, np.zeros(70, np.int16))
    with pytest.raises(ConfigError, match="codes"):
        fast(ReceiverConfig(), np.full((1, 7), 2), np.zeros(280, np.int16))


def test_wide_noise_sumsq_is_accepted_and_exact():
    """A noise_sumsq wider than int64 (RTL: SQ_W = 2 OUT_W + G_W) is carried exactly."""
    cfg = ReceiverConfig(gate_len=2047 * 4)  # out_bits = 32, whole period of a degree-11 code
    w = cfg.widths(2047)
    assert w.noise_sumsq == 2 * 29 - 2 + 13 and w.wide_sumsq and w.sumsq_dtype is object
    assert not cfg.replace(out_bits=26).widths(2047).wide_sumsq
    # saturating full-scale data: every out is +-2^31 -> sum of squares ~ 62 * 2^62 > 2^63
    n, s, r, n_uid = 31, 2, 1024, 16
    codes = mseq((5, 2))[None, :]
    cfg = ReceiverConfig(adc_bits=16, samples_per_chip=s, averages=r, uid_bits=n_uid, uid=0,
                         gate_len=n * s, peak_exclude=0, out_bits=32)
    assert cfg.widths(n).noise_sumsq == 68
    lo, hi = -(1 << 15), (1 << 15) - 1
    ref = np.repeat(1 - 2 * codes[0].astype(np.int64), s)
    x = np.tile(np.where(np.roll(ref, 3) > 0, hi, lo), r * n_uid).astype(np.int16)
    want = reference(cfg, codes, x)
    assert want.noise_sumsq.dtype == object
    total = int(want.noise_sumsq[0])
    assert total > 2**63
    assert total == sum(int(v) ** 2 for j, v in enumerate(want.corr[0].tolist()) if j != 3)
    for method in ("matmul", "fft"):
        got = FastReceiver(cfg, codes, method=method).column(x)
        assert got.mismatches(want) == [], method
    assert np.isfinite(want.snr_db()).all()


def test_the_widest_noise_sumsq_is_accepted():
    # 16-bit ADC, S = 64, R = 1024, n = 16, degree 20, whole-period gate, 32-bit output:
    # out^2 <= 2^62 summed over 67108800 < 2^26 lags needs 2*32-2+26 = 88 bits
    big = ReceiverConfig(adc_bits=16, samples_per_chip=64, averages=1024, uid_bits=16,
                         gate_len=(2**20 - 1) * 64, out_bits=32)
    assert big.widths(2**20 - 1).noise_sumsq == 88


def test_two_word_sum_of_squares_is_exact_at_the_largest_terms():
    from cdma_lidar.firmware_model.peaks import _sum_squares

    # the largest square (2^62, out = -2^31) and its neighbours, 2^20 of each per row:
    # the int64 halves stay far from overflow (2^26 lags * 2^31 < 2^58); the result is exact
    terms = np.array([2**62, 2**62 - 1, (2**31 - 1) ** 2, 0, 1], dtype=np.int64)
    sq = np.tile(terms, (2, 2**20))
    where = np.ones(sq.shape, dtype=bool)
    where[1, ::3] = False
    got = _sum_squares(sq, where, wide=True)
    assert got.dtype == object
    for row in range(2):
        assert got[row] == sum(v for v, ok in zip(sq[row].tolist(), where[row].tolist(),
                                                  strict=True) if ok)
    narrow = _sum_squares(sq[:, :5] >> 8, where[:, :5], wide=False)
    assert narrow.dtype == np.int64


def test_widths_of_the_default_and_the_largest_config():
    w = ReceiverConfig().widths(2047)
    assert (w.acc, w.desp, w.raw, w.out, w.noise_sumsq) == (16, 16, 29, 29, 63)
    big = ReceiverConfig(adc_bits=16, samples_per_chip=64, averages=1024, uid_bits=16,
                         gate_len=64, out_bits=24)
    wb = big.widths(2**20 - 1)
    assert wb.raw == 56 and not wb.float_exact
    assert wb.noise_sumsq <= 63


@pytest.mark.parametrize("run", [reference, fast])
def test_bad_samples_are_rejected(run):
    codes = np.zeros((1, 5), dtype=np.uint8)
    cfg = ReceiverConfig(adc_bits=8, samples_per_chip=1, averages=1, gate_len=5)
    with pytest.raises(ConfigError, match="samples"):
        run(cfg, codes, np.array([0, 0, 128, 0, 0]))
    with pytest.raises(ConfigError, match="samples"):
        run(cfg, codes, np.zeros(4, dtype=np.int16))
    with pytest.raises(ConfigError, match="samples"):
        run(cfg, codes, np.zeros(5))


def test_reference_rejects_overfeeding_and_early_finish():
    rx = ReferenceReceiver(ReceiverConfig(samples_per_chip=1, averages=1, gate_len=3),
                           np.zeros((1, 3), np.uint8))
    rx.feed([1, 2])
    with pytest.raises(ConfigError, match="samples"):
        rx.finish()
    with pytest.raises(ConfigError, match="samples"):
        rx.feed([1, 2])
    rx.feed([3])
    assert rx.finish().corr.shape == (1, 3)


@pytest.mark.parametrize(("degree", "gate_len"), [(7, 40), (9, 1022)])
def test_automatic_correlator_choice_on_gold_codes(degree, gate_len):
    from cdma_lidar.firmware_model.correlators import choose_correlator
    from cdma_lidar.firmware_model.gold import gold_family
    from cdma_lidar.firmware_model.pairs import preferred_pairs

    codes = gold_family(*preferred_pairs(degree)[0])[:5]
    n = codes.shape[1]
    cfg = ReceiverConfig(samples_per_chip=2, averages=2, gate_start=200, gate_len=gate_len,
                         out_bits=20, peaks=2)
    rng = np.random.default_rng(gate_len)
    x = rng.integers(-2048, 2048, cfg.column_samples(n))
    rx = FastReceiver(cfg, codes)
    assert rx.correlator_method == choose_correlator(rx.plan)
    got = rx.column(x)
    if degree == 7:
        assert got.mismatches(reference(cfg, codes, x)) == []
    for method in correlator_methods()[1:]:  # the reference would take seconds at degree 9
        assert got.mismatches(FastReceiver(cfg, codes, method=method).column(x)) == [], method


@settings(max_examples=40)
@given(st.integers(1, 4), st.integers(1, 3), st.integers(1, 3), st.data())
def test_uid_echo_straddling_period_boundaries(n_uid, s, r, data):
    """A continuous UID stream delayed by d samples: c_p = A R ((NS - d) s_p + d s_(p-1)).

    docs/firmware.md section 5: the first d samples of period p carry period p - 1's
    polarity, so the signs decode the UID only for d < NS/2 and the despread peak is
    A R (n NS - 2 d t), t the number of cyclic bit changes of the UID.
    """
    n_chips = data.draw(st.integers(3, 15))
    ns = n_chips * s
    uid = data.draw(st.integers(0, (1 << n_uid) - 1))
    d = data.draw(st.integers(0, ns - 1))
    amp = data.draw(st.integers(1, 50))
    codes = np.random.default_rng(d).integers(0, 2, (1, n_chips))
    pol = np.array([-1 if (uid >> p) & 1 else 1 for p in range(n_uid)])
    ref = np.repeat(1 - 2 * codes[0].astype(np.int64), s)
    stream = np.concatenate([q * ref for q in pol])  # one UID frame as emitted
    x = np.tile(np.roll(stream, d), r) * amp  # delayed continuously across periods
    # a one-lag gate at d isolates the correlation there, whatever the code's sidelobes
    cfg = ReceiverConfig(samples_per_chip=s, averages=r, uid_bits=n_uid, uid=uid,
                         gate_start=d, gate_len=1)
    c = amp * r * ((ns - d) * pol + d * np.roll(pol, 1))  # np.roll(pol, 1)[p] = s_(p-1)
    changes = int((pol != np.roll(pol, 1)).sum())
    for run in (reference, fast):
        out = run(cfg, codes, x)
        assert out.peak_lag.tolist() == [d]
        assert out.peak.tolist() == [amp * r * (n_uid * ns - 2 * d * changes)]
        assert out.uid_signs.tolist() == [np.sign(c).tolist()]
        if 2 * d < ns:
            assert out.uid_match.tolist() == [True]


def test_a_large_frame_split_across_threads_equals_its_columns():
    # 16 columns of 32512 samples: the passes outside the kernel run in several threads
    rng = np.random.default_rng(11)
    codes = rng.integers(0, 2, (3, 127))
    cfg = ReceiverConfig(samples_per_chip=4, averages=64, uid_bits=2, uid=2, gate_start=500,
                         gate_len=40, peaks=2, out_shift=3, rounding="convergent")
    frame = rng.integers(-2048, 2048, (16, cfg.column_samples(127))).astype(np.int16)
    rx = FastReceiver(cfg, codes)
    outs = rx.frame(frame)
    acc_outs = rx.from_accumulators(rx.accumulate(frame))
    for col, out, acc_out in zip(frame, outs, acc_outs, strict=True):
        single = rx.column(col)
        assert out.same_as(single) and acc_out.same_as(single)
    assert outs[3].same_as(reference(cfg, codes, frame[3]))


def test_auto_chooses_per_number_of_columns_and_keeps_its_kernels():
    from cdma_lidar.firmware_model.correlators import choose_correlator

    rng = np.random.default_rng(12)
    codes = rng.integers(0, 2, (40, 2047))
    cfg = ReceiverConfig(gate_start=100, gate_len=64)
    rx = FastReceiver(cfg, codes)
    assert rx.correlator_method == choose_correlator(rx.plan)  # plan.columns = 1
    k160 = rx.kernel_for(160)
    assert k160.method == "matmul"  # the paper frame's class: one large product
    assert rx.kernel_for(129) is k160  # same power-of-two bucket, same prepared kernel
    assert FastReceiver(cfg, codes, columns=160).correlator_method == "matmul"
    named = FastReceiver(cfg, codes, method="fft")
    assert named.kernel_for(1).method == named.kernel_for(1000).method == "fft"
    with pytest.raises(ConfigError, match="columns"):
        FastReceiver(cfg, codes, columns=0)


def test_fast_keeps_the_prepared_receiver():
    from cdma_lidar.firmware_model import receiver as rxmod

    rxmod.clear_receiver_cache()
    rng = np.random.default_rng(13)
    codes = rng.integers(0, 2, (2, 31))
    cfg = ReceiverConfig(samples_per_chip=2, averages=2, gate_len=10)
    x = rng.integers(-2048, 2048, cfg.column_samples(31))
    first = fast(cfg, codes, x)
    kept = rxmod._receiver(cfg, codes, "auto")
    assert rxmod._receiver(cfg, codes.copy(), "auto") is kept  # same bits, same receiver
    assert fast(cfg, codes, x).same_as(first)
    other = codes.copy()
    other[0, 0] ^= 1
    assert rxmod._receiver(cfg, other, "auto") is not kept  # different codes: a new plan
    assert fast(cfg, other, x).same_as(reference(cfg, other, x))
    for i in range(rxmod.RECEIVER_CACHE_SIZE + 1):
        rxmod._receiver(cfg.replace(gate_len=3 + i), codes, "auto")
    assert rxmod._receiver(cfg, codes, "auto") is not kept  # evicted, least recently used
    rxmod.clear_receiver_cache()


def test_a_large_frame_with_a_code_out_of_range_is_refused():
    rng = np.random.default_rng(14)
    codes = rng.integers(0, 2, (2, 127))
    cfg = ReceiverConfig(samples_per_chip=4, averages=64, gate_len=40)
    frame = rng.integers(-2048, 2048, (16, cfg.column_samples(127))).astype(np.int16)
    frame[11, 5] = 2048  # one code past the 12-bit range, in a later thread's columns
    with pytest.raises(ConfigError, match="samples"):
        FastReceiver(cfg, codes).frame(frame)


def test_an_unprepared_receiver_builds_its_kernel_on_first_use():
    rng = np.random.default_rng(8)
    codes = rng.integers(0, 2, (3, 31), dtype=np.uint8)
    cfg = ReceiverConfig(samples_per_chip=2, averages=2, gate_len=9)
    x = rng.integers(-2048, 2048, cfg.column_samples(31))
    lazy = FastReceiver(cfg, codes, prepare=False)
    assert lazy._kernels == {} and lazy.plan.count == 11
    assert lazy.column(x).same_as(reference(cfg, codes, x)) and len(lazy._kernels) == 1
