"""rx_chain RTL against cdma_lidar.firmware_model.receiver.reference, word for word.

Every case runs the Icarus build of ``hdl_ref/rtl`` under cocotb (one build per
parameter set, configurations are run-time ports) and compares, per case:

* every ``corr`` word, in stream order j = 0..G-1;
* every result word: peak lag and value, neighbours, noise count/sum/sumsq,
  UID signs/observed/match, extra peaks (``ReceiverOutput.mismatches``);
* the clock counts with the latency documented in docs/hdl.md.

Cases: seeded random configurations (degrees 5-7, S 1-4, gates 8-32 lags, R 1-4,
UID 1-3 bits, ghost windows, 1-3 peaks), extremes (full-scale inputs, wrapping
gates, saturation of an 8-bit output, no eligible lag, zero input, UID
mismatch, gaps in the sample stream), one degree-11 case with the paper's pair
and a 64-lag gate, hypothesis-chosen batches, and a small parameter set
(MAX_UID = MAX_R = MAX_P = 1, 8-bit ADC port) that exercises the degenerate
widths. A deliberately wrong model parameter must make the comparison fail.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from cdma_lidar.firmware_model.gold import gold_code
from cdma_lidar.firmware_model.pairs import PAPER_PAIR, preferred_pairs
from cdma_lidar.firmware_model.receiver import ReceiverConfig, reference
from cdma_lidar.hdl_ref import cosim
from cdma_lidar.hdl_ref.mutants import MUTANTS, mutated_copy
from cdma_lidar.hdl_ref.stimuli import echo_column, full_scale_column
from cdma_lidar.rounding import ROUNDING_MODES

PARAMS = cosim.RxParams(max_deg=11, max_s=4, max_uid=4, max_r=4, max_g=64, max_p=3,
                        nghost=2, adc_w=16, out_w=32)
SMALL = cosim.RxParams(max_deg=5, max_s=1, max_uid=1, max_r=1, max_g=8, max_p=1,
                       nghost=1, adc_w=8, out_w=16)


@dataclasses.dataclass(frozen=True)
class Case:
    """One co-simulation case: configuration, Gold member and column of samples."""

    name: str
    cfg: ReceiverConfig
    pair: tuple[tuple[int, ...], tuple[int, ...]]
    index: int
    samples: tuple[int, ...]
    gap: int = 0  # the source drops s_valid on every gap-th clock (0: never)

    @property
    def code(self) -> np.ndarray:
        return gold_code(self.pair[0], self.pair[1], self.index)

    def model(self, **wrong: object):
        """The model's output; ``wrong`` overrides config fields (or ``index``)."""
        index = int(wrong.pop("index", self.index))
        code = gold_code(self.pair[0], self.pair[1], index)
        cfg = self.cfg.replace(**wrong) if wrong else self.cfg
        return reference(cfg, code[None, :], np.array(self.samples, dtype=np.int64))


def _random_case(pick: Callable[[int, int], int], name: str) -> Case:
    """A configuration and an echo column; ``pick(lo, hi)`` chooses each integer in lo..hi.

    ``pick`` is a seeded numpy generator for the fixed cases and hypothesis's
    ``draw(st.integers(lo, hi))`` for the property test, so hypothesis chooses
    (and shrinks) every field.
    """
    m = pick(5, 7)
    pairs = preferred_pairs(m)
    pair = pairs[pick(0, len(pairs) - 1)]
    n_chips = (1 << m) - 1
    s = pick(1, 4)
    ns = n_chips * s
    n = pick(1, 3)
    r = pick(1, 4)
    b = pick(8, 16)
    g = min(pick(8, 32), ns)
    ghosts = tuple((pick(0, ns - 1), pick(1, 8)) for _ in range(pick(0, 2)))
    cfg = ReceiverConfig(
        adc_bits=b, samples_per_chip=s, averages=r, uid_bits=n,
        uid=pick(0, (1 << n) - 1), gate_start=pick(0, ns - 1), gate_len=g,
        peak_exclude=pick(0, 5), ghost_windows=ghosts,
        out_shift=pick(0, 11), rounding=ROUNDING_MODES[pick(0, 2)],
        out_bits=pick(8, 32), peaks=pick(1, 3),
    )
    index = pick(0, n_chips + 1)
    delay = (cfg.gate_start + pick(0, g - 1)) % ns
    tx_uid = cfg.uid if pick(0, 9) < 7 else pick(0, (1 << n) - 1)
    full = 1 << (b - 1)
    samples = echo_column(
        gold_code(*pair, index), spc=s, averages=r, uid_bits=n, tx_uid=tx_uid, adc_bits=b,
        delay=delay, amplitude=pick(1, 50) / 100 * full, noise_rms=pick(1, 30) / 100 * full,
        rng=np.random.default_rng(pick(0, 2**32 - 1)))
    return Case(name, cfg, pair, index, tuple(samples.tolist()))


