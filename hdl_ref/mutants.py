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
    Mutant("chip-index-drops-carry", "rx_top.v",
           "g_q_sum  = {1'b0, g_q} + L[MAX_DEG:0];",
           "g_q_sum  = {1'b0, g_q + L[MAX_DEG-1:0]};",
           "the next group's chip shift loses its carry (gate_start 0 at the largest degree)"),
    Mutant("lanes-hardcoded-2", "rx_top.v",
           "g_q_sum  = {1'b0, g_q} + L[MAX_DEG:0];",
           "g_q_sum  = {1'b0, g_q} + 2;",
           "the group step written for L = 2"),
    Mutant("ghost-window-no-wrap", "rx_post.v",
           "            if (gd[LAG_W])\n                gd = gd + {1'b0, ns};",
           "            if (1'b0)\n                gd = gd + {1'b0, ns};",
           "a ghost window does not wrap through lag 0"),
    Mutant("overrun-never-flagged", "rx_top.v",
           "            if (ser_busy)\n                err_overrun <= 1'b1;",
           "            if (1'b0)\n                err_overrun <= 1'b1;",
           "the serializer overrun is never flagged"),
    Mutant("resume-one-clock-late", "rx_top.v",
           "assign s_ready   = (tstate == T_RUN) && !full[acc_buf]",
           "assign s_ready   = (tstate == T_RUN) && !full[acc_buf] && !(res_valid && !proc_on)",
           "sampling resumes one clock after the buffer is freed"),
    Mutant("noise-square-two-bits-short", "rx_post.v",
           "sq4[2*OUT_W-1:0]};",
           "2'b00, sq4[2*OUT_W-3:0]};",
           "the noise square loses its top bits (only rail-sized words have them)"),
    Mutant("samples-of-a-clock-reversed", "rx_top.v",
           "localparam integer  SX = gs % P_IN;",
           "localparam integer  SX = P_IN - 1 - gs % P_IN;",
           "the P_IN samples of a clock go to the banks in reverse order"),
    Mutant("stop-drops-open-column", "rx_top.v",
           "cols_in + {{(COL_W-1){1'b0}}, a_mid}",
           "cols_in",
           "stop abandons the column being taken (it never completes)"),
    Mutant("refused-only-while-running", "rx_top.v",
           "assign s_refused = busy && s_valid && !s_ready;",
           "assign s_refused = (tstate == T_RUN) && s_valid && !s_ready;",
           "offers in the two set-up clocks after start are not flagged"),
    Mutant("clear-leaves-refused", "rx_top.v",
           "            err_overrun <= 1'b0;\n            err_refused <= 1'b0;\n        end\n"
           "        if (s_refused)",
           "            err_overrun <= 1'b0;\n        end\n        if (s_refused)",
           "clear_err does not clear err_refused"),
    Mutant("lane-code-delay-off-by-one", "rx_top.v",
           "assign e_code[gk*L +: L] = {sr_code[gk*L +: L-1], code2[gk]};",
           "assign e_code[gk*L +: L] = {sr_code[gk*L +: L-1], sr_code[gk*L]};",
           "lane 0 uses the previous chip of the Gold code"),
    Mutant("lane-state-stale-after-start", "rx_top.v",
           "x0_fst <= ser_fst;",
           "x0_fst <= 1'b0;",
           "the first stream after start subtracts the state RAM's old word, not 0"),
    Mutant("uid-fold-restarts-every-period", "rx_top.v",
           "x2_p0 = (x2_p == {UID_W{1'b0}});",
           "x2_p0 = 1'b1;",
           "the despread total keeps only the last UID period"),
    Mutant("all-sum-misses-first-box", "rx_top.v",
           "all_sum <= (f2 ? {PER_W{1'b0}} : all_sum) + bx;",
           "all_sum <= f2 ? {PER_W{1'b0}} : all_sum + bx;",
           "the sum of every box of a stream leaves out its first box"),
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
