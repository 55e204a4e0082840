"""gold_gen RTL against cdma_lidar.firmware_model.gold/.uid, clock by clock.

One simulation plays every case: seeds from ``gold_seeds`` (the model's
jump-ahead), a random enable pattern, and for every clock the RTL's chip,
unmodulated chip, chip index and UID period are compared with the model's
member ``index`` of the pair, polarity-modulated with the UID.
"""

from __future__ import annotations

import numpy as np
import pytest

from cdma_lidar.firmware_model.gold import gold_code
from cdma_lidar.firmware_model.pairs import PAPER_PAIR, preferred_pairs
from cdma_lidar.firmware_model.uid import polarity_modulate
from cdma_lidar.hdl_ref import cosim

PARAMS = cosim.GoldParams(max_deg=11, max_uid=8)


def _cases() -> list[dict]:
    rng = np.random.default_rng(20261121)
    cases = []
    for m in (5, 6, 7, 5, 6, 7):
        pu, pv = preferred_pairs(m)[int(rng.integers(len(preferred_pairs(m))))]
        n_chips = (1 << m) - 1
        cases.append({"pair": (pu, pv), "index": int(rng.integers(0, n_chips + 2)),
                      "uid_bits": int(rng.integers(1, 5)), "enable": 0.75})
    n7 = (1 << 7) - 1
    # members N (u alone) and N + 1 (v alone): the LFSRs' own m-sequences
    cases.append({"pair": preferred_pairs(7)[0], "index": n7, "uid_bits": 1, "enable": 1.0})
    cases.append({"pair": preferred_pairs(7)[0], "index": n7 + 1, "uid_bits": 2, "enable": 0.5})
    cases.append({"pair": PAPER_PAIR, "index": 1234, "uid_bits": 3, "enable": 1.0})
    # reloads at random clocks, often together with an enable (load wins)
    for m in (5, 6):
        cases.append({"pair": preferred_pairs(m)[0], "index": 3, "uid_bits": 2, "enable": 0.75,
                      "reload": 0.06})
    for c in cases:
        c["uid"] = int(rng.integers(0, 1 << c["uid_bits"]))
        n_chips = (1 << c["pair"][0][0]) - 1
        # two whole UID frames (plus a few chips) of enabled clocks
        want = 2 * c["uid_bits"] * n_chips + 5 if n_chips < 2047 else c["uid_bits"] * n_chips + 5
        clocks = int(want / c["enable"]) + 8
        en = (rng.random(clocks) < c["enable"]).astype(int)
        c["en"] = en.tolist()
        if "reload" in c:
            c["load"] = (rng.random(clocks) < c["reload"]).astype(int).tolist()
    return cases


CASES = _cases()


def _expected(case: dict) -> dict[str, np.ndarray]:
    """Model chips for every clock: chip c is chip number (enables since the last load) of
    the UID stream; a load restarts at chip 0 whatever ``en`` says in its clock."""
    (pu, pv), index, n, uid = case["pair"], case["index"], case["uid_bits"], case["uid"]
    n_chips = (1 << pu[0]) - 1
    code = gold_code(pu, pv, index)
    frame = polarity_modulate(code, uid, n)
    steps, count = [], 0
    for en, load in zip(case["en"], case.get("load", [0] * len(case["en"])), strict=True):
        steps.append(count)
        count = 0 if load else count + en
    step = np.array(steps)
    return {
        "chip": frame[step % frame.size],
        "chip_raw": code[step % n_chips],
        "chip_index": step % n_chips,
        "period": (step // n_chips) % n,
    }


@pytest.fixture(scope="module")
def gold_run(gold_builder) -> list[dict]:
    build_dir = gold_builder(PARAMS)
    job = {"cases": [
        {"ports": cosim.gold_ports(c["pair"][0], c["pair"][1], c["index"], c["uid"],
                                   c["uid_bits"], PARAMS), "en": c["en"],
         **({"load": c["load"]} if "load" in c else {})}
        for c in CASES
    ]}
    return cosim.run_job(cosim.GOLD_TOP, "cdma_lidar.hdl_ref.tb.test_gold_gen", build_dir, job,
                         name="gold")["cases"]


@pytest.mark.hdl
@pytest.mark.parametrize("k", range(len(CASES)),
                         ids=[f"m{c['pair'][0][0]}-idx{c['index']}-n{c['uid_bits']}"
                              + ("-reload" if "load" in c else "") for c in CASES])
def test_gold_chips_clock_by_clock(gold_run, k):
    got = gold_run[k]
    want = _expected(CASES[k])
    for key, values in want.items():
        rtl = np.array(got[key])
        assert rtl.shape == values.shape, key
        bad = np.flatnonzero(rtl != values)
        assert bad.size == 0, f"{key}: first mismatch at clock {bad[:1]} of {rtl.size}"


@pytest.mark.hdl
def test_wrong_member_is_detected(gold_run):
    """The comparison can fail: the RTL's stream is not the neighbouring member's."""
    case = dict(CASES[0])
    n_chips = (1 << case["pair"][0][0]) - 1
    case["index"] = (case["index"] + 1) % n_chips
    want = _expected(case)
    assert np.any(np.array(gold_run[0]["chip"]) != want["chip"])


def test_reload_cases_load_and_enable_together():
    """The reload cases do what they claim: loads, some in a clock with en high."""
    pairs = [(np.array(c["load"]), np.array(c["en"])) for c in CASES if "load" in c]
    assert all((load & en).sum() >= 2 for load, en in pairs)
    assert any((load & (1 - en)).any() for load, en in pairs)


@pytest.mark.hdl
def test_lfsr_mutant_en_beats_load_is_caught(hdl_build_root):
    """lfsr_fib with enable over load: the reload cases see it, clock by clock."""
    from cdma_lidar.hdl_ref.mutants import MUTANTS, mutated_copy

    (mutant,) = [m for m in MUTANTS if m.name == "en-beats-load"]
    rtl = mutated_copy(mutant, hdl_build_root / f"rtl_{mutant.name}")
    build_dir = cosim.build(cosim.GOLD_TOP, PARAMS.generics(),
                            hdl_build_root / f"gold_{mutant.name}", rtl_dir=rtl)
    cases = [c for c in CASES if "load" in c]
    job = {"cases": [{"ports": cosim.gold_ports(c["pair"][0], c["pair"][1], c["index"],
                                                c["uid"], c["uid_bits"], PARAMS),
                      "en": c["en"], "load": c["load"]} for c in cases]}
    got = cosim.run_job(cosim.GOLD_TOP, "cdma_lidar.hdl_ref.tb.test_gold_gen", build_dir, job,
                        name="gold_mutant")["cases"]
    assert any(np.any(np.array(g["chip_raw"]) != _expected(c)["chip_raw"])
               for g, c in zip(got, cases, strict=True))