def _extreme_cases() -> list[Case]:
    rng = np.random.default_rng(7)
    cases = []
    pair7 = preferred_pairs(7)[0]
    code7 = gold_code(*pair7, 3)
    ns7 = 127 * 4

    # Full scale: every sample at an end code, R = 4, n = 3, 16-bit ADC -> largest raw.
    cfg = ReceiverConfig(adc_bits=16, samples_per_chip=4, averages=4, uid_bits=3, uid=5,
                         gate_start=100, gate_len=32, peak_exclude=2, out_bits=32, peaks=2)
    x = full_scale_column(code7, spc=4, averages=4, uid_bits=3, tx_uid=5, adc_bits=16, delay=117)
    cases.append(Case("full-scale-echo", cfg, pair7, 3, tuple(x.tolist()), gap=3))

    # Every sample the most negative code: the accumulators' negative extreme.
    x = np.full(4 * 2 * ns7, -(1 << 15), dtype=np.int64)
    cfg = ReceiverConfig(adc_bits=16, samples_per_chip=4, averages=4, uid_bits=2, uid=2,
                         gate_start=0, gate_len=16, peak_exclude=1, out_bits=32)
    cases.append(Case("full-scale-negative-dc", cfg, pair7, 3, tuple(x.tolist())))

    # Gate wrapping through lag 0, echo inside the wrapped part; first lag's
    # left neighbour at NS - 1.
    pair6 = preferred_pairs(6)[0]
    ns6 = 63 * 3
    cfg = ReceiverConfig(adc_bits=12, samples_per_chip=3, averages=2, uid_bits=1,
                         gate_start=ns6 - 10, gate_len=24, peak_exclude=3, peaks=2,
                         out_shift=3, rounding="convergent", ghost_windows=((ns6 - 2, 4),))
    x = echo_column(gold_code(*pair6, 10), spc=3, averages=2, uid_bits=1, tx_uid=0, adc_bits=12,
                    delay=5, amplitude=600.0, noise_rms=80.0, rng=rng)
    cases.append(Case("wrapping-gate", cfg, pair6, 10, tuple(x.tolist()), gap=7))
    cfg = cfg.replace(gate_start=0, gate_len=12, ghost_windows=())
    x = echo_column(gold_code(*pair6, 10), spc=3, averages=2, uid_bits=1, tx_uid=0, adc_bits=12,
                    delay=0, amplitude=600.0, noise_rms=80.0, rng=rng)
    cases.append(Case("peak-at-lag-0", cfg, pair6, 10, tuple(x.tolist())))

    # Narrow output: 8-bit words saturate on the peak and on the sidelobes.
    pair5 = preferred_pairs(5)[1]
    cfg = ReceiverConfig(adc_bits=14, samples_per_chip=2, averages=3, uid_bits=2, uid=1,
                         gate_start=20, gate_len=30, peak_exclude=2, out_shift=2,
                         rounding="half_up", out_bits=8, peaks=3)
    x = echo_column(gold_code(*pair5, 30), spc=2, averages=3, uid_bits=2, tx_uid=1, adc_bits=14,
                    delay=33, amplitude=3000.0, noise_rms=2000.0, rng=rng)
    cases.append(Case("saturated-8-bit-output", cfg, pair5, 30, tuple(x.tolist())))

    # Every gate lag in a ghost window: no peak (-1, 0, zero signs, no match).
    cfg = ReceiverConfig(adc_bits=10, samples_per_chip=1, averages=1, uid_bits=2, uid=3,
                         gate_start=10, gate_len=8, ghost_windows=((8, 5), (13, 6)), peaks=2)
    x = echo_column(gold_code(*pair5, 4), spc=1, averages=1, uid_bits=2, tx_uid=3, adc_bits=10,
                    delay=12, amplitude=100.0, noise_rms=20.0, rng=rng)
    cases.append(Case("all-ghost-no-peak", cfg, pair5, 4, tuple(x.tolist())))

    # Exclusion wider than the gate: only the first of three peaks exists.
    cfg = ReceiverConfig(adc_bits=10, samples_per_chip=2, averages=2, uid_bits=1,
                         gate_start=5, gate_len=9, peak_exclude=40, peaks=3)
    x = echo_column(gold_code(*pair5, 6), spc=2, averages=2, uid_bits=1, tx_uid=0, adc_bits=10,
                    delay=9, amplitude=100.0, noise_rms=20.0, rng=rng)
    cases.append(Case("later-peaks-missing", cfg, pair5, 6, tuple(x.tolist())))

    # Zero input: every correlation 0, UID signs 0, no match, peak at j = 0.
    cfg = ReceiverConfig(adc_bits=8, samples_per_chip=1, averages=2, uid_bits=3, uid=6,
                         gate_start=3, gate_len=10, peaks=2, peak_exclude=1)
    cases.append(Case("zero-input", cfg, pair5, 2, (0,) * (2 * 3 * 31)))

    # Another emitter's UID on our code: signs show its pattern, no match.
    cfg = ReceiverConfig(adc_bits=12, samples_per_chip=2, averages=2, uid_bits=3, uid=1,
                         gate_start=0, gate_len=20, peak_exclude=2)
    x = echo_column(gold_code(*pair5, 7), spc=2, averages=2, uid_bits=3, tx_uid=6, adc_bits=12,
                    delay=11, amplitude=500.0, noise_rms=50.0, rng=rng)
    cases.append(Case("foreign-uid", cfg, pair5, 7, tuple(x.tolist())))
    return cases


