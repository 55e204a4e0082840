// rx_adc_top -- the receive chain from the ADC pins: adc_rx (deserialiser and
// asynchronous FIFO from adc_clk into clk) in front of an unchanged rx_top, and the
// real-time check of the configuration (docs/hdl.md, "From the ADC pins").
//
//   PINS = 0: adc_clk: adc_valid, adc_data (1 sample/clock) --> adc_rx --+
//   PINS = 1: adc_clk = the converter's DDR data clock, adc_data its      |
//             DDR pins --> adc_pins (IDDRX2F gearing, P_IN = 4, adc_rx's  |
//             FIFO; adc_valid unused)                                     |
//                        s_valid/s_data/s_ready (P_IN samples per clk) <--+--> rx_top
//   With PINS = 1 words are captured while rx_top is busy and the FIFO is drained while
//   it is idle (the converter never stops; adc_pins.v: the overflow flag, and how long
//   after busy falls a start must wait).
//   start --> [R >= r_min(degree, S)? pins: FIFO drained?] --yes--> rx_top.start
//                                                         --no---> err_config (sticky),
//                                                                  rx_top stays idle
//
// A fixed-rate ADC cannot wait, so rx_top must never hold s_ready low for long: the
// configuration is refused at `start` (rx_top is not started, err_config set) when
// cfg_averages is below r_min_rom's bound for its degree and samples_per_chip (or
// the build cannot run that degree and S at all), or above MAX_R; with the pins also when
// it comes sooner than 2^FIFO_AW + 8 clocks after busy fell. Everything else is
// rx_top's, ports and timing included; its s_refused/err_refused are internal here
// (the FIFO holds the samples offered in rx_top's two set-up clocks): a lost sample
// is err_overflow. clear_err clears err_config, err_overflow and rx_top's flags.
`default_nettype none

module rx_adc_top #(
    parameter integer K         = 4,
    parameter integer L         = 2,
    parameter integer P_IN      = 1,
    parameter integer MAX_DEG   = 11,
    parameter integer MAX_S     = 4,
    parameter integer MAX_UID   = 1,
    parameter integer MAX_R     = 16,
    parameter integer MAX_G     = 64,
    parameter integer MAX_P     = 1,
    parameter integer NGHOST    = 1,
    parameter integer ADC_W     = 12,
    parameter integer OUT_W     = 32,
    parameter integer FIFO_AW   = 4,    // adc_rx FIFO: 2^FIFO_AW words of P_IN samples
    parameter integer PINS      = 0,    // 1: DDR pins through adc_pins (P_IN must be 4)
    // ---- derived, do not override ----
    parameter integer DEG_W     = $clog2(MAX_DEG + 1),
    parameter integer MAX_NS    = ((1 << MAX_DEG) - 1) * MAX_S,
    parameter integer LAG_W     = $clog2(MAX_NS + 1),
    parameter integer S_W       = $clog2(MAX_S + 1),
    parameter integer UID_W     = $clog2(MAX_UID + 1),
    parameter integer R_W       = $clog2(MAX_R + 1),
    parameter integer G_W       = $clog2(MAX_G + 1),
    parameter integer P_W       = $clog2(MAX_P + 1),
    parameter integer K_W       = (K > 1) ? $clog2(K) : 1,
    parameter integer COL_W     = 16
) (
    input  wire                         adc_clk,
    input  wire                         adc_valid,  // PINS = 0 only
    input  wire [ADC_W-1:0]             adc_data,   // PINS = 1: one bit a pin, DDR

    input  wire                         clk,
    input  wire                         rst,        // both domains (synchronised to adc_clk)
    input  wire                         start,
    input  wire                         stop,
    input  wire                         clear_err,
    input  wire [COL_W-1:0]             cfg_columns,
    input  wire [DEG_W-1:0]             cfg_degree,
    input  wire [MAX_DEG-1:0]           cfg_taps_u,
    input  wire [MAX_DEG-1:0]           cfg_taps_v,
    input  wire [K*MAX_DEG-1:0]         cfg_seed_u,
    input  wire [K*MAX_DEG-1:0]         cfg_seed_v,
    input  wire [S_W-1:0]               cfg_spc,
    input  wire [R_W-1:0]               cfg_averages,
    input  wire [UID_W-1:0]             cfg_uid_bits,
    input  wire [MAX_UID-1:0]           cfg_uid,
    input  wire [LAG_W-1:0]             cfg_gate_start,
    input  wire [G_W-1:0]               cfg_gate_len,
    input  wire [G_W-1:0]               cfg_peak_exclude,
    input  wire [NGHOST*LAG_W-1:0]      cfg_ghost_start,
    input  wire [NGHOST*LAG_W-1:0]      cfg_ghost_len,
    input  wire [5:0]                   cfg_out_shift,
    input  wire [1:0]                   cfg_rounding,
    input  wire [5:0]                   cfg_out_bits,
    input  wire [P_W-1:0]               cfg_peaks,

    output wire                         corr_valid,
    output wire [K_W-1:0]               corr_channel,
    output wire [G_W-1:0]               corr_index,
    output wire signed [OUT_W-1:0]      corr_data,
    output wire                         res_valid,
    output wire [K_W-1:0]               res_channel,
    output wire [MAX_P-1:0]             res_found,
    output wire [MAX_P*LAG_W-1:0]       res_lag,
    output wire [MAX_P*G_W-1:0]         res_index,
    output wire [MAX_P*OUT_W-1:0]       res_peak,
    output wire [MAX_P*MAX_UID-1:0]     res_neg,
    output wire [MAX_P*MAX_UID-1:0]     res_nz,
    output wire signed [OUT_W-1:0]      res_nb_lo,
    output wire signed [OUT_W-1:0]      res_nb_hi,
    output wire [G_W-1:0]               res_noise_count,
    output wire signed [OUT_W+G_W-1:0]  res_noise_sum,
    output wire [2*OUT_W+G_W-1:0]       res_noise_sumsq,
    output wire [MAX_UID-1:0]           res_uid_observed,
    output wire                         res_uid_match,
    output wire                         res_saturated,
    output wire                         busy,
    output wire                         done,
    output wire                         col_start,
    output wire                         err_overrun,
    output wire                         err_overflow,   // sticky: the FIFO lost a word
    output reg                          err_config      // sticky: a start was refused
);
    generate   // a derived parameter overridden by mistake stops the elaboration
        if (DEG_W != $clog2(MAX_DEG + 1) || MAX_NS != ((1 << MAX_DEG) - 1) * MAX_S
            || LAG_W != $clog2(MAX_NS + 1) || S_W != $clog2(MAX_S + 1)
            || UID_W != $clog2(MAX_UID + 1) || R_W != $clog2(MAX_R + 1)
            || G_W != $clog2(MAX_G + 1) || P_W != $clog2(MAX_P + 1)
            || K_W != ((K > 1) ? $clog2(K) : 1))
        begin : g_derived_width_mismatch
            rx_adc_top_derived_width_mismatch bad ();
        end
    endgenerate

    wire                  s_valid, s_ready;
    wire [P_IN*ADC_W-1:0] s_data;
    generate
        if (PINS != 0) begin : g_pins
            if (P_IN != 4) begin : g_p_in_not_4
                rx_adc_top_pins_need_p_in_4 bad ();
            end
            /* verilator lint_off UNUSEDSIGNAL */
            wire unused = adc_valid;        // the pins carry no valid: run is rx_top's busy
            /* verilator lint_on UNUSEDSIGNAL */
            adc_pins #(.ADC_W(ADC_W), .AW(FIFO_AW)) pins (
                .dco(adc_clk), .d(adc_data), .clk(clk), .rst(rst), .run(busy),
                .m_valid(s_valid), .m_data(s_data), .m_ready(s_ready),
                .clear_ovf(clear_err), .err_overflow(err_overflow)
            );
        end else begin : g_one
            // ---- the ADC domain's reset: rst through two adc_clk flip-flops ----
            reg [1:0] adc_rst_s;
            /* verilator lint_off UNUSEDSIGNAL */
            wire      adc_full;             // the sticky err_overflow says it all here
            /* verilator lint_on UNUSEDSIGNAL */
            always @(posedge adc_clk)
                adc_rst_s <= {adc_rst_s[0], rst};
            adc_rx #(.ADC_W(ADC_W), .P_IN(P_IN), .AW(FIFO_AW)) rx (
                .adc_clk(adc_clk), .adc_rst(adc_rst_s[1]), .adc_valid(adc_valid),
                .adc_data(adc_data), .clk(clk), .rst(rst), .m_valid(s_valid),
                .m_data(s_data), .m_ready(s_ready), .clear_ovf(clear_err),
                .err_overflow(err_overflow), .adc_full(adc_full)
            );
        end
    endgenerate

    // ---- real-time check at start ----
    wire [R_W:0] r_min;
    r_min_rom #(.K(K), .L(L), .P_IN(P_IN), .MAX_DEG(MAX_DEG), .MAX_S(MAX_S), .MAX_R(MAX_R),
                .MAX_G(MAX_G), .MAX_P(MAX_P), .DEG_W(DEG_W), .S_W(S_W), .R_W(R_W)) rmin (
        .degree(cfg_degree), .spc(cfg_spc), .r_min(r_min)
    );
    localparam [31:0] MAX_R32 = MAX_R;
    // With the pins a start also waits until the last capture's words have left the FIFO
    // (drained while idle, one a clock: 2^FIFO_AW words and the crossing's few clocks);
    // an earlier start would take a stale word as sample 0, so it is refused instead.
    localparam integer DRAIN = (PINS != 0) ? (1 << FIFO_AW) + 8 : 0;
    localparam integer DR_W  = $clog2(DRAIN + 2);
    localparam [DR_W-1:0] DRAINED = DRAIN[DR_W-1:0];
    reg [DR_W-1:0] idle_clocks;                 // clocks since busy fell, up to DRAIN
    always @(posedge clk)
        idle_clocks <= rst ? DRAINED : busy ? {DR_W{1'b0}}
                     : idle_clocks + {{(DR_W-1){1'b0}}, idle_clocks != DRAINED};
    wire cfg_ok    = ({1'b0, cfg_averages} >= r_min) && (cfg_averages <= MAX_R32[R_W-1:0])
                     && idle_clocks == DRAINED;
    wire start_req = start && !busy;
    always @(posedge clk) begin
        if (rst)
            err_config <= 1'b0;
        else if (start_req && !cfg_ok)
            err_config <= 1'b1;
        else if (clear_err)
            err_config <= 1'b0;
    end

    /* verilator lint_off UNUSEDSIGNAL */
    wire s_refused, err_refused;   // the FIFO absorbs refusals: a loss is err_overflow
    /* verilator lint_on UNUSEDSIGNAL */
    rx_top #(.K(K), .L(L), .P_IN(P_IN), .MAX_DEG(MAX_DEG), .MAX_S(MAX_S), .MAX_UID(MAX_UID),
             .MAX_R(MAX_R), .MAX_G(MAX_G), .MAX_P(MAX_P), .NGHOST(NGHOST), .ADC_W(ADC_W),
             .OUT_W(OUT_W)) top (
        .clk(clk), .rst(rst), .start(start_req && cfg_ok), .stop(stop), .clear_err(clear_err),
        .cfg_columns(cfg_columns), .cfg_degree(cfg_degree), .cfg_taps_u(cfg_taps_u),
        .cfg_taps_v(cfg_taps_v), .cfg_seed_u(cfg_seed_u), .cfg_seed_v(cfg_seed_v),
        .cfg_spc(cfg_spc), .cfg_averages(cfg_averages), .cfg_uid_bits(cfg_uid_bits),
        .cfg_uid(cfg_uid), .cfg_gate_start(cfg_gate_start), .cfg_gate_len(cfg_gate_len),
        .cfg_peak_exclude(cfg_peak_exclude), .cfg_ghost_start(cfg_ghost_start),
        .cfg_ghost_len(cfg_ghost_len), .cfg_out_shift(cfg_out_shift),
        .cfg_rounding(cfg_rounding), .cfg_out_bits(cfg_out_bits), .cfg_peaks(cfg_peaks),
        .s_valid(s_valid), .s_data(s_data), .s_ready(s_ready), .s_refused(s_refused),
        .err_refused(err_refused),
        .corr_valid(corr_valid), .corr_channel(corr_channel), .corr_index(corr_index),
        .corr_data(corr_data),
        .res_valid(res_valid), .res_channel(res_channel), .res_found(res_found),
        .res_lag(res_lag), .res_index(res_index), .res_peak(res_peak), .res_neg(res_neg),
        .res_nz(res_nz), .res_nb_lo(res_nb_lo), .res_nb_hi(res_nb_hi),
        .res_noise_count(res_noise_count), .res_noise_sum(res_noise_sum),
        .res_noise_sumsq(res_noise_sumsq), .res_uid_observed(res_uid_observed),
        .res_uid_match(res_uid_match), .res_saturated(res_saturated),
        .busy(busy), .done(done), .col_start(col_start), .err_overrun(err_overrun)
    );
endmodule

`default_nettype wire
