"""Deliberate RTL faults that the co-simulation must catch (mutation tests).

Each :class:`Mutant` replaces one exact piece of text in one RTL file by a
plausible mistake; :func:`mutated_copy` writes a copy of ``hdl_ref/rtl`` with
that change into a folder, for :func:`cdma_lidar.hdl_ref.cosim.build` to compile.
The tests of the module a mutant changes build it and assert that the
co-simulation against the model reports a difference: ``tests/hdl_ref/test_rx_top.py``
(``rx_top.v``, ``rx_post.v``, ``lfsr_fib.v``, ``sdp_ram.v``),
``tests/hdl_ref/test_rx_chain.py`` (``rx_chain.v``) and ``tests/hdl_ref/test_out_scale.py``
(``out_scale.v``); ``tests/hdl_ref/test_rx_top.py::test_every_mutant_is_simulated``
checks that each mutant belongs to one of them.
"""

from __future__ import annotations

import shutil
from dataclasses import dataclass
from pathlib import Path

from cdma_lidar.errors import ConfigError
from cdma_lidar.hdl_ref.cosim import RTL_DIR

__all__ = ["MUTANTS", "Mutant", "mutated_copy"]


@dataclass(frozen=True)
class Mutant:
    """One fault: in ``file``, the text ``original`` (exactly once) becomes ``mutated``."""

    name: str
    file: str
    original: str
    mutated: str
    why: str


MUTANTS: tuple[Mutant, ...] = (
    Mutant("uid-match-ignores-zero-sign", "rx_post.v",
           "res_uid_match    <= b_have && (b_nz == uid_mask)\n"
           "                                            && (b_neg == (uid & uid_mask));",
           "res_uid_match    <= b_have && (b_neg == (uid & uid_mask));",
           "a period whose correlation is 0 at the peak still matches"),
    Mutant("half-lsb-16-bit", "out_scale.v",
           "                  : ({{(EXT_W-1){1'b0}}, 1'b1} << (sh_c - 1'b1));",
           "                  : {{(EXT_W-16){1'b0}}, 16'd1 << (sh_c - 1'b1)};",
           "the half-LSB rounding constant is 16 bits wide: 0 for out_shift >= 17"),
    Mutant("half-lsb-16-bit-chain", "rx_chain.v",
           "                                      : ({{(EXT_W-1){1'b0}}, 1'b1} << (sh_c - 1'b1));",
           "                                      : {{(EXT_W-16){1'b0}}, 16'd1 << (sh_c - 1'b1)};",
           "the same fault in rx_chain's rounding"),
    Mutant("symmetric-saturation", "out_scale.v",
           "smin   <= ~(({{(EXT_W-1){1'b0}}, 1'b1}",
           "smin   <= -(({{(EXT_W-1){1'b0}}, 1'b1}",
           "the negative rail is -(2^(b-1) - 1) instead of -2^(b-1)"),
    Mutant("ties-to-last", "rx_post.v",
           "if (s3_ok && (!b_have || s3_mag > b_mag)) begin",
           "if (s3_ok && (!b_have || s3_mag >= b_mag)) begin",
           "equal |out| keeps the highest gate index instead of the lowest"),
    Mutant("ghost-window-one-long", "rx_post.v",
           "if (gd[LAG_W-1:0] < gh_len[w*LAG_W +: LAG_W])",
           "if (gd[LAG_W-1:0] <= gh_len[w*LAG_W +: LAG_W])",
           "a ghost window also hides the lag after its end"),
    Mutant("box-sum-no-chip-wrap", "rx_top.v",
           "(bi >= ph_s) ? st_t : st_t1};",
           "(bi >= ph_s) ? st_t : st_t + 1'b1};",
           "the S-sample box sum of the last chip does not wrap to chip 0"),
    Mutant("en-beats-load", "lfsr_fib.v",
           "        if (load)\n            st <= seed;\n        else if (en)\n"
           "            st <= {st[MAX_DEG-2:0], fb};",
           "        if (en)\n            st <= {st[MAX_DEG-2:0], fb};\n        else if (load)\n"
           "            st <= seed;",
           "an enable in the clock of a load steps instead of loading"),
    Mutant("rdw-returns-new", "sdp_ram.v",
           "        rd0 <= mem[raddr];",
           "        rd0 <= (we && waddr == raddr) ? wdata : mem[raddr];",
           "a read of the word being written returns the new word (write-first)"),
    Mutant("lane-code-delay-off-by-one", "rx_top.v",
           "assign e_code[gk*L +: L] = {sr_code[gk*L +: L-1], code2[gk]};",
           "assign e_code[gk*L +: L] = {sr_code[gk*L +: L-1], sr_code[gk*L]};",
           "lane 0 uses the previous chip of the Gold code"),
)


def mutated_copy(mutant: Mutant, folder: str | Path) -> Path:
    """Copy ``hdl_ref/rtl`` into ``folder`` with ``mutant`` applied; return the folder.

    Raises ``ConfigError`` when the original text is not found exactly once (the
    RTL changed and the mutant must be updated, so it cannot silently test nothing).
    """
    folder = Path(folder)
    if folder.exists():
        shutil.rmtree(folder)
    shutil.copytree(RTL_DIR, folder)
    path = folder / mutant.file
    text = path.read_text()
    if text.count(mutant.original) != 1:
        raise ConfigError(f"mutant {mutant.name}: its original text occurs "
                          f"{text.count(mutant.original)} times in {mutant.file}, not once",
                          field="mutant")
    path.write_text(text.replace(mutant.original, mutant.mutated))
    return folder