def _degree11_case() -> Case:
    rng = np.random.default_rng(11)
    index = 5
    cfg = ReceiverConfig(adc_bits=12, samples_per_chip=1, averages=2, uid_bits=1, uid=0,
                         gate_start=2000, gate_len=64, peak_exclude=4,
                         ghost_windows=((2010, 3),), out_shift=4, rounding="convergent",
                         out_bits=16, peaks=2)
    x = echo_column(gold_code(*PAPER_PAIR, index), spc=1, averages=2, uid_bits=1, tx_uid=0,
                    adc_bits=12, delay=2030, amplitude=150.0, noise_rms=400.0, rng=rng)
    return Case("degree-11-paper-pair", cfg, PAPER_PAIR, index, tuple(x.tolist()))


def _fixed_cases() -> list[Case]:
    rng = np.random.default_rng(20261121)

    def pick(lo: int, hi: int) -> int:
        return int(rng.integers(lo, hi + 1))

    cases = [_random_case(pick, f"random-{k}") for k in range(10)]
    return cases + _extreme_cases() + [_degree11_case()]


FIXED = _fixed_cases()


def _simulate(builder, params: cosim.RxParams, cases: list[Case], name: str) -> list[dict]:
    """Run ``cases`` in one simulation; return per case the ports and raw result."""
    build_dir = builder(params)
    ports = [cosim.rx_ports(c.cfg, c.pair[0], c.pair[1], c.index, params) for c in cases]
    job = {"cases": [{"ports": p, "samples": list(c.samples), "gap": c.gap}
                     for p, c in zip(ports, cases, strict=True)]}
    raw = cosim.run_job(cosim.RX_TOP, "cdma_lidar.hdl_ref.tb.test_rx_chain", build_dir, job,
                        name=name)
    return [{"ports": p, "raw": r} for p, r in zip(ports, raw["cases"], strict=True)]


