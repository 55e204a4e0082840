"""``python -m cdma_lidar.hdl_ref.mutate``: every listed RTL fault is killed by a fast test.

The full run (every fault against the fast co-simulation suite, tens of minutes) is in
the slow set; the normal suite checks that every fault still applies to the RTL and
runs one fault end to end.
"""

from __future__ import annotations

import pytest

from cdma_lidar.hdl_ref import cosim, mutate
from cdma_lidar.hdl_ref.mutants import MUTANTS


def test_every_fault_applies_once(tmp_path):
    """Each fault's original text occurs exactly once in its file (else mutated_copy raises)."""
    for m in MUTANTS:
        assert (cosim.RTL_DIR / m.file).read_text().count(m.original) == 1, m.name
    assert len({m.name for m in MUTANTS}) == len(MUTANTS)


@pytest.mark.hdl
def test_one_fault_is_killed_and_reported():
    if not cosim.iverilog_available():
        pytest.skip("Icarus Verilog is not installed")
    (m,) = [m for m in MUTANTS if m.name == "lfsr-output-stage-off-by-one"]
    out = mutate.run_mutant(m, tests=["test_gold_gen.py"])
    assert out.status == "killed" and "test_gold_gen.py::" in out.killer
    text = mutate.table([out, mutate.run_mutant(next(x for x in MUTANTS if x.equivalent))])
    assert "Killed 1 of 2 faults (1 equivalent, 0 survived)" in text


def test_a_timeout_is_not_a_kill():
    """A run cut off by the time limit failed no test: the fault survives, "timeout" says why
    (a hang must fail a test through the bench's cycle watchdog)."""
    (m,) = [m for m in MUTANTS if m.name == "lfsr-output-stage-off-by-one"]
    out = mutate.run_mutant(m, tests=["test_gold_gen.py"], timeout_s=0)
    assert out.status == "SURVIVED" and out.killer == "" and out.detail.startswith("timeout")
    assert "**survived** timeout" in mutate.table([out])


def test_partial_run_merges_into_the_table():
    """--only with --write-doc: the faults run replace their rows, the others keep theirs,
    a fault without a row is "not run", and the tally is counted from the rows."""
    a, b, c = MUTANTS[:3]
    old = mutate.table([mutate.Outcome(a, killer="t.py::x"), mutate.Outcome(b)])
    assert "1 survived" in old
    new = mutate.merged_table(old, [mutate.Outcome(b, killer="t.py::y")])
    rows = [r for r in new.splitlines() if r.startswith("| `")]
    assert rows[:3] == [mutate._row(mutate.Outcome(a, killer="t.py::x")),
                        mutate._row(mutate.Outcome(b, killer="t.py::y")),
                        mutate._row(mutate.Outcome(c, ran=False))]
    eq = sum(bool(m.equivalent) for m in MUTANTS)       # listed as equivalent, never run
    assert f"Killed 2 of {len(MUTANTS)} faults ({eq} equivalent, 0 survived, " \
           f"{len(MUTANTS) - 2 - eq} not run)." in new


def test_unknown_name_exits_2(capsys):
    assert mutate.main(["--only", "no-such-fault"]) == 2
    assert "no-such-fault" in capsys.readouterr().err


@pytest.mark.hdl
@pytest.mark.slow
def test_every_fault_is_killed():
    """The whole list: every non-equivalent fault fails a fast test (exit status 0)."""
    assert mutate.main([]) == 0
