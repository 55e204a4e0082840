// rx_top_pnr -- place-and-route harness for rx_top (synthesis only, not simulated).
//
// rx_top's configuration ports are several hundred bits wide, more than any
// package has pins. This harness loads them from a shift register (cfg_sin,
// cfg_shift: one bit per clock) and folds every result and correlation word
// into one 32-bit register by XOR, so no logic of rx_top can be optimised away
// and the design fits in a package. The ADC stream and the handshakes are real
// pins, each through a register beside its pad (as an ADC's input registers, or
// rx_adc_top's FIFO, would feed it), and so are start, stop and clear_err (as a control
// block in front of rx_top would drive them), so where the placer puts a pad does not
// lengthen a path inside rx_top. Resource and clock figures in docs/hdl.md are of this harness; the
// shift register and the XOR fold add about (config bits) flip-flops and a few
// hundred LUTs to rx_top itself.
`default_nettype none

module rx_top_pnr #(
    parameter integer K       = 4,
    parameter integer L       = 2,
    parameter integer P_IN    = 1,
    parameter integer MAX_DEG = 11,
    parameter integer MAX_S   = 4,
    parameter integer MAX_UID = 1,
    parameter integer MAX_R   = 16,
    parameter integer MAX_G   = 64,
    parameter integer MAX_P   = 1,
    parameter integer NGHOST  = 1,
    parameter integer ADC_W   = 12,
    parameter integer OUT_W   = 32
) (
    input  wire              clk,
    input  wire              rst,
    input  wire              start,
    input  wire              stop,
    input  wire              clear_err,
    input  wire              cfg_sin,
    input  wire              cfg_shift,
    input  wire              s_valid,
    input  wire [P_IN*ADC_W-1:0] s_data,
    output reg               s_ready,
    output reg               s_refused,
    output wire              err_refused,
    output reg               res_valid,
    output reg  [31:0]       fold,
    output wire              busy,
    output wire              done,
    output wire              err_overrun
);
    localparam integer DEG_W  = $clog2(MAX_DEG + 1);
    localparam integer MAX_NS = ((1 << MAX_DEG) - 1) * MAX_S;
    localparam integer LAG_W  = $clog2(MAX_NS + 1);
    localparam integer S_W    = $clog2(MAX_S + 1);
    localparam integer UID_W  = $clog2(MAX_UID + 1);
    localparam integer R_W    = $clog2(MAX_R + 1);
    localparam integer G_W    = $clog2(MAX_G + 1);
    localparam integer P_W    = $clog2(MAX_P + 1);
    localparam integer K_W    = (K > 1) ? $clog2(K) : 1;
    localparam integer CFG_W  = 16 + DEG_W + 2 * MAX_DEG + 2 * K * MAX_DEG + S_W + R_W + UID_W
                                + MAX_UID + LAG_W + 2 * G_W + 2 * NGHOST * LAG_W + 6 + 2 + 6
                                + P_W;
    localparam integer RES_W  = 1 + K_W + MAX_P * (1 + LAG_W + G_W + OUT_W + 2 * MAX_UID)
                                + 2 * OUT_W + G_W + (OUT_W + G_W) + (2 * OUT_W + G_W)
                                + MAX_UID + 2;
    localparam integer FOLD_N = (RES_W + 31) / 32;

    reg [CFG_W-1:0] cfg;
    always @(posedge clk)
        if (cfg_shift)
            cfg <= {cfg[CFG_W-2:0], cfg_sin};

    wire              corr_valid;
    wire [K_W-1:0]    corr_channel;
    wire [G_W-1:0]    corr_index;
    wire [OUT_W-1:0]  corr_data;
    wire              rv;
    wire [RES_W-2:0]  res;
    wire              col_start;
    reg               in_valid;
    reg [P_IN*ADC_W-1:0] in_data;
    wire              ready, refused;
    reg               start_q, stop_q, clear_q;
    always @(posedge clk) begin
        start_q   <= start;
        stop_q    <= stop;
        clear_q   <= clear_err;
        in_valid  <= s_valid;
        in_data   <= s_data;
        s_ready   <= ready;
        s_refused <= refused;
    end

    rx_top #(.K(K), .L(L), .P_IN(P_IN), .MAX_DEG(MAX_DEG), .MAX_S(MAX_S), .MAX_UID(MAX_UID), .MAX_R(MAX_R),
             .MAX_G(MAX_G), .MAX_P(MAX_P), .NGHOST(NGHOST), .ADC_W(ADC_W), .OUT_W(OUT_W)) dut (
        .clk(clk), .rst(rst), .start(start_q), .stop(stop_q), .clear_err(clear_q),
        .cfg_columns(cfg[15:0]),
        .cfg_degree(cfg[16 +: DEG_W]),
        .cfg_taps_u(cfg[16 + DEG_W +: MAX_DEG]),
        .cfg_taps_v(cfg[16 + DEG_W + MAX_DEG +: MAX_DEG]),
        .cfg_seed_u(cfg[16 + DEG_W + 2 * MAX_DEG +: K * MAX_DEG]),
        .cfg_seed_v(cfg[16 + DEG_W + 2 * MAX_DEG + K * MAX_DEG +: K * MAX_DEG]),
        .cfg_spc(cfg[16 + DEG_W + 2 * MAX_DEG + 2 * K * MAX_DEG +: S_W]),
        .cfg_averages(cfg[16 + DEG_W + 2 * MAX_DEG + 2 * K * MAX_DEG + S_W +: R_W]),
        .cfg_uid_bits(cfg[16 + DEG_W + 2 * MAX_DEG + 2 * K * MAX_DEG + S_W + R_W +: UID_W]),
        .cfg_uid(cfg[16 + DEG_W + 2 * MAX_DEG + 2 * K * MAX_DEG + S_W + R_W + UID_W +: MAX_UID]),
        .cfg_gate_start(cfg[CFG_W - P_W - 14 - 2 * NGHOST * LAG_W - 2 * G_W - LAG_W +: LAG_W]),
        .cfg_gate_len(cfg[CFG_W - P_W - 14 - 2 * NGHOST * LAG_W - 2 * G_W +: G_W]),
        .cfg_peak_exclude(cfg[CFG_W - P_W - 14 - 2 * NGHOST * LAG_W - G_W +: G_W]),
        .cfg_ghost_start(cfg[CFG_W - P_W - 14 - 2 * NGHOST * LAG_W +: NGHOST * LAG_W]),
        .cfg_ghost_len(cfg[CFG_W - P_W - 14 - NGHOST * LAG_W +: NGHOST * LAG_W]),
        .cfg_out_shift(cfg[CFG_W - P_W - 14 +: 6]),
        .cfg_rounding(cfg[CFG_W - P_W - 8 +: 2]),
        .cfg_out_bits(cfg[CFG_W - P_W - 6 +: 6]),
        .cfg_peaks(cfg[CFG_W - P_W +: P_W]),
        .s_valid(in_valid), .s_data(in_data), .s_ready(ready), .s_refused(refused),
        .err_refused(err_refused),
        .corr_valid(corr_valid), .corr_channel(corr_channel), .corr_index(corr_index),
        .corr_data(corr_data),
        .res_valid(rv), .res_channel(res[K_W-1:0]),
        .res_found(res[K_W +: MAX_P]),
        .res_lag(res[K_W + MAX_P +: MAX_P * LAG_W]),
        .res_index(res[K_W + MAX_P * (1 + LAG_W) +: MAX_P * G_W]),
        .res_peak(res[K_W + MAX_P * (1 + LAG_W + G_W) +: MAX_P * OUT_W]),
        .res_neg(res[K_W + MAX_P * (1 + LAG_W + G_W + OUT_W) +: MAX_P * MAX_UID]),
        .res_nz(res[K_W + MAX_P * (1 + LAG_W + G_W + OUT_W + MAX_UID) +: MAX_P * MAX_UID]),
        .res_nb_lo(res[K_W + MAX_P * (1 + LAG_W + G_W + OUT_W + 2 * MAX_UID) +: OUT_W]),
        .res_nb_hi(res[K_W + MAX_P * (1 + LAG_W + G_W + OUT_W + 2 * MAX_UID) + OUT_W +: OUT_W]),
        .res_noise_count(res[K_W + MAX_P * (1 + LAG_W + G_W + OUT_W + 2 * MAX_UID)
                             + 2 * OUT_W +: G_W]),
        .res_noise_sum(res[K_W + MAX_P * (1 + LAG_W + G_W + OUT_W + 2 * MAX_UID)
                           + 2 * OUT_W + G_W +: OUT_W + G_W]),
        .res_noise_sumsq(res[K_W + MAX_P * (1 + LAG_W + G_W + OUT_W + 2 * MAX_UID)
                             + 3 * OUT_W + 2 * G_W +: 2 * OUT_W + G_W]),
        .res_uid_observed(res[RES_W - 3 - MAX_UID +: MAX_UID]),
        .res_uid_match(res[RES_W - 3]),
        .res_saturated(res[RES_W - 2]),
        .busy(busy), .done(done), .col_start(col_start), .err_overrun(err_overrun)
    );

    // XOR fold of every result bit (on res_valid) and corr word (on corr_valid)
    wire [FOLD_N*32-1:0] res_pad = {{(FOLD_N*32-RES_W+1){1'b0}}, res};
    reg  [31:0] rf;
    integer i;
    always @(*) begin
        rf = 32'd0;
        for (i = 0; i < FOLD_N; i = i + 1)
            rf = rf ^ res_pad[i*32 +: 32];
    end
    always @(posedge clk) begin
        res_valid <= rv;
        if (rv)
            fold <= fold ^ rf;
        else if (corr_valid)
            fold <= fold ^ {{(32-OUT_W){1'b0}}, corr_data}
                         ^ {{(32-K_W-G_W){1'b0}}, corr_channel, corr_index};
        else if (col_start)
            fold <= {fold[30:0], fold[31]};
    end
endmodule

`default_nettype wire