def _rtl_output(run: dict, params: cosim.RxParams):
    return cosim.to_receiver_output(cosim.decode_rx_result(run["raw"], run["ports"], params))


def _check(case: Case, run: dict, params: cosim.RxParams) -> None:
    """Assert that the RTL's words and clock counts are those of the model."""
    g = case.cfg.gate_len
    assert [j for j, _ in run["raw"]["corr"]] == list(range(g)), "corr stream order"
    rtl = _rtl_output(run, params)
    model = case.model()
    bad = model.mismatches(rtl)
    assert not bad, {f: (getattr(model, f).tolist(), getattr(rtl, f).tolist()) for f in bad}
    assert run["raw"]["clocks"] == cosim.rx_latency_clocks(run["ports"], gap=case.gap)


@pytest.fixture(scope="module")
def fixed_runs(rx_builder) -> list[dict]:
    return _simulate(rx_builder, PARAMS, FIXED, "fixed")


@pytest.mark.hdl
@pytest.mark.parametrize("k", range(len(FIXED)), ids=[c.name for c in FIXED])
def test_rtl_equals_model(fixed_runs, k):
    _check(FIXED[k], fixed_runs[k], PARAMS)


def test_extremes_reach_their_extremes():
    """The extreme stimuli do what their names say (checked on the model)."""
    by_name = {c.name: c for c in FIXED}
    full = by_name["full-scale-echo"]
    out = full.model()
    terms = 127 * 4 * 4 * 3  # NS * R * n products, each of magnitude 2^15 - 1 or 2^15
    assert terms * ((1 << 15) - 1) <= abs(int(out.peak[0])) <= terms * (1 << 15)
    sat = by_name["saturated-8-bit-output"].model()
    assert np.isin(sat.corr, (-128, 127)).sum() >= 2
    assert by_name["all-ghost-no-peak"].model().peak_lag[0] == -1
    late = by_name["later-peaks-missing"].model()
    assert late.peak_lag[0] >= 0 and (late.extra_lag[0] == -1).all()
    wrap = by_name["wrapping-gate"]
    ns6 = 63 * 3
    assert wrap.cfg.gate_start + wrap.cfg.gate_len > ns6
    assert not by_name["foreign-uid"].model().uid_match[0]


@pytest.mark.hdl
@pytest.mark.parametrize(("name", "wrong"), [
    ("saturated-8-bit-output", {"gate_start": 21}),   # lags shifted by one sample
    ("saturated-8-bit-output", {"index": 31}),        # the neighbouring Gold member
    ("saturated-8-bit-output", {"out_bits": 9}),      # saturation width
    ("wrapping-gate", {"rounding": "truncate"}),      # rounding of the output shift
    ("foreign-uid", {"uid": 6}),                      # our UID
], ids=["gate_start", "code_index", "out_bits", "rounding", "uid"])
def test_wrong_model_parameter_is_caught(fixed_runs, name, wrong):
    """A model run with one wrong parameter disagrees with the RTL: the test can fail."""
    k = next(i for i, c in enumerate(FIXED) if c.name == name)
    case = FIXED[k]
    rtl = _rtl_output(fixed_runs[k], PARAMS)
    assert not case.model().mismatches(rtl)
    assert case.model(**wrong).mismatches(rtl)


@st.composite
def _batches(draw) -> list[Case]:
    def pick(lo: int, hi: int) -> int:
        return draw(st.integers(lo, hi))

    return [_random_case(pick, f"hyp-{k}") for k in range(draw(st.integers(3, 5)))]


@pytest.mark.hdl
@settings(max_examples=3, suppress_health_check=[HealthCheck.too_slow])
@given(batch=_batches())
def test_rtl_equals_model_hypothesis(rx_builder, batch):
    runs = _simulate(rx_builder, PARAMS, batch, "hypothesis")
    for case, run in zip(batch, runs, strict=True):
        _check(case, run, PARAMS)


