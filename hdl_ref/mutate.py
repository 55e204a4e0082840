"""``python -m cdma_lidar.hdl_ref.mutate``: which fast test kills each RTL fault.

Every fault of :data:`cdma_lidar.hdl_ref.mutants.MUTANTS` is applied alone to a
copy of ``hdl_ref/rtl`` (:func:`~cdma_lidar.hdl_ref.mutants.mutated_copy`); the
fast co-simulation suite (``tests/hdl_ref`` without the ``slow`` tests, the
mutant tests themselves and the tool checks: simulation only) then runs against
that copy (``$HDL_REF_RTL_DIR``, read by :func:`cdma_lidar.hdl_ref.cosim.build`
and the vectors test) and stops at the first failing test, which is reported as
the fault's killer. A fault that no test fails "survives"; so does one whose run
outlasts the time limit ("timeout": a hang must be caught by the bench's cycle
watchdog, which fails a test, not by the clock); one marked ``equivalent`` (it
changes no output, with the reason) is listed and not run.
The tests of the mutated file run first (the cheapest kill).

    python -m cdma_lidar.hdl_ref.mutate                 # every fault (tens of minutes)
    python -m cdma_lidar.hdl_ref.mutate --only NAME     # one fault (repeatable)
    python -m cdma_lidar.hdl_ref.mutate --jobs 2        # two faults at a time
    python -m cdma_lidar.hdl_ref.mutate --write-doc     # and the table in docs/hdl.md

With ``--only`` and ``--write-doc`` the rows of the faults run replace theirs in the
table and the other rows stay as the earlier runs wrote them (the tally is counted
from the rows); a fault without a row is "not run".

Exit status 0 when every non-equivalent fault is killed, 1 otherwise, 2 for an
unknown ``--only`` name.
"""

from __future__ import annotations

import argparse
import logging
import os
import re
import subprocess
import sys
import tempfile
from collections.abc import Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path

from cdma_lidar.errors import ConfigError
from cdma_lidar.fileio import atomic_write_text
from cdma_lidar.hdl_ref.cosim import RTL_ENV
from cdma_lidar.hdl_ref.mutants import MUTANTS, Mutant, mutated_copy

__all__ = ["Outcome", "main", "run_mutant", "test_order"]

log = logging.getLogger(__name__)

ROOT = Path(__file__).resolve().parent.parent
TESTS = ROOT / "tests" / "hdl_ref"
DOC_PATH = ROOT / "docs" / "hdl.md"
BEGIN, END = "<!-- mutate:begin -->", "<!-- mutate:end -->"
#: simulation test files, and which of them to try first for a fault in each RTL file
SIM_TESTS = ("test_gold_gen.py", "test_sdp_ram.py", "test_out_scale.py", "test_rx_top.py",
             "test_rx_chain.py", "test_vectors.py", "test_adc_top.py")
#: (the rx_top cases that kill most faults before the long hypothesis and Verilator runs)
_TOP_FIRST = ("test_rx_top.py::test_top_equals_model",
              "test_rx_top.py::test_sweep_build_equals_model",
              "test_rx_top.py::test_top_equals_model_on_verilator")
FIRST: dict[str, tuple[str, ...]] = {
    "lfsr_fib.v": ("test_gold_gen.py",), "gold_gen.v": ("test_gold_gen.py",),
    "sdp_ram.v": ("test_sdp_ram.py",), "out_scale.v": ("test_out_scale.py",),
    "rx_post.v": (*_TOP_FIRST, "test_rx_chain.py"), "rx_top.v": _TOP_FIRST,
    "rx_chain.v": ("test_rx_chain.py",), "adc_rx.v": ("test_adc_top.py",),
    "r_min_rom.v": ("test_adc_top.py",), "rx_adc_top.v": ("test_adc_top.py",),
}
#: tests that are not a simulation of the mutated RTL (the per-mutant tests build their
#: own mutant from the unchanged sources; the tool checks count cells or lint)
DESELECT = "not mutant"
#: a failing test, or one whose fixture failed (a simulation that hangs raises in the
#: fixture that runs it: the bench's watchdog)
_FAILED = re.compile(r"^(?:FAILED|ERROR) (\S+)", re.MULTILINE)


@dataclass(frozen=True)
class Outcome:
    """What the fast suite did with one fault: ``killer`` is the first failing test's id,
    empty when no test failed (the fault survived: every test passed, or the run timed
    out, said in ``detail``) or the fault is equivalent."""

    mutant: Mutant
    killer: str = ""
    detail: str = ""
    #: False for a fault a cut-off run did not reach (listed, counted apart)
    ran: bool = True

    @property
    def status(self) -> str:
        if self.mutant.equivalent:
            return "equivalent"
        if not self.ran:
            return "not run"
        return "killed" if self.killer else "SURVIVED"


def test_order(mutant: Mutant) -> list[str]:
    """The simulation tests (files or test ids), those of the mutated file first."""
    first = FIRST.get(mutant.file, ())
    return [*first, *(t for t in SIM_TESTS if t not in first)]


