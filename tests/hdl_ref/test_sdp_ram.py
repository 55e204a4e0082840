"""sdp_ram against its documented behaviour, clock by clock, read-during-write included.

Random writes and reads over a small RAM, a third of the reads at the address being
written in the same clock (the RTL returns the old word: docs/hdl.md, ``sdp_ram``),
for both output latencies (OUTREG 0 and 1). The mutant that forwards the new word
(``rdw-returns-new``) must fail the same comparison.
"""

from __future__ import annotations

import numpy as np
import pytest

from cdma_lidar.hdl_ref import cosim
from cdma_lidar.hdl_ref.mutants import MUTANTS, mutated_copy

WIDTH, DEPTH, CLOCKS = 8, 16, 400


def _commands() -> dict[str, list[int]]:
    rng = np.random.default_rng(27)
    we = (rng.random(CLOCKS) < 0.6).astype(int)
    waddr = rng.integers(0, DEPTH, CLOCKS)
    raddr = np.where(rng.random(CLOCKS) < 0.35, waddr, rng.integers(0, DEPTH, CLOCKS))
    return {"we": we.tolist(), "waddr": waddr.tolist(),
            "wdata": rng.integers(0, 1 << WIDTH, CLOCKS).tolist(), "raddr": raddr.tolist()}


CMDS = _commands()


def expected(cmds: dict[str, list[int]], outreg: int) -> list[int | None]:
    """``rdata`` seen in each clock: the word at raddr of clock c - 1 - outreg, read before
    that clock's write (None: not yet defined)."""
    mem: list[int | None] = [None] * DEPTH
    reads: list[int | None] = []
    for we, wa, wd, ra in zip(cmds["we"], cmds["waddr"], cmds["wdata"], cmds["raddr"],
                              strict=True):
        reads.append(mem[ra])           # read first: the old word
        if we:
            mem[wa] = wd
    lag = 1 + outreg                    # recorded at the falling edge after the taking edge
    return [None] * lag + reads[:CLOCKS - lag]


def _run(build_dir, name: str) -> list[int | None]:
    return cosim.run_job("sdp_ram", "cdma_lidar.hdl_ref.tb.test_sdp_ram", build_dir,
                         {"cases": [CMDS]}, name=name)["cases"][0]["rdata"]


def _agrees(got: list[int | None], want: list[int | None]) -> bool:
    return all(w is None or g == w for g, w in zip(got, want, strict=True))


def test_commands_read_the_word_being_written():
    rdw = [we and wa == ra for we, wa, ra in zip(CMDS["we"], CMDS["waddr"], CMDS["raddr"],
                                                   strict=True)]
    assert sum(rdw) >= 50


@pytest.mark.hdl
@pytest.mark.parametrize("outreg", [0, 1])
def test_sdp_ram_equals_model(hdl_build_root, outreg):
    build = cosim.build("sdp_ram", {"WIDTH": WIDTH, "DEPTH": DEPTH, "OUTREG": outreg},
                        hdl_build_root / f"sdp_ram_o{outreg}")
    got = _run(build, f"ram{outreg}")
    want = expected(CMDS, outreg)
    assert sum(w is not None for w in want) > CLOCKS // 2
    assert _agrees(got, want)


@pytest.mark.hdl
def test_sdp_ram_mutant_is_caught(hdl_build_root):
    (mutant,) = [m for m in MUTANTS if m.file == "sdp_ram.v"]
    rtl = mutated_copy(mutant, hdl_build_root / f"rtl_{mutant.name}")
    build = cosim.build("sdp_ram", {"WIDTH": WIDTH, "DEPTH": DEPTH, "OUTREG": 1},
                        hdl_build_root / f"sdp_ram_{mutant.name}", rtl_dir=rtl)
    assert not _agrees(_run(build, "ram_mutant"), expected(CMDS, 1))