def _small_cases() -> list[Case]:
    rng = np.random.default_rng(5)
    cases = []
    for k, (rounding, shift, bits) in enumerate([("truncate", 0, 16), ("half_up", 3, 8),
                                                 ("convergent", 5, 12)]):
        pair = preferred_pairs(5)[k]
        cfg = ReceiverConfig(adc_bits=8, samples_per_chip=1, averages=1, uid_bits=1,
                             uid=k % 2, gate_start=int(rng.integers(0, 31)), gate_len=8,
                             peak_exclude=1, ghost_windows=((int(rng.integers(0, 31)), 2),),
                             out_shift=shift, rounding=rounding, out_bits=bits)
        x = echo_column(gold_code(*pair, k), spc=1, averages=1, uid_bits=1, tx_uid=k % 2,
                        adc_bits=8, delay=cfg.gate_start + 3, amplitude=60.0, noise_rms=30.0,
                        rng=rng)
        cases.append(Case(f"small-{rounding}", cfg, pair, k, tuple(x.tolist())))
    return cases


@pytest.mark.hdl
def test_small_parameter_set(rx_builder):
    """A build with single-entry maxima (no UID, R = 1, P = 1, 8-bit ADC, 16-bit out)."""
    cases = _small_cases()
    for case, run in zip(cases, _simulate(rx_builder, SMALL, cases, "small"), strict=True):
        _check(case, run, SMALL)


def _chain_mutant_cases() -> list[Case]:
    """A period whose correlation is 0 at the peak; rounding at out_shift 17..20 (half_up)."""
    rng = np.random.default_rng(9)
    pair5 = preferred_pairs(5)[0]
    cfg = ReceiverConfig(adc_bits=12, samples_per_chip=2, averages=2, uid_bits=2, uid=0,
                         gate_start=20, gate_len=16, peak_exclude=2)
    x = echo_column(gold_code(*pair5, 1), spc=2, averages=2, uid_bits=2, tx_uid=0, adc_bits=12,
                    delay=25, amplitude=600.0, noise_rms=40.0, rng=rng).reshape(2, 2, 62)
    x[:, 1, :] = 0
    cases = [Case("uid-period-zero-sign", cfg, pair5, 1, tuple(x.reshape(-1).tolist()))]
    full = full_scale_column(gold_code(*pair5, 3), spc=4, averages=4, uid_bits=1, tx_uid=1,
                             adc_bits=16, delay=17)
    for shift in (17, 19):  # |raw| reaches 124 * 4 * 2^15 = 2^24
        cfg = ReceiverConfig(adc_bits=16, samples_per_chip=4, averages=4, uid_bits=1, uid=1,
                             gate_start=10, gate_len=16, peak_exclude=2, out_shift=shift,
                             rounding="half_up", out_bits=32)
        cases.append(Case(f"half-up-shift-{shift}", cfg, pair5, 3, tuple(full.tolist())))
    return cases


@pytest.fixture(scope="module")
def chain_mutant_cases(rx_builder) -> list[Case]:
    """The mutants' cases, checked on the unchanged RTL first."""
    cases = _chain_mutant_cases()
    for case, run in zip(cases, _simulate(rx_builder, PARAMS, cases, "mutant-cases"),
                         strict=True):
        _check(case, run, PARAMS)
    return cases


@pytest.mark.hdl
@pytest.mark.parametrize("mutant", [m for m in MUTANTS if m.file == "rx_chain.v"],
                         ids=lambda m: m.name)
def test_rx_chain_mutant_is_caught(chain_mutant_cases, hdl_build_root, mutant):
    """rx_chain with a deliberate fault disagrees with the model; unchanged, it agrees."""
    cases = chain_mutant_cases
    rtl = mutated_copy(mutant, hdl_build_root / f"rtl_{mutant.name}")
    built = cosim.build(cosim.RX_TOP, PARAMS.generics(), hdl_build_root / f"rx_{mutant.name}",
                        rtl_dir=rtl)
    bad = []
    try:
        runs = _simulate(lambda _: built, PARAMS, cases, "mutant")
    except (RuntimeError, SystemExit):  # a hang, failed by the bench's watchdog in seconds
        return
    for case, run in zip(cases, runs, strict=True):
        bad += case.model().mismatches(_rtl_output(run, PARAMS))
    assert bad, f"{mutant.name} was not caught"
