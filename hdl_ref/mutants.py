"""Deliberate RTL faults that the co-simulation must catch (mutation tests).

Each :class:`Mutant` replaces one exact piece of text in one RTL file by a
plausible mistake; :func:`mutated_copy` writes a copy of ``hdl_ref/rtl`` with
that change into a folder, for :func:`cdma_lidar.hdl_ref.cosim.build` to compile.
The tests of the module a mutant changes build it and assert that the
co-simulation against the model reports a difference: ``tests/hdl_ref/test_rx_top.py``
(``rx_top.v``, ``lane_feed.v``, ``rx_post.v``, ``lfsr_fib.v``, ``sdp_ram.v``),
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
    #: why no test can kill it (the fault changes no output), empty for a real fault
    equivalent: str = ""


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
    Mutant("chain-uid-fold-polarity-inverted", "rx_chain.v",
           "p_flip  = |(c_uid & p_sel);",
           "p_flip  = |(~c_uid & p_sel);",
           "rx_chain folds every period with the wrong UID polarity"),
    Mutant("chain-frames-off-by-one", "rx_chain.v",
           "if (a_frame == c_averages - 1'b1)",
           "if (a_frame == c_averages)",
           "rx_chain averages one frame more than R: it waits for samples that never come"),
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
           "        if (latch_v && ser_busy)\n            err_overrun <= 1'b1;",
           "        if (1'b0)\n            err_overrun <= 1'b1;",
           "the serializer overrun is never flagged"),
    Mutant("resume-one-clock-late", "rx_top.v",
           "&& !full_nx[acc_buf_nx]",
           "&& !full_nx[acc_buf_nx] && !p_free",
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
           "assign e_code = {sr_code, code2[gk]};",
           "assign e_code = {sr_code, sr_code[0]};",
           "lane 0 uses the previous chip of the Gold code"),
    Mutant("lane-feed-reads-other-buffer", "lane_feed.v",
           "q   <= pb ? rd[MAX_S*AVG_W +: MAX_S*AVG_W] : rd[0 +: MAX_S*AVG_W];",
           "q   <= pb ? rd[0 +: MAX_S*AVG_W] : rd[MAX_S*AVG_W +: MAX_S*AVG_W];",
           "a channel's lanes sum the RAM words of the buffer being averaged"),
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
    # ---- the survivors, and the kinds of docs/hdl.md "Mutation tests" ----
    Mutant("avg-chip-counter-off-by-one", "rx_top.v",
           "a_c_last <= (a_c_nx == nn - 1'b1);",
           "a_c_last <= (a_c_nx == nn);",
           "the averaging chip counter runs to N: a column never completes (a hang)"),
    Mutant("refusal-lost-in-clear-clock", "rx_top.v",
           "        if (s_refused)\n            err_refused <= 1'b1;",
           "        if (s_refused && !clear_err)\n            err_refused <= 1'b1;",
           "a refusal in the clock of clear_err is lost"),
    Mutant("stop-between-columns-takes-one-more", "rx_top.v",
           "cols_in + {{(COL_W-1){1'b0}}, a_mid}",
           "cols_in + 1'b1",
           "a stop between two columns still takes one more column"),
    Mutant("proc-on-not-reset", "rx_top.v",
           "            ln_clr      <= 1'b0;\n            proc_on     <= 1'b0;\n",
           "            ln_clr      <= 1'b0;\n",
           "proc_on left out of reset: the first column's reads may use the engine's address"),
    Mutant("full-not-reset", "rx_top.v",
           "full_nx   = (rst || t_init) ? 2'b00",
           "full_nx   = t_init ? 2'b00",
           "full left out of reset",
           equivalent="T_INIT2 clears full before anything reads it (s_ready and the "
                      "engine wait for T_RUN)"),
    Mutant("err-refused-not-reset", "rx_top.v",
           "        if (rst) begin\n            err_overrun <= 1'b0;\n"
           "            err_refused <= 1'b0;\n",
           "        if (rst) begin\n            err_overrun <= 1'b0;\n",
           "err_refused left out of reset: a register that may start set"),
    Mutant("round-half-up-strict", "out_scale.v",
           "((rounding == 2'd1) && (r_gt || r_eq))",
           "((rounding == 2'd1) && r_gt)",
           "half_up rounds an exact half down"),
    Mutant("convergent-ties-to-odd", "out_scale.v",
           "(r_eq && s1_q[0])",
           "(r_eq && !s1_q[0])",
           "convergent rounding sends ties to odd"),
    Mutant("shift-logical", "out_scale.v",
           "        s1_q    <= rx >>> k_sh;",
           "        s1_q    <= rx >> k_sh;",
           "the output shift is logical: negative words lose their sign"),
    Mutant("saturated-flag-rail-off-by-one", "rx_post.v",
           "(out_bits - 1'b1)) - 1'b1;",
           "(out_bits - 1'b1)) - 2'd2;",
           "the saturation flag compares with a rail one below the real one"),
    Mutant("swapped-taps", "rx_top.v",
           ".taps(c_taps_v), .degree(c_degree), .out(cv)",
           ".taps(c_taps_u), .degree(c_degree), .out(cv)",
           "the second LFSR of each channel runs the first one's polynomial"),
    Mutant("gate-one-lag-long", "rx_post.v",
           "q_j_last = gate_len - 1'b1;",
           "q_j_last = gate_len;",
           "the post-processing scans one lag past the gate"),
    Mutant("correlated-lags-one-long", "rx_top.v",
           "jj_last = {1'b0, c_gate_len} + 1'b1;",
           "jj_last = {1'b0, c_gate_len} + 2'd2;",
           "the correlation covers one lag more than the gate and its neighbours"),
    Mutant("uid-fold-polarity-inverted", "rx_top.v",
           "x2_flip = |(c_uid & x2_sel);",
           "x2_flip = |(~c_uid & x2_sel);",
           "the despread total folds every period with the wrong UID polarity"),
    Mutant("uid-match-polarity-inverted", "rx_post.v",
           "&& (b_neg == (uid & uid_mask));",
           "&& (b_neg == (~uid & uid_mask));",
           "the UID match compares the signs with the inverted UID"),
    Mutant("noise-count-includes-masked", "rx_post.v",
           "                if (s3_ok) begin\n                    res_noise_count",
           "                if (1'b1) begin\n                    res_noise_count",
           "the noise floor also counts peak and ghost lags"),
    Mutant("noise-sum-zero-extended", "rx_post.v",
           "res_noise_sum + {{(SUM_W-OUT_W){s3_out[OUT_W-1]}}, s3_out};",
           "res_noise_sum + {{(SUM_W-OUT_W){1'b0}}, s3_out};",
           "the noise sum zero-extends negative words"),
    Mutant("noise-square-cross-term-once", "rx_post.v",
           "{HB{1'b0}}} << 1);",
           "{HB{1'b0}}} << 0);",
           "the pipelined square adds its cross term 2 h l once, not twice"),
    Mutant("neighbour-hi-is-the-peak", "rx_post.v",
           "{CA_W{1'b0}} : CA_TWO);",
           "{CA_W{1'b0}} : CA_TWO - 1'b1);",
           "the right neighbour is read at the peak's own gate index"),
    Mutant("exclusion-strict", "rx_post.v",
           "dj <= excl",
           "dj < excl",
           "peak_exclude W hides |j - j_q| < W instead of <= W"),
    Mutant("period-sum-not-doubled", "rx_top.v",
           "x2_c2 = {x1_d[PER_W-2:0], 1'b0} - x1_all;",
           "x2_c2 = x1_d - x1_all;",
           "c_p = plus - all instead of 2 plus - all (a shift lost)"),
    Mutant("samples-lose-sign", "rx_top.v",
           "{{(AVG_W-ADC_W+1){wx[ADC_W-1]}}, wx[ADC_W-2:0]}",
           "{{(AVG_W-ADC_W+1){1'b0}}, wx[ADC_W-2:0]}",
           "ADC samples are zero-extended: negative samples lose their sign"),
    Mutant("bank-step-ignores-p-in", "rx_top.v",
           "a_s_last <= (a_s_nx == c_spc - P_STEP);",
           "a_s_last <= (a_s_nx == c_spc - 1'b1);",
           "the last bank of a chip is found as for one sample per clock (P-lane merging)"),
    Mutant("box-phase-off-by-one", "rx_top.v",
           "(bi >= ph_s) ? st_t : st_t1};",
           "(bi > ph_s) ? st_t : st_t1};",
           "a box sum takes bank ph_s from the next chip"),
    Mutant("overrun-flagged-every-stream", "rx_top.v",
           "        if (latch_v && ser_busy)\n            err_overrun <= 1'b1;",
           "        if (latch_v)\n            err_overrun <= 1'b1;",
           "err_overrun is set at every stream's end"),
    Mutant("free-running-never-starts", "rx_top.v",
           "t_load ? (cfg_columns == {COL_W{1'b0}}) : c_free;",
           "t_load ? 1'b0 : c_free;",
           "cfg_columns = 0 is a count of 0, not free running"),
    Mutant("samples-taken-during-init", "rx_top.v",
           "s_ready   <= (tstate_nx == T_RUN)",
           "s_ready   <= (tstate_nx != T_IDLE)",
           "s_ready is high in the two set-up clocks after start"),
    # ---- the registered ADC handshake: s_ready and the averaging counters' last flags ----
    Mutant("ready-from-current-full", "rx_top.v",
           "&& !full_nx[acc_buf_nx]",
           "&& !full[acc_buf_nx]",
           "the registered s_ready reads this clock's full, not the next one's"),
    Mutant("period-last-flag-from-current-count", "rx_top.v",
           "a_p_last <= (a_p_nx == c_uid_bits - 1'b1);",
           "a_p_last <= (a_p == c_uid_bits - 1'b1);",
           "the UID period counter's last flag is computed from its value before the step"),
    Mutant("stream-one-step-long", "rx_top.v",
           "- {{(KST_W-2){1'b0}}, 2'd2};",
           "- {{(KST_W-2){1'b0}}, 2'd1};",
           "every correlation stream runs one step longer"),
    Mutant("lfsr-output-stage-off-by-one", "lfsr_fib.v",
           "<< (degree - 1'b1);",
           "<< (degree - 2'd2);",
           "the generator's output is stage degree - 1"),
    # ---- the ADC side: deserialiser, asynchronous FIFO, real-time check ----
    Mutant("fifo-write-pointer-binary", "adc_rx.v",
           "wire [AW:0]   wgray_nx = (wbin_nx >> 1) ^ wbin_nx;",
           "wire [AW:0]   wgray_nx = wbin_nx;",
           "the write pointer crosses in binary, not Gray code"),
    Mutant("fifo-full-never", "adc_rx.v",
           "full  <= (wgray_nx == {~wq2_rgray[AW:AW-1], wq2_rgray[AW-2:0]});",
           "full  <= 1'b0;",
           "full never rises: a full FIFO is overwritten, no flag"),
    Mutant("fifo-full-when-empty", "adc_rx.v",
           "{~wq2_rgray[AW:AW-1], wq2_rgray[AW-2:0]}",
           "{wq2_rgray[AW:AW-1], wq2_rgray[AW-2:0]}",
           "full compares the pointers as empty does (top bits not inverted)"),
    Mutant("overflow-not-sticky", "adc_rx.v",
           "ovf   <= (ovf && !clr_adc) || (word && full);",
           "ovf   <= word && full;",
           "the overflow flag is a one-clock pulse in adc_clk (lost by the synchroniser)"),
    Mutant("words-packed-in-reverse", "adc_rx.v",
           "assign wdata = {adc_data, pack};",
           "assign wdata = {pack[ADC_W-1:0], pack[WW-ADC_W-1:ADC_W], adc_data};",
           "the samples of a word are rotated: the last one lands in lane 0"),
    Mutant("empty-from-current-pointer", "adc_rx.v",
           "empty   <= (rgray_nx == rq2_wgray);",
           "empty   <= (rgray == rq2_wgray);",
           "empty is computed from the read pointer before this clock's pop"),
    Mutant("r-min-one-short", "r_min_rom.v",
           "r = ((clocks + 1) * P_IN + n * s - 1) / (n * s);",
           "r = (clocks * P_IN + n * s - 1) / (n * s);",
           "R_MIN misses the clock of the column's last take"),
    Mutant("r-min-ignores-p-in", "r_min_rom.v",
           "|| (s % P_IN) != 0",
           "",
           "S not a multiple of P_IN is not refused"),
    Mutant("config-never-refused", "rx_adc_top.v",
           "wire cfg_ok    = ({1'b0, cfg_averages} >= r_min)",
           "wire cfg_ok    = 1'b1",
           "R below R_MIN starts rx_top"),
    Mutant("gold-period-never-wraps", "gold_gen.v",
           "(period == uid_bits - 1'b1) ? {UID_W{1'b0}} : period + 1'b1;",
           "period + 1'b1;",
           "the UID period counter does not wrap at uid_bits"),
    # ---- the DDR pins (adc_pins through rx_adc_top's PINS = 1) ----
    Mutant("pins-capture-while-idle", "rx_adc_top.v",
           ".run(busy)",
           ".run(1'b1)",
           "the pins write words from reset on, not from the acquisition's start"),
    Mutant("pins-loss-never-seen", "adc_rx.v",
           "assign adc_full     = full;",
           "assign adc_full     = 1'b0;",
           "the pin path never learns that a word was not written: no gap bit, no flag"),
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