def run_mutant(mutant: Mutant, tests: Sequence[str] | None = None,
               timeout_s: float = 900.0) -> Outcome:
    """Apply ``mutant``, run ``tests`` (default :func:`test_order`) until one fails."""
    if mutant.equivalent:
        return Outcome(mutant, detail=mutant.equivalent)
    with tempfile.TemporaryDirectory(prefix=f"mutant_{mutant.name}_") as tmp:
        rtl = mutated_copy(mutant, Path(tmp) / "rtl")
        cmd = [sys.executable, "-m", "pytest", "-q", "-x", "-p", "no:randomly", "-p",
               "no:cacheprovider", "-rfE", "-k", DESELECT,
               "--basetemp", str(Path(tmp) / "pytest"),
               *(str(TESTS / t) for t in (tests or test_order(mutant)))]
        env = {**os.environ, RTL_ENV: str(rtl)}
        try:
            proc = subprocess.run(cmd, cwd=ROOT, env=env, capture_output=True, text=True,
                                  timeout=timeout_s, check=False)
        except subprocess.TimeoutExpired:    # not a kill: no test failed
            return Outcome(mutant, detail=f"timeout: no result in {timeout_s:g} s")
    found = _FAILED.search(proc.stdout)
    if found:
        return Outcome(mutant, killer=found.group(1).replace(str(TESTS) + "/", ""))
    if proc.returncode != 0:   # an error outside a test (collection, fixture): not a kill
        return Outcome(mutant, detail=f"pytest exit {proc.returncode}: "
                                      f"{proc.stdout.strip().splitlines()[-1:]}")
    return Outcome(mutant)


def _row(o: Outcome) -> str:
    what = (f"killed by `{o.killer}`" if o.status == "killed"
            else f"equivalent: {o.detail}" if o.status == "equivalent"
            else "not run" if o.status == "not run"
            else f"**survived** {o.detail}".rstrip())
    return f"| `{o.mutant.name}` | `{o.mutant.file}` | {o.mutant.why} | {what} |"


#: a row's result cell -> its status (the inverse of _row)
_STATUS = (("killed by", "killed"), ("equivalent:", "equivalent"), ("not run", "not run"),
           ("**survived**", "SURVIVED"))


def _rows_table(rows: Sequence[str]) -> str:
    statuses = [next(s for head, s in _STATUS if r.rsplit(" | ", 1)[1].startswith(head))
                for r in rows]
    killed, equivalent, not_run, survived = (statuses.count(s) for s in (
        "killed", "equivalent", "not run", "SURVIVED"))
    lines = ["| mutant | file | fault | result |", "|---|---|---|---|", *rows, ""]
    lines.append(f"Killed {killed} of {len(rows)} faults ({equivalent} equivalent, "
                 f"{survived} survived" + (f", {not_run} not run" if not_run else "") + ").")
    return "\n".join(lines) + "\n"


def table(outcomes: Sequence[Outcome]) -> str:
    """The markdown table of every fault and its killer, and the tally."""
    return _rows_table([_row(o) for o in outcomes])


def merged_table(block: str, outcomes: Sequence[Outcome]) -> str:
    """The table of every fault of MUTANTS: the rows of ``outcomes``, the other faults'
    rows as ``block`` (an earlier table) has them, "not run" for a fault it lacks."""
    old = {line.split("`")[1]: line for line in block.splitlines()
           if line.startswith("| `")}
    new = {o.mutant.name: _row(o) for o in outcomes}
    return _rows_table([new.get(m.name) or old.get(m.name) or _row(Outcome(m, ran=False))
                        for m in MUTANTS])


def update_doc(text: str, block: str) -> str:
    """``text`` with the block between the mutate markers replaced by ``block``."""
    start, end = text.find(BEGIN), text.find(END)
    if start < 0 or end < start:
        raise ConfigError(f"docs/hdl.md must contain {BEGIN} ... {END}", "docs/hdl.md")
    return text[:start + len(BEGIN)] + "\n" + block + text[end:]


def main(argv: list[str] | None = None) -> int:
    """Run every fault (or ``--only`` ones) and print which test kills each."""
    parser = argparse.ArgumentParser(prog="python -m cdma_lidar.hdl_ref.mutate",
                                     description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--only", action="append", default=[], metavar="NAME",
                        help="run this fault only (repeatable)")
    parser.add_argument("--jobs", type=int, default=1, metavar="N",
                        help="faults run at once (default 1)")
    parser.add_argument("--write-doc", action="store_true",
                        help=f"replace the mutation table of {DOC_PATH}")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    names = {m.name for m in MUTANTS}
    unknown = [n for n in args.only if n not in names]
    if unknown:
        sys.stderr.write(f"--only: unknown mutant {unknown[0]!r} (python -m "
                         f"cdma_lidar.hdl_ref.mutate lists them all)\n")
        return 2
    chosen = [m for m in MUTANTS if not args.only or m.name in args.only]

    def one(m: Mutant) -> Outcome:
        outcome = run_mutant(m)
        log.info("%-40s %s %s", m.name, outcome.status, outcome.killer or outcome.detail)
        return outcome

    with ThreadPoolExecutor(max(1, args.jobs)) as pool:    # each fault: its own pytest
        outcomes = list(pool.map(one, chosen))
    text = table(outcomes)
    if args.write_doc:
        doc = DOC_PATH.read_text()
        if args.only:
            text = merged_table(doc[doc.find(BEGIN):doc.find(END)], outcomes)
        atomic_write_text(DOC_PATH, update_doc(doc, text))
    sys.stdout.write(text)
    return 0 if all(o.status != "SURVIVED" for o in outcomes) else 1


if __name__ == "__main__":
    raise SystemExit(main())
