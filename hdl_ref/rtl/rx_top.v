// rx_top -- K-channel receive chain that keeps up with the ADC: one sample per
// clock in, K channels' peak / neighbours / noise floor / UID results out per
// column, bit for bit firmware_model.receiver.reference (docs/hdl.md).
//
// Architecture (the arithmetic is in docs/hdl.md, "rx_top"):
//   * Coherent averaging into a double-buffered RAM: while column c+1 is
//     accumulated (read-modify-write, one sample per clock) into one buffer,
//     column c is correlated from the other. Each buffer is MAX_S banks:
//     bank s holds acc[p][c*S + s] at address p*N + c (chip c, period p).
//   * Chip-domain sums: lag l = q*S + s' needs box(t, s') = sum of the S
//     samples acc[t*S + s' .. t*S + s' + S - 1], i.e. banks s >= s' at chip t
//     and banks s < s' at chip t + 1: the S banks are read in parallel and
//     summed by one adder tree shared by every lane, so S samples cost one add
//     per lane.  raw(q*S + s') = sum_c b_c box(c + q, s').
//   * Lanes: each channel has L lanes. A "group" is L lags of one phase s'
//     (chip shifts q0..q0+L-1, i.e. lags S apart); the box stream t = q0 + k
//     (k = 0..N+L-2) is broadcast to all K*L lanes; lane j of channel k adds
//     +-box with chip b_(k-j) of channel k's Gold code (a delay line of the
//     generator's chips) for k = j..j+N-1. Per UID period p one stream; the
//     lane folds (-1)^uid_p c_p into its despread total and keeps the sign
//     bits of c_p. The G+2 lags gate_start-1 .. gate_start+G are covered by
//     sum over phases of ceil(lags of the phase / L) groups.
//   * At the end of a group the K*L totals move into a shift chain that
//     feeds one shared out_scale (round, saturate) and the correlation RAM
//     ({channel, gate index} addressed); it must drain (K*L clocks) before
//     the next group ends (checked: err_overrun).
//   * Post-processing per channel (peaks, neighbours, noise floor, UID,
//     saturation flag) scans the correlation RAM as rx_chain does, and emits
//     the channel's results with a res_valid pulse and its gate trace on corr_*.
// Result order: per column, channels 0..K-1; per channel corr words j = 0..G-1
// then res_valid.
//
// Configuration is sampled at `start`; then cfg_columns columns are taken
// (samples in the order repetition r, period p, sample i; P_IN of them per
// clock, the earliest at s_data[ADC_W-1:0]) and `done` pulses after the last
// column's last channel. cfg_columns = 0 runs free: columns follow each other
// until `stop`, which lets the column already begun finish (any column count
// is cut short the same way). ADC interface: s_valid/s_ready in the clk domain
// (the clock-domain crossing from the converter is the integrator's). A source
// that cannot wait (a fixed-rate strobe) loses every sample offered while
// s_ready is low: s_refused marks each such clock, and the sticky err_refused
// (like err_overrun) holds until clear_err.
`default_nettype none

module rx_top #(
    parameter integer K         = 4,    // channels (Gold members)
    parameter integer L         = 2,    // lanes (parallel lags) per channel
    parameter integer P_IN      = 1,    // ADC samples per clock (divides MAX_S and cfg_spc)
    parameter integer MAX_DEG   = 11,
    parameter integer MAX_S     = 4,
    parameter integer MAX_UID   = 1,
    parameter integer MAX_R     = 16,
    parameter integer MAX_G     = 64,
    parameter integer MAX_P     = 1,
    parameter integer NGHOST    = 1,
    parameter integer ADC_W     = 12,
    parameter integer OUT_W     = 32,
    // ---- derived, do not override ----
    parameter integer DEG_W     = $clog2(MAX_DEG + 1),
    parameter integer MAX_N     = (1 << MAX_DEG) - 1,
    parameter integer MAX_NS    = MAX_N * MAX_S,
    parameter integer LAG_W     = $clog2(MAX_NS + 1),
    parameter integer S_W       = $clog2(MAX_S + 1),
    parameter integer UID_W     = $clog2(MAX_UID + 1),
    parameter integer R_W       = $clog2(MAX_R + 1),
    parameter integer G_W       = $clog2(MAX_G + 1),
    parameter integer P_W       = $clog2(MAX_P + 1),
    parameter integer K_W       = (K > 1) ? $clog2(K) : 1,
    parameter integer SH_W      = 6,
    parameter integer OB_W      = 6,
    parameter integer COL_W     = 16,
    parameter integer CNT_W     = G_W,
    parameter integer SUM_W     = OUT_W + G_W,
    parameter integer SQ_W      = 2 * OUT_W + G_W
) (
    input  wire                         clk,
    input  wire                         rst,

    input  wire                         start,
    input  wire                         stop,           // finish the column being taken, then done
    input  wire                         clear_err,      // clears err_refused and err_overrun
    input  wire [COL_W-1:0]             cfg_columns,    // columns to take; 0 = until stop
    input  wire [DEG_W-1:0]             cfg_degree,
    input  wire [MAX_DEG-1:0]           cfg_taps_u,
    input  wire [MAX_DEG-1:0]           cfg_taps_v,
    input  wire [K*MAX_DEG-1:0]         cfg_seed_u,     // channel k at [k*MAX_DEG +: MAX_DEG]
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
    input  wire [SH_W-1:0]              cfg_out_shift,
    input  wire [1:0]                   cfg_rounding,
    input  wire [OB_W-1:0]              cfg_out_bits,
    input  wire [P_W-1:0]               cfg_peaks,

    input  wire                         s_valid,
    input  wire [P_IN*ADC_W-1:0]        s_data,         // sample k of the clock at [k*ADC_W]
    output reg                          s_ready,        // a register: see "ADC handshake"
    output wire                         s_refused,      // s_valid && !s_ready while busy
    output reg                          err_refused,    // sticky: a sample was refused

    output wire                         corr_valid,
    output reg  [K_W-1:0]               corr_channel,
    output wire [G_W-1:0]               corr_index,
    output wire signed [OUT_W-1:0]      corr_data,

    output wire                         res_valid,      // one pulse per channel and column
    output reg  [K_W-1:0]               res_channel,
    output wire [MAX_P-1:0]             res_found,
    output wire [MAX_P*LAG_W-1:0]       res_lag,
    output wire [MAX_P*G_W-1:0]         res_index,
    output wire [MAX_P*OUT_W-1:0]       res_peak,
    output wire [MAX_P*MAX_UID-1:0]     res_neg,
    output wire [MAX_P*MAX_UID-1:0]     res_nz,
    output wire signed [OUT_W-1:0]      res_nb_lo,
    output wire signed [OUT_W-1:0]      res_nb_hi,
    output wire [CNT_W-1:0]             res_noise_count,
    output wire signed [SUM_W-1:0]      res_noise_sum,
    output wire [SQ_W-1:0]              res_noise_sumsq,
    output wire [MAX_UID-1:0]           res_uid_observed,
    output wire                         res_uid_match,
    output wire                         res_saturated,  // first peak's out word at a rail

    output wire                         busy,
    output reg                          done,
    output reg                          col_start,      // pulse: a column's processing starts
    output reg                          err_overrun     // sticky: lanes outran the serializer
);
    // ------------------------------------------------------------------
    // Widths
    // ------------------------------------------------------------------
    generate   // a derived parameter overridden by mistake stops the elaboration
        if (DEG_W != $clog2(MAX_DEG + 1) || MAX_N != (1 << MAX_DEG) - 1
            || MAX_NS != MAX_N * MAX_S || LAG_W != $clog2(MAX_NS + 1)
            || S_W != $clog2(MAX_S + 1) || UID_W != $clog2(MAX_UID + 1)
            || R_W != $clog2(MAX_R + 1) || G_W != $clog2(MAX_G + 1)
            || P_W != $clog2(MAX_P + 1) || K_W != ((K > 1) ? $clog2(K) : 1)
            || CNT_W != G_W || SUM_W != OUT_W + G_W || SQ_W != 2 * OUT_W + G_W)
        begin : g_derived_width_mismatch
            rx_top_derived_width_mismatch bad ();
        end
    endgenerate
    localparam integer AVG_W  = ADC_W + $clog2(MAX_R);
    localparam integer BOX_W  = AVG_W + $clog2(MAX_S);
    localparam integer PER_W  = BOX_W + MAX_DEG + 1;
    localparam integer RAW_W  = PER_W + $clog2(MAX_UID);
    localparam integer ADDR_W = $clog2(MAX_UID * MAX_N);
    localparam integer KST_W  = $clog2(MAX_N + L + 1);      // stream step
    localparam integer JJ_W   = G_W + 1;                     // extended gate index 0..G+1
    localparam integer CA_W   = $clog2(MAX_G + 2);
    localparam integer CW     = OUT_W + 2 * MAX_UID;         // correlation RAM word
    localparam integer KL     = K * L;
    localparam integer TAG_W  = 2 * MAX_UID + K_W + CA_W;
    localparam integer DIV_W  = $clog2(LAG_W + 1);
    localparam integer SJ_W   = $clog2(L + 1);
    localparam [31:0]     K_M1 = K - 1, L_M1 = L;
    localparam [K_W-1:0]  K_LAST = K_M1[K_W-1:0];
    localparam [SJ_W-1:0] L_LAST = L_M1[SJ_W-1:0] - 1'b1;

    localparam [1:0] T_IDLE = 2'd0, T_INIT1 = 2'd1, T_INIT2 = 2'd2, T_RUN = 2'd3;
    localparam [3:0] P_IDLE  = 4'd0, P_SETUP = 4'd1, P_STREAM = 4'd2, P_FLUSH = 4'd3,
                     P_POST  = 4'd4, P_START = 4'd5;

    reg [1:0] tstate;
    reg [3:0] pstate;

    // ------------------------------------------------------------------
    // Configuration
    // ------------------------------------------------------------------
    reg [COL_W-1:0]        c_columns;
    reg                    c_free;      // cfg_columns = 0: columns until `stop`
    wire [DEG_W-1:0]        c_degree;
    wire [MAX_DEG-1:0]      c_taps_u, c_taps_v;
    wire [K*MAX_DEG-1:0]    c_seed_u, c_seed_v;
    wire [S_W-1:0]          c_spc;
    wire [R_W-1:0]          c_averages;
    wire [UID_W-1:0]        c_uid_bits;
    wire [MAX_UID-1:0]      c_uid;
    wire [LAG_W-1:0]        c_gate_start;
    wire [G_W-1:0]          c_gate_len, c_excl;
    wire [NGHOST*LAG_W-1:0] c_gh_start, c_gh_len;
    wire [SH_W-1:0]         c_shift;
    wire [1:0]              c_round;
    wire [OB_W-1:0]         c_out_bits;
    wire [P_W-1:0]          c_peaks;
    cfg_latch #(.MAX_DEG(MAX_DEG), .MAX_UID(MAX_UID), .NGHOST(NGHOST), .SEED_W(K * MAX_DEG),
                .DEG_W(DEG_W), .S_W(S_W), .R_W(R_W), .UID_W(UID_W), .LAG_W(LAG_W), .G_W(G_W),
                .P_W(P_W), .SH_W(SH_W), .OB_W(OB_W)) cfg (
        .clk(clk), .load(tstate == T_IDLE && start),
        .cfg_degree(cfg_degree), .cfg_taps_u(cfg_taps_u), .cfg_taps_v(cfg_taps_v),
        .cfg_seed_u(cfg_seed_u), .cfg_seed_v(cfg_seed_v), .cfg_spc(cfg_spc),
        .cfg_averages(cfg_averages), .cfg_uid_bits(cfg_uid_bits), .cfg_uid(cfg_uid),
        .cfg_gate_start(cfg_gate_start), .cfg_gate_len(cfg_gate_len),
        .cfg_peak_exclude(cfg_peak_exclude), .cfg_ghost_start(cfg_ghost_start),
        .cfg_ghost_len(cfg_ghost_len), .cfg_out_shift(cfg_out_shift),
        .cfg_rounding(cfg_rounding), .cfg_out_bits(cfg_out_bits), .cfg_peaks(cfg_peaks),
        .c_degree(c_degree), .c_taps_u(c_taps_u), .c_taps_v(c_taps_v), .c_seed_u(c_seed_u),
        .c_seed_v(c_seed_v), .c_spc(c_spc), .c_averages(c_averages), .c_uid_bits(c_uid_bits),
        .c_uid(c_uid), .c_gate_start(c_gate_start), .c_gate_len(c_gate_len), .c_excl(c_excl),
        .c_gh_start(c_gh_start), .c_gh_len(c_gh_len), .c_shift(c_shift), .c_round(c_round),
        .c_out_bits(c_out_bits), .c_peaks(c_peaks)
    );

    reg [MAX_DEG-1:0]      nn;          // N chips
    reg [LAG_W-1:0]        ns;          // N * S
    reg [LAG_W-1:0]        lo;          // gate_start - 1 mod NS
    wire [MAX_DEG:0]       n_chips = ({{MAX_DEG{1'b0}}, 1'b1} << c_degree) - {{MAX_DEG{1'b0}}, 1'b1};
    wire [MAX_DEG+S_W:0]   ns_full = n_chips * {{MAX_DEG{1'b0}}, c_spc};
    wire [MAX_UID-1:0]     uid_mask = ({{(MAX_UID-1){1'b0}}, 1'b1} << c_uid_bits)
                                      - {{(MAX_UID-1){1'b0}}, 1'b1};
    wire [JJ_W-1:0]        jj_last = {1'b0, c_gate_len} + 1'b1;   // G + 1

    function [LAG_W-1:0] lag_inc(input [LAG_W-1:0] x, input [LAG_W-1:0] m);
        lag_inc = (x == m - 1'b1) ? {LAG_W{1'b0}} : x + 1'b1;
    endfunction
    function [MAX_DEG-1:0] chip_inc(input [MAX_DEG-1:0] x, input [MAX_DEG-1:0] m);
        chip_inc = (x == m - 1'b1) ? {MAX_DEG{1'b0}} : x + 1'b1;
    endfunction

    // ---- lo = q_lo * S + s_lo: restoring division, one quotient bit per clock ----
    reg              div_run, div_done;
    reg [DIV_W-1:0]  div_i;
    reg [LAG_W-1:0]  div_q;
    reg [S_W:0]      div_r;
    wire [LAG_W-1:0] lo_sh = lo >> (div_i - 1'b1);
    wire [S_W+1:0]   div_t = {div_r, lo_sh[0]};
    wire             div_ge = div_t >= {2'b00, c_spc};
    wire [S_W+1:0]   div_d  = div_t - {2'b00, c_spc};

    // ------------------------------------------------------------------
    // Averaging: two buffers of MAX_S banks (n * N words of AVG_W bits each)
    // ------------------------------------------------------------------
    reg               acc_buf;          // buffer being accumulated
    reg               proc_buf;         // buffer being correlated
    reg  [1:0]        full;             // buffer b holds a complete column not yet processed
    reg               proc_on;          // the engine is reading proc_buf
    reg [COL_W-1:0]   cols_in, cols_out;
    reg [S_W-1:0]     a_s;              // bank of the clock's first sample (multiple of P_IN)
    reg [MAX_DEG-1:0] a_c;
    reg [UID_W-1:0]   a_p;
    reg [ADDR_W-1:0]  a_base;
    reg [R_W-1:0]     a_r;
    // a_X_last == (a_X is at its wrap value), registered with the counter (below)
    reg               a_s_last, a_c_last, a_p_last, a_r_last;

    assign busy      = (tstate != T_IDLE);
    assign s_refused = busy && s_valid && !s_ready;
    wire a_take      = s_valid && s_ready;
    // a_open: a column is open (some sample of it taken, not its last), i.e. the averaging
    // counters are not all 0; a register updated with them (below), so `stop` needs no OR
    // of the counters
    reg  a_open;
    localparam [31:0]    P_IN32 = P_IN;
    localparam [S_W-1:0] P_STEP = P_IN32[S_W-1:0];

    reg               r_v, r_first, r_buf;   // read issued last clock
    reg [S_W-1:0]     r_bank;
    reg [ADDR_W-1:0]  r_addr;
    reg [P_IN*ADC_W-1:0] r_x;
    reg               rr_v, rr_first, rr_buf; // read data on rd (output register)
    reg [S_W-1:0]     rr_bank;
    reg [ADDR_W-1:0]  rr_addr;
    reg [P_IN*ADC_W-1:0] rr_x;
    reg [MAX_S*AVG_W-1:0] w_old;             // the buffer's bank words, registered
    reg               w_v, w_first, w_buf;
    reg [S_W-1:0]     w_bank;
    reg [ADDR_W-1:0]  w_addr;
    reg [P_IN*ADC_W-1:0] w_x;
    wire [ADDR_W-1:0] a_addr = a_base + {{(ADDR_W-MAX_DEG){1'b0}}, a_c};

    wire [AVG_W-1:0]  rd [0:2*MAX_S-1];            // bank (b, s) at b*MAX_S + s
    reg  [ADDR_W-1:0] corr_addr [0:MAX_S-1];
    reg  [MAX_S*ADDR_W-1:0] addr0;           // stage 0 (below): registered corr_addr

    genvar gb, gs;
    generate
        for (gb = 0; gb < 2; gb = gb + 1) begin : g_buf
            for (gs = 0; gs < MAX_S; gs = gs + 1) begin : g_bank
                // bank gs takes sample gs % P_IN of a clock whose first bank is gs - gs % P_IN
                localparam integer  SX = gs % P_IN;
                localparam [31:0]   GB32 = gs - SX;
                wire [ADC_W-1:0]    wx = w_x[SX*ADC_W +: ADC_W];
                wire [AVG_W-1:0]    wx_ext = {{(AVG_W-ADC_W+1){wx[ADC_W-1]}}, wx[ADC_W-2:0]};
                wire we = w_v && (w_buf == gb) && (w_bank == GB32[S_W-1:0]);
                wire [ADDR_W-1:0] ra = (proc_on && proc_buf == gb) ? addr0[gs*ADDR_W +: ADDR_W]
                                                                   : a_addr;
                sdp_ram #(.WIDTH(AVG_W), .DEPTH(MAX_UID * MAX_N), .OUTREG(1)) bank (
                    .clk(clk), .we(we), .waddr(w_addr),
                    .wdata(w_first ? wx_ext : w_old[gs*AVG_W +: AVG_W] + wx_ext),
                    .raddr(ra), .rdata(rd[gb * MAX_S + gs])
                );
            end
        end
    endgenerate

    // ------------------------------------------------------------------
    // Correlation streams (stage 0: issue)
    // ------------------------------------------------------------------
    reg  [S_W-1:0]     ph;              // phase index: lags lo+ph, lo+ph+S, ...
    reg  [MAX_DEG-1:0] ph_q;            // lag lo+ph = ph_q * S + ph_s
    reg  [S_W-1:0]     ph_s;
    reg  [MAX_DEG-1:0] g_q;             // chip shift of lane 0 of the group
    reg  [JJ_W-1:0]    g_jj;            // extended gate index of lane 0
    reg  [UID_W-1:0]   st_p;
    reg  [ADDR_W-1:0]  st_base;         // st_p * N
    reg  [KST_W-1:0]   st_k;            // 0 .. N+L-2
    reg  [MAX_DEG-1:0] st_t;            // (g_q + k) mod N
    wire [MAX_DEG-1:0] st_t1 = chip_inc(st_t, nn);
    // k_end: the stream's last step less one, N + L - 3 (set at T_INIT2 from nn), so the
    // last-step test is one equality with st_k, no adder
    reg  [KST_W-1:0]   k_end;
    // st_end (the stream's last step) is a register, set one clock ahead, so the
    // generators' enables below need no comparator in front of them.
    reg                st_end;
    wire               st_end_nx = (pstate == P_STREAM) && !st_end && (st_k == k_end);
    wire               st_lastp = (st_p == c_uid_bits - 1'b1);
    localparam [JJ_W+S_W:0] L_JJ = L_M1[JJ_W+S_W:0];
    wire [JJ_W+S_W:0]  g_jj_nx  = {{(S_W+1){1'b0}}, g_jj} + L_JJ * {{(JJ_W+1){1'b0}}, c_spc};
    // g_more (another group of this phase) and ph_more (another phase) are registers: the
    // compares of g_jj_nx and ph_nx with the gate, one clock behind g_jj and ph. Those
    // change only at a stream's end (P_START for the first), and the next end, which reads
    // the flags, is N + L - 1 >= 7 clocks later: the delay is never seen, and no carry
    // chain from c_spc sits in front of stream_done and the generators' strobes.
    reg                g_more, ph_more;
    wire [MAX_DEG:0]   g_q_sum  = {1'b0, g_q} + L[MAX_DEG:0];
    wire [MAX_DEG:0]   g_q_dif  = g_q_sum - {1'b0, nn};
    wire [MAX_DEG-1:0] g_q_nx   = (g_q_sum >= {1'b0, nn}) ? g_q_dif[MAX_DEG-1:0]
                                                          : g_q_sum[MAX_DEG-1:0];
    wire [S_W-1:0]     ph_nx    = ph + 1'b1;
    always @(posedge clk) begin
        g_more  <= g_jj_nx <= {{(S_W+1){1'b0}}, jj_last};
        ph_more <= (ph_nx < c_spc) && ({{(JJ_W-S_W){1'b0}}, ph_nx} <= jj_last);
    end
    wire               ph_s_wrap = (ph_s == c_spc - 1'b1);

    integer bi;
    always @(*) begin
        for (bi = 0; bi < MAX_S; bi = bi + 1)
            corr_addr[bi] = st_base + {{(ADDR_W-MAX_DEG){1'b0}},
                                       (bi >= ph_s) ? st_t : st_t1};
    end

    // Gold generators, one pair per channel. Their load and enable are registers (the
    // next clock's values, below), one copy per GEN_GRP channels, so no strobe crosses
    // the die to 2 K generators in one clock (each copy a gen_strobe instance: synthesis
    // keeps them apart, where it would merge identical flip-flops of one module).
    localparam integer GEN_GRP = 4;
    localparam integer GEN_NG  = (K + GEN_GRP - 1) / GEN_GRP;
    wire              stream_done = st_lastp && !g_more && !ph_more;
    wire              gen_load_nx = (pstate == P_START) || st_end_nx;
    wire              gen_en_nx   = (pstate == P_SETUP)
                                    || (pstate == P_STREAM && (st_end ? !stream_done
                                                                      : !st_end_nx));
    wire [GEN_NG-1:0] gen_load, gen_en;
    genvar gg;
    generate
        for (gg = 0; gg < GEN_NG; gg = gg + 1) begin : g_strobe
            gen_strobe copy (.clk(clk), .rst(rst), .load_nx(gen_load_nx), .en_nx(gen_en_nx),
                             .load(gen_load[gg]), .en(gen_en[gg]));
        end
    endgenerate
    wire [K-1:0]      chip;
    genvar gk;
    generate
        for (gk = 0; gk < K; gk = gk + 1) begin : g_gen
            wire cu, cv;
            wire [MAX_DEG-1:0] su, sv;
            lfsr_fib #(.MAX_DEG(MAX_DEG)) gu (
                .clk(clk), .load(gen_load[gk / GEN_GRP]), .en(gen_en[gk / GEN_GRP]),
                .seed(c_seed_u[gk*MAX_DEG +: MAX_DEG]),
                .taps(c_taps_u), .degree(c_degree), .out(cu), .state(su));
            lfsr_fib #(.MAX_DEG(MAX_DEG)) gv (
                .clk(clk), .load(gen_load[gk / GEN_GRP]), .en(gen_en[gk / GEN_GRP]),
                .seed(c_seed_v[gk*MAX_DEG +: MAX_DEG]),
                .taps(c_taps_v), .degree(c_degree), .out(cv), .state(sv));
            assign chip[gk] = cu ^ cv;
            wire unused_gen = &{1'b0, su, sv};
        end
    endgenerate

    // ---- stage 0: registered RAM addresses ----
    reg               v0, f0, a0, gend0, glast0;
    reg [UID_W-1:0]   p0;
    reg [K-1:0]       code0;
    reg [JJ_W-1:0]    gjj0;
    // ---- stage 1: RAM data ----
    reg               v1, f1, a1, gend1, glast1;
    reg [UID_W-1:0]   p1;
    reg [K-1:0]       code1;
    reg [JJ_W-1:0]    gjj1;
    // ---- stage 2: box sum ----
    reg               v2, f2, a2, gend2, glast2;
    reg [UID_W-1:0]   p2;
    reg [K-1:0]       code2;
    reg [JJ_W-1:0]    gjj2;
    reg signed [BOX_W-1:0] box2;

    reg               vr, fr, ar, gendr, glastr;   // stage 1a: RAM output register
    reg [UID_W-1:0]   pr;
    reg [K-1:0]       coder;
    reg [JJ_W-1:0]    gjjr;
    reg               vq, fq, aq, gendq, glastq;   // stage 1b: RAM words registered
    reg [UID_W-1:0]   pq;
    reg [K-1:0]       codeq;
    reg [JJ_W-1:0]    gjjq;
    reg [MAX_S*AVG_W-1:0] rdq;
    reg signed [BOX_W-1:0] box1;
    integer bsi, si, sj;    // bsi: the combinational loop; si, sj: two clocked blocks' loops
    // s_on[s]: bank s is summed (s < S), a register, so the configuration's S is off the
    // box sum's clock (it changes only while the configuration is latched)
    reg [MAX_S-1:0] s_on;
    generate
        for (gs = 0; gs < MAX_S; gs = gs + 1) begin : g_s_on
            localparam [31:0] GS32 = gs;
            always @(posedge clk)
                s_on[gs] <= ({1'b0, GS32[S_W-1:0]} < {1'b0, c_spc});
        end
    endgenerate
    always @(*) begin
        box1 = {BOX_W{1'b0}};
        for (bsi = 0; bsi < MAX_S; bsi = bsi + 1)
            if (s_on[bsi])
                box1 = box1 + {{(BOX_W-AVG_W){rdq[bsi*AVG_W + AVG_W-1]}},
                               rdq[bsi*AVG_W +: AVG_W]};
    end

    // ---- lanes: c_p = 2 * plus - all ----
    // With chips b in {0 -> +1, 1 -> -1}, sum_c (-1)^b_c box = 2 * (sum of the boxes whose
    // chip is 0) - (sum of every box of the period). A lane therefore only adds box when
    // its chip is 0 (a clock enable: no negation, no multiplexer) and is never cleared
    // between streams: the serializer subtracts the lane's value at the previous stream's
    // end (PER_W-bit arithmetic wraps, the difference is exact). `all_sum` sums every
    // box of the stream's first N steps (lane 0's window: every chip once), the same for
    // every lane. Lane k*L + j at [(k*L + j)*PER_W +: PER_W].
    //
    // Each channel's lanes read their own copy of stage 2 (a lane_feed: box sum, valid,
    // "all" flag, clear) and delay its "all" flag and chip along their own line (entry j
    // = step k - j), so no net reaches the K L lane adders from one register.
    wire [KL*PER_W-1:0]     ln_per;
    wire [PER_W-1:0]        bx = {{(PER_W-BOX_W){box2[BOX_W-1]}}, box2};
    reg                     ln_clr;         // start of a run: every lane to 0
    reg  [PER_W-1:0]        all_sum;
    wire [2*MAX_S*AVG_W-1:0] rd_all;
    genvar gj;
    generate
        for (gj = 0; gj < 2 * MAX_S; gj = gj + 1) begin : g_rd
            assign rd_all[gj*AVG_W +: AVG_W] = rd[gj];
        end
        for (gk = 0; gk < K; gk = gk + 1) begin : g_lk
            wire signed [BOX_W-1:0] f_box;
            wire                    f_v, f_a, f_clr;
            wire [PER_W-1:0]        f_bx = {{(PER_W-BOX_W){f_box[BOX_W-1]}}, f_box};
            wire [L-1:0]            e_a, e_code;
            lane_feed #(.MAX_S(MAX_S), .AVG_W(AVG_W), .BOX_W(BOX_W)) feed (
                .clk(clk), .rst(rst), .rd(rd_all), .proc_buf(proc_buf), .s_on(s_on),
                .vq(vq), .aq(aq), .clr_nx(tstate == T_INIT2),
                .box(f_box), .v(f_v), .a(f_a), .clr(f_clr));
            if (L == 1) begin : g_l1
                assign e_a = f_a;
                assign e_code = code2[gk];
            end else begin : g_ln
                reg [L-2:0] sr_a, sr_code;  // sr[j] = step k - 1 - j
                assign e_a = {sr_a, f_a};
                assign e_code = {sr_code, code2[gk]};
                always @(posedge clk) begin
                    if (f_v) begin
                        sr_a <= e_a[L-2:0];
                        sr_code <= e_code[L-2:0];
                    end
                    if (rst)
                        sr_a <= {(L-1){1'b0}};
                end
            end
            for (gj = 0; gj < L; gj = gj + 1) begin : g_lj
                localparam integer IX = gk * L + gj;
                reg [PER_W-1:0] per;
                always @(posedge clk) begin
                    if (f_clr)
                        per <= {PER_W{1'b0}};
                    else if (f_v && e_a[gj] && !e_code[gj])
                        per <= per + f_bx;
                end
                assign ln_per[IX*PER_W +: PER_W] = per;
            end
        end
    endgenerate

    always @(posedge clk)
        if (v2 && a2)
            all_sum <= (f2 ? {PER_W{1'b0}} : all_sum) + bx;

    // ---- hold chain and serializer ----
    // At a stream's end the K*L lane values move into the hold chain (one clock before
    // lane 0 adds again); the serializer walks it, one lane per clock, through
    //   x0: lane value; state RAM word {previous value, total, neg, nz} of the lane
    //   x1: d = value - previous (0 after ln_clr)
    //   x2: c_p = 2 d - all
    //   x3: total (+-c_p folded by the UID bit), neg, nz; state RAM write;
    //       on the last UID period: out_scale (round, saturate) and the correlation RAM.
    localparam integer KL_W = (KL > 1) ? $clog2(KL) : 1;
    localparam integer ST_W = PER_W + RAW_W + 2 * MAX_UID;
    reg                     latch_v;        // a stream ended: copy
    reg  [JJ_W-1:0]         latch_jj;
    reg  [UID_W-1:0]        latch_p;
    reg                     latch_last;
    wire [KL*PER_W-1:0]     h_per;          // entry 0 at the bottom
    reg  [PER_W-1:0]        h_all;
    reg                     ser_busy, ser_fst, ser_last, ln_fst;
    reg  [UID_W-1:0]        ser_p;
    reg  [KL_W-1:0]         ser_idx;
    reg  [K_W-1:0]          ser_k;
    reg  [SJ_W-1:0]         ser_j;
    reg  [JJ_W+S_W:0]       ser_jj;
    reg  [JJ_W-1:0]         ser_base;
    wire                    ser_ok = ser_busy && (ser_jj <= {{(S_W+1){1'b0}}, jj_last});

    reg                     x0_v, x0_ok, x0_fst, x0_last;
    reg  [UID_W-1:0]        x0_p;
    reg  [KL_W-1:0]         x0_idx;
    reg  [K_W+CA_W-1:0]     x0_tag;
    reg  [PER_W-1:0]        x0_h, x0_all;
    reg                     x1_v, x1_ok, x1_last;
    reg  [UID_W-1:0]        x1_p;
    reg  [KL_W-1:0]         x1_idx;
    reg  [K_W+CA_W-1:0]     x1_tag;
    reg  [PER_W-1:0]        x1_h, x1_all, x1_d;
    reg  [RAW_W-1:0]        x1_tot;
    reg  [MAX_UID-1:0]      x1_neg, x1_nz;
    reg                     x2_v, x2_ok, x2_last;
    reg  [UID_W-1:0]        x2_p;
    reg  [KL_W-1:0]         x2_idx;
    reg  [K_W+CA_W-1:0]     x2_tag;
    reg  [PER_W-1:0]        x2_h;
    reg  signed [PER_W-1:0] x2_c;
    reg  [RAW_W-1:0]        x2_tot;
    reg  [MAX_UID-1:0]      x2_neg, x2_nz;
    reg                     x3_v, x3_ok, x3_last;
    reg  [KL_W-1:0]         x3_idx;
    reg  [K_W+CA_W-1:0]     x3_tag;
    reg  [PER_W-1:0]        x3_h;
    reg  [RAW_W-1:0]        x3_tot;
    reg  [MAX_UID-1:0]      x3_neg, x3_nz;

    // The state RAM is read through its output register (block-RAM clock-to-out would
    // otherwise start x1's subtract), so its address runs one clock ahead of ser_idx:
    // st_ra is lane 0 while the serializer idles (the latch clock reads it), counts with
    // the walk and is back at 0 after lane K L - 1. Lane i is written (x3) at least
    // N + L - 1 - 5 clocks before the next stream reads it (K L <= N - 2, N >= 7).
    localparam [31:0]       KL_M1 = KL - 1;
    localparam [KL_W-1:0]   KL_LAST = KL_M1[KL_W-1:0];
    reg  [KL_W-1:0]         st_ra;
    wire [ST_W-1:0]         st_rdata;
    wire [PER_W-1:0]        st_prev = st_rdata[ST_W-1 -: PER_W];
    sdp_ram #(.WIDTH(ST_W), .DEPTH((KL > 1) ? KL : 2), .OUTREG(1)) st_ram (
        .clk(clk), .we(x3_v), .waddr(x3_idx), .wdata({x3_h, x3_tot, x3_neg, x3_nz}),
        .raddr(st_ra), .rdata(st_rdata)
    );
    always @(posedge clk) begin
        if ((latch_v || (ser_busy && st_ra != {KL_W{1'b0}})) && st_ra != KL_LAST)
            st_ra <= st_ra + 1'b1;
        else
            st_ra <= {KL_W{1'b0}};
        if (rst)
            st_ra <= {KL_W{1'b0}};
    end

    wire [PER_W-1:0]        x2_c2 = {x1_d[PER_W-2:0], 1'b0} - x1_all;
    wire signed [RAW_W-1:0] x2_cext = {{(RAW_W-PER_W){x2_c[PER_W-1]}}, x2_c};
    wire [MAX_UID-1:0]      x2_sel = {{(MAX_UID-1){1'b0}}, 1'b1} << x2_p;
    wire                    x2_flip = |(c_uid & x2_sel);
    wire                    x2_p0 = (x2_p == {UID_W{1'b0}});

    always @(posedge clk) begin
        x0_v <= ser_busy;
        x0_ok <= ser_ok;
        x0_fst <= ser_fst;
        x0_last <= ser_last;
        x0_p <= ser_p;
        x0_idx <= ser_idx;
        x0_tag <= {ser_k, ser_jj[CA_W-1:0]};
        x0_h <= h_per[PER_W-1:0];
        x0_all <= h_all;

        x1_v <= x0_v;
        x1_ok <= x0_ok;
        x1_last <= x0_last;
        x1_p <= x0_p;
        x1_idx <= x0_idx;
        x1_tag <= x0_tag;
        x1_h <= x0_h;
        x1_all <= x0_all;
        x1_d <= x0_h - (x0_fst ? {PER_W{1'b0}} : st_prev);
        {x1_tot, x1_neg, x1_nz} <= st_rdata[RAW_W+2*MAX_UID-1:0];

        x2_v <= x1_v;
        x2_ok <= x1_ok;
        x2_last <= x1_last;
        x2_p <= x1_p;
        x2_idx <= x1_idx;
        x2_tag <= x1_tag;
        x2_h <= x1_h;
        x2_c <= x2_c2;
        x2_tot <= x1_tot;
        x2_neg <= x1_neg;
        x2_nz <= x1_nz;

        x3_v <= x2_v;
        x3_ok <= x2_ok;
        x3_last <= x2_last;
        x3_idx <= x2_idx;
        x3_tag <= x2_tag;
        x3_h <= x2_h;
        x3_tot <= (x2_p0 ? {RAW_W{1'b0}} : x2_tot) + (x2_flip ? -x2_cext : x2_cext);
        x3_neg <= (x2_p0 ? {MAX_UID{1'b0}} : x2_neg)
                  | (x2_c[PER_W-1] ? x2_sel : {MAX_UID{1'b0}});
        x3_nz  <= (x2_p0 ? {MAX_UID{1'b0}} : x2_nz)
                  | ((x2_c != {PER_W{1'b0}}) ? x2_sel : {MAX_UID{1'b0}});

        if (latch_v)
            h_all <= all_sum;
        if (rst) begin
            x0_v <= 1'b0;
            x1_v <= 1'b0;
            x2_v <= 1'b0;
            x3_v <= 1'b0;
        end
    end

    // The hold chain: each channel's L entries load the lane values in the latch clock
    // and otherwise shift down one entry a clock (zeros in at the top). Between walks it
    // shifts what no stage reads, so it needs no clock enable; its load select is a
    // register copy per channel (latch_v's, a gen_strobe instance each), so no one net
    // reaches the K L PER_W flip-flops of the chain across the die.
    wire [KL*PER_W-1:0]     h_dn = h_per >> PER_W;
    wire [K-1:0]            h_ld;
    generate
        for (gk = 0; gk < K; gk = gk + 1) begin : g_hold
            reg [L*PER_W-1:0] h;
            wire              unused_en;
            gen_strobe ld (.clk(clk), .rst(rst), .load_nx(v2 && gend2), .en_nx(1'b0),
                           .load(h_ld[gk]), .en(unused_en));
            always @(posedge clk)
                h <= h_ld[gk] ? ln_per[gk*L*PER_W +: L*PER_W] : h_dn[gk*L*PER_W +: L*PER_W];
            assign h_per[gk*L*PER_W +: L*PER_W] = h;
        end
    endgenerate

    wire                    sc_v;
    wire signed [OUT_W-1:0] sc_word;
    wire [TAG_W-1:0]        sc_tag;

    out_scale #(.RAW_W(RAW_W), .OUT_W(OUT_W), .TAG_W(TAG_W), .SH_W(SH_W), .OB_W(OB_W)) scale (
        .clk(clk), .in_v(x3_v && x3_ok && x3_last), .in_raw(x3_tot),
        .in_tag({x3_nz, x3_neg, x3_tag}),
        .shift(c_shift), .rounding(c_round), .out_bits(c_out_bits),
        .out_v(sc_v), .out_word(sc_word), .out_tag(sc_tag)
    );

    // ------------------------------------------------------------------
    // Correlation RAM: K * 2^CA_W words {nz, neg, out}, address {channel, jj}
    // ------------------------------------------------------------------
    reg  [K_W+CA_W-1:0] cr_raddr;
    wire [CW-1:0]       cr_rdata;
    sdp_ram #(.WIDTH(CW), .DEPTH(((K > 1) ? K : 2) << CA_W)) corr_ram (
        .clk(clk), .we(sc_v), .waddr(sc_tag[K_W+CA_W-1:0]),
        .wdata({sc_tag[TAG_W-1:K_W+CA_W], sc_word}),
        .raddr(cr_raddr), .rdata(cr_rdata)
    );

    // ------------------------------------------------------------------
    // Post-processing (per channel): rx_post, shared with rx_chain
    // ------------------------------------------------------------------
    // The drain is watched through registers: fl_str (the stream pipeline) and fl_ser
    // (the serializer), each set beside the stages it watches, say that all of them were
    // empty in the previous clock; post_go is itself a register, set one clock ahead. So
    // the valid bits spread over the die reach rx_post's state machine through two
    // registered clocks, and post_go is high in the 5th clock of an empty pipeline as
    // before: the stages drain in P_FLUSH and stay empty (nothing enters them there),
    // and fl_str is low in P_FLUSH's first clock (v0 is high in the last P_STREAM clock).
    reg  [K_W-1:0]    pk_ch;
    reg  [2:0]        wait_cnt;
    reg               fl_str, fl_ser, post_go;
    wire              flushed = fl_str && fl_ser;
    always @(posedge clk) begin
        fl_str <= !v0 && !v1 && !vr && !vq && !v2 && !latch_v;
        fl_ser <= !ser_busy && !x0_v && !x1_v && !x2_v && !x3_v;
        if (rst) begin
            fl_str <= 1'b0;
            fl_ser <= 1'b0;
        end
    end
    wire              post_last, post_last_nx;
    wire [CA_W-1:0]   post_raddr;

    rx_post #(.MAX_G(MAX_G), .MAX_P(MAX_P), .MAX_UID(MAX_UID), .NGHOST(NGHOST),
              .OUT_W(OUT_W), .LAG_W(LAG_W), .G_W(G_W), .CA_W(CA_W), .P_W(P_W), .OB_W(OB_W),
              .CW(CW), .SUM_W(SUM_W), .SQ_W(SQ_W)) post (
        .clk(clk), .rst(rst), .go(post_go), .more(pk_ch != K_LAST),
        .ns(ns), .gate_start(c_gate_start), .gate_len(c_gate_len), .excl(c_excl),
        .gh_start(c_gh_start), .gh_len(c_gh_len), .peaks(c_peaks), .uid(c_uid),
        .uid_mask(uid_mask), .out_bits(c_out_bits),
        .raddr(post_raddr), .rdata(cr_rdata), .last(post_last), .last_nx(post_last_nx),
        .corr_valid(corr_valid), .corr_index(corr_index), .corr_data(corr_data),
        .res_valid(res_valid), .res_found(res_found), .res_lag(res_lag),
        .res_index(res_index), .res_peak(res_peak), .res_neg(res_neg), .res_nz(res_nz),
        .res_nb_lo(res_nb_lo), .res_nb_hi(res_nb_hi), .res_noise_count(res_noise_count),
        .res_noise_sum(res_noise_sum), .res_noise_sumsq(res_noise_sumsq),
        .res_uid_observed(res_uid_observed), .res_uid_match(res_uid_match),
        .res_saturated(res_saturated)
    );

    always @(*)
        cr_raddr = {pk_ch, post_raddr};

    // ------------------------------------------------------------------
    // Sticky status (cleared by clear_err; an event in the same clock wins)
    // ------------------------------------------------------------------
    always @(posedge clk) begin
        if (clear_err) begin
            err_overrun <= 1'b0;
            err_refused <= 1'b0;
        end
        if (s_refused)
            err_refused <= 1'b1;
        if (latch_v && ser_busy)
            err_overrun <= 1'b1;        // the lanes outran the serializer
        if (rst) begin
            err_overrun <= 1'b0;
            err_refused <= 1'b0;
        end
    end

    // ------------------------------------------------------------------
    // lo = q_lo * S + s_lo: restoring division, started in T_INIT2
    // ------------------------------------------------------------------
    always @(posedge clk) begin
        if (tstate == T_INIT2) begin
            div_run  <= 1'b1;
            div_done <= 1'b0;
            div_i    <= LAG_W[DIV_W-1:0];
            div_q    <= {LAG_W{1'b0}};
            div_r    <= {(S_W+1){1'b0}};
        end
        if (div_run) begin
            div_r <= div_ge ? div_d[S_W:0] : div_t[S_W:0];
            div_q <= {div_q[LAG_W-2:0], div_ge};
            div_i <= div_i - 1'b1;
            if (div_i == {{(DIV_W-1){1'b0}}, 1'b1}) begin
                div_run  <= 1'b0;
                div_done <= 1'b1;
            end
        end
        if (rst) begin
            div_run  <= 1'b0;
            div_done <= 1'b0;
        end
    end

    // ------------------------------------------------------------------
    // Averaging read-modify-write pipeline: read, RAM output register, add and write
    // ------------------------------------------------------------------
    // Only the valid bits (r_v, rr_v, w_v) follow a_take; the data registers load every
    // clock and are read only while their valid bit is high, so a_take (a net from
    // s_ready, across the die) drives no clock enable of the P_IN * ADC_W sample bits.
    always @(posedge clk) begin
        r_v      <= a_take;
        r_buf    <= acc_buf;
        r_bank   <= a_s;
        r_addr   <= a_addr;
        r_first  <= (a_r == {R_W{1'b0}});
        r_x      <= s_data;
        rr_v     <= r_v;
        rr_buf   <= r_buf;
        rr_bank  <= r_bank;
        rr_addr  <= r_addr;
        rr_first <= r_first;
        rr_x     <= r_x;
        w_v      <= rr_v;
        w_buf    <= rr_buf;
        w_bank   <= rr_bank;
        w_addr   <= rr_addr;
        w_first  <= rr_first;
        w_x      <= rr_x;
        for (si = 0; si < MAX_S; si = si + 1)
            w_old[si*AVG_W +: AVG_W] <= rr_buf ? rd[MAX_S + si] : rd[si];
        if (rst) begin
            r_v  <= 1'b0;
            rr_v <= 1'b0;
            w_v  <= 1'b0;
        end
    end

    // ------------------------------------------------------------------
    // Correlation pipeline: issue, RAM, RAM output register, RAM words, box sum, lanes;
    // a stream's end latches the lane values for the serializer
    // ------------------------------------------------------------------
    always @(posedge clk) begin
        v0      <= 1'b0;
        v1      <= 1'b0;
        vr      <= 1'b0;
        vq      <= 1'b0;
        v2      <= 1'b0;
        latch_v <= 1'b0;
        if (pstate == P_STREAM) begin
            v0    <= 1'b1;
            f0    <= (st_k == {KST_W{1'b0}});
            a0    <= (st_k < {{(KST_W-MAX_DEG){1'b0}}, nn});
            p0    <= st_p;
            code0 <= chip;
            gend0 <= st_end;
            glast0 <= st_lastp;
            gjj0  <= g_jj;
            for (sj = 0; sj < MAX_S; sj = sj + 1)
                addr0[sj*ADDR_W +: ADDR_W] <= corr_addr[sj];
        end
        if (v0) begin
            v1    <= 1'b1;
            f1    <= f0;
            a1    <= a0;
            p1    <= p0;
            code1 <= code0;
            gend1 <= gend0;
            glast1 <= glast0;
            gjj1  <= gjj0;
        end
        if (v1) begin
            vr    <= 1'b1;
            fr    <= f1;
            ar    <= a1;
            pr    <= p1;
            coder <= code1;
            gendr <= gend1;
            glastr <= glast1;
            gjjr  <= gjj1;
        end
        if (vr) begin
            vq    <= 1'b1;
            fq    <= fr;
            aq    <= ar;
            pq    <= pr;
            codeq <= coder;
            gendq <= gendr;
            glastq <= glastr;
            gjjq  <= gjjr;
            for (sj = 0; sj < MAX_S; sj = sj + 1)
                rdq[sj*AVG_W +: AVG_W] <= rd[(proc_buf ? MAX_S : 0) + sj];
        end
        if (vq) begin
            v2    <= 1'b1;
            f2    <= fq;
            a2    <= aq;
            p2    <= pq;
            code2 <= codeq;
            gend2 <= gendq;
            glast2 <= glastq;
            gjj2  <= gjjq;
            box2  <= box1;
        end
        if (v2) begin
            if (gend2) begin
                latch_v    <= 1'b1;
                latch_jj   <= gjj2;
                latch_p    <= p2;
                latch_last <= glast2;
            end
        end
        if (rst) begin
            v0      <= 1'b0;
            v1      <= 1'b0;
            vr      <= 1'b0;
            vq      <= 1'b0;
            v2      <= 1'b0;
            latch_v <= 1'b0;
        end
    end

    // ------------------------------------------------------------------
    // Serializer: walks the hold chain one lane a clock after each stream's end
    // ------------------------------------------------------------------
    always @(posedge clk) begin
        if (ln_clr)
            ln_fst <= 1'b1;             // the first stream after start: no previous value
        if (latch_v) begin
            ser_busy <= 1'b1;
            ser_fst  <= ln_fst;
            ln_fst   <= 1'b0;
            ser_p    <= latch_p;
            ser_last <= latch_last;
            ser_idx  <= {KL_W{1'b0}};
            ser_k    <= {K_W{1'b0}};
            ser_j    <= 0;
            ser_jj   <= {{(S_W+1){1'b0}}, latch_jj};
            ser_base <= latch_jj;
        end else if (ser_busy) begin
            ser_idx <= ser_idx + 1'b1;
            if (ser_j == L_LAST) begin
                ser_j  <= 0;
                ser_jj <= {{(S_W+1){1'b0}}, ser_base};
                ser_k  <= ser_k + 1'b1;
                if (ser_k == K_LAST)
                    ser_busy <= 1'b0;
            end else begin
                ser_j  <= ser_j + 1'b1;
                ser_jj <= ser_jj + {{(JJ_W+1){1'b0}}, c_spc};
            end
        end
        if (rst)
            ser_busy <= 1'b0;
    end

    // ------------------------------------------------------------------
    // ADC handshake: s_ready is a register, computed one clock ahead from the
    // next values of what it reads (tstate, full, acc_buf, cols_in, c_free,
    // c_columns; every writer of those is here), so in every clock it equals
    //   (tstate == T_RUN) && !full[acc_buf] && (c_free || cols_in != c_columns).
    // The averaging counters keep registered "last" flags (a_X_last: a_X is at its
    // wrap value, recomputed at T_INIT2 from the configuration latched at start),
    // so a column's end (a_wrap) is one AND of a_take and four flags; a_open (a column
    // is open) and cols_in1 = cols_in + 1 keep adders and the counters' OR off the path
    // from a_take, which reaches s_ready and c_columns only as a select (more_nx).
    // ------------------------------------------------------------------
    // p_free (proc_buf processed: the last channel's last post-processing clock) is a
    // register set one clock ahead from rx_post's last_nx; pstate and pk_ch hold until
    // `last`, so it equals (pstate == P_POST) && post_last && (pk_ch == K_LAST) every clock
    // and keeps the channel counter's compare off the path into s_ready's next value.
    reg  p_free;
    always @(posedge clk)
        p_free <= !rst && (pstate == P_POST) && post_last_nx && (pk_ch == K_LAST);
    wire t_init = (tstate == T_INIT2);
    wire t_end  = !c_free && cols_out == c_columns;                // T_RUN: the last column is out
    wire a_wrap = a_take && a_s_last && a_c_last && a_p_last && a_r_last;  // a column's last take
    wire t_load = (tstate == T_IDLE) && start;
    wire s_stop = stop && tstate != T_IDLE;   // take the column begun (if any) to its end, no more
    wire [S_W-1:0]     a_s_nx = (t_init || a_s_last) ? {S_W{1'b0}} : a_s + P_STEP;
    wire [MAX_DEG-1:0] a_c_nx = (t_init || a_c_last) ? {MAX_DEG{1'b0}} : a_c + 1'b1;
    wire [UID_W-1:0]   a_p_nx = (t_init || a_p_last) ? {UID_W{1'b0}} : a_p + 1'b1;
    wire [R_W-1:0]     a_r_nx = (t_init || a_r_last) ? {R_W{1'b0}} : a_r + 1'b1;

    wire [1:0] tstate_nx = rst ? T_IDLE
                         : (tstate == T_IDLE) ? (start ? T_INIT1 : T_IDLE)
                         : (tstate == T_INIT1) ? T_INIT2
                         : (tstate == T_INIT2 || !t_end) ? T_RUN : T_IDLE;
    wire [1:0] full_set  = {a_wrap && acc_buf, a_wrap && !acc_buf};    // full[acc_buf] <= 1
    wire [1:0] full_clr  = {p_free && proc_buf, p_free && !proc_buf};  // full[proc_buf] <= 0
    wire [1:0] full_nx   = (rst || t_init) ? 2'b00 : (full | full_set) & ~full_clr;
    wire       acc_buf_nx = !t_init && (acc_buf ^ a_wrap);
    wire [COL_W-1:0] cols_in1 = cols_in + 1'b1;      // from registers: ready before a_take
    wire [COL_W-1:0] cols_in_nx = t_init ? {COL_W{1'b0}} : a_wrap ? cols_in1 : cols_in;
    wire       a_open_nx = !t_init && (a_take ? !a_wrap : a_open);
    wire       c_free_nx = s_stop ? 1'b0 : t_load ? (cfg_columns == {COL_W{1'b0}}) : c_free;
    // stop: the columns begun, this clock's take included (a_take selects, adds nothing)
    wire [COL_W-1:0] c_columns_nx = t_load ? cfg_columns : !s_stop ? c_columns
                                  : (tstate == T_RUN) ? ((a_take || a_open) ? cols_in1 : cols_in)
                                  : {COL_W{1'b0}};
    // More columns to take after this clock, (c_free_nx || cols_in_nx != c_columns_nx)
    // wherever tstate_nx == T_RUN, with a_take only behind selects: after a stop, exactly
    // while a column stays open; otherwise the count compared from registers.
    wire       more_nx = s_stop ? (tstate == T_RUN) && a_open_nx
                       : c_free || (t_init ? c_columns != {COL_W{1'b0}}
                                    : a_wrap ? cols_in1 != c_columns : cols_in != c_columns);

    always @(posedge clk) begin
        tstate    <= tstate_nx;
        full      <= full_nx;
        acc_buf   <= acc_buf_nx;
        cols_in   <= cols_in_nx;
        c_free    <= c_free_nx;
        c_columns <= c_columns_nx;
        a_open    <= a_open_nx;
        s_ready   <= (tstate_nx == T_RUN) && !full_nx[acc_buf_nx] && more_nx;
    end

    // ------------------------------------------------------------------
    // Control: run and column count, averaging counters and buffers, processing engine
    // ------------------------------------------------------------------
    always @(posedge clk) begin
        done       <= 1'b0;
        col_start  <= 1'b0;
        ln_clr     <= 1'b0;

        // ---- run: configuration (cfg_latch, above) and column count; tstate is
        //      written by the ADC handshake block (above) ----
        case (tstate)
        T_INIT1: begin
            nn     <= n_chips[MAX_DEG-1:0];
            ns     <= ns_full[LAG_W-1:0];
        end
        T_INIT2: begin
            lo          <= (c_gate_start == {LAG_W{1'b0}}) ? ns - 1'b1 : c_gate_start - 1'b1;
            k_end       <= {{(KST_W-MAX_DEG){1'b0}}, nn} + L[KST_W-1:0]
                           - {{(KST_W-2){1'b0}}, 2'd3};
            proc_buf    <= 1'b0;
            cols_out    <= {COL_W{1'b0}};
            ln_clr      <= 1'b1;
        end
        T_RUN: if (t_end) done <= 1'b1;
        default: ;
        endcase

        // ---- averaging counters: bank, chip, period, repetition (0 at T_INIT2) ----
        if (t_init || a_take) begin
            a_s      <= a_s_nx;
            a_s_last <= (a_s_nx == c_spc - P_STEP);
        end
        if (t_init || (a_take && a_s_last)) begin
            a_c      <= a_c_nx;
            a_c_last <= (a_c_nx == nn - 1'b1);
        end
        if (t_init || (a_take && a_s_last && a_c_last)) begin
            a_p      <= a_p_nx;
            a_base   <= (t_init || a_p_last) ? {ADDR_W{1'b0}}
                                             : a_base + {{(ADDR_W-MAX_DEG){1'b0}}, nn};
            a_p_last <= (a_p_nx == c_uid_bits - 1'b1);
        end
        if (t_init || (a_take && a_s_last && a_c_last && a_p_last)) begin
            a_r      <= a_r_nx;
            a_r_last <= (a_r_nx == c_averages - 1'b1);
        end

        // ---- processing engine: phases, groups, UID periods, stream steps; rx_post ----
        case (pstate)
        P_IDLE: if (tstate == T_RUN && full[proc_buf] && div_done) begin
            proc_on     <= 1'b1;
            col_start   <= 1'b1;
            pstate      <= P_START;
        end
        P_START: begin
            // first phase: lag lo = q_lo * S + s_lo
            ph      <= {S_W{1'b0}};
            ph_q    <= div_q[MAX_DEG-1:0];
            ph_s    <= div_r[S_W-1:0];
            g_q     <= div_q[MAX_DEG-1:0];
            g_jj    <= {JJ_W{1'b0}};
            pstate  <= P_SETUP;
        end
        P_SETUP: begin
            st_end  <= 1'b0;
            st_p    <= {UID_W{1'b0}};
            st_base <= {ADDR_W{1'b0}};
            st_k    <= {KST_W{1'b0}};
            st_t    <= g_q;
            pstate  <= P_STREAM;
        end
        P_STREAM: begin
            st_end <= st_end_nx;
            if (!st_end) begin
                st_k <= st_k + 1'b1;
                st_t <= st_t1;
            end else begin
                st_k <= {KST_W{1'b0}};
                if (!st_lastp) begin
                    st_p    <= st_p + 1'b1;
                    st_base <= st_base + {{(ADDR_W-MAX_DEG){1'b0}}, nn};
                    st_t    <= g_q;
                end else begin
                    st_p    <= {UID_W{1'b0}};
                    st_base <= {ADDR_W{1'b0}};
                    if (g_more) begin
                        g_q  <= g_q_nx;
                        st_t <= g_q_nx;
                        g_jj <= g_jj_nx[JJ_W-1:0];
                    end else if (ph_more) begin
                        ph   <= ph_nx;
                        ph_s <= ph_s_wrap ? {S_W{1'b0}} : ph_s + 1'b1;
                        ph_q <= ph_s_wrap ? chip_inc(ph_q, nn) : ph_q;
                        g_q  <= ph_s_wrap ? chip_inc(ph_q, nn) : ph_q;
                        st_t <= ph_s_wrap ? chip_inc(ph_q, nn) : ph_q;
                        g_jj <= {{(JJ_W-S_W){1'b0}}, ph_nx};
                    end else begin
                        pstate   <= P_FLUSH;
                        wait_cnt <= 3'd0;
                    end
                end
            end
        end
        P_FLUSH: begin
            // stages 1, 2, latch, serializer, out_scale (3) and the RAM write
            if (flushed)
                wait_cnt <= wait_cnt + 1'b1;
            if (post_go) begin
                pk_ch  <= {K_W{1'b0}};
                pstate <= P_POST;
            end
        end
        P_POST: if (post_last) begin
            res_channel <= pk_ch;
            if (pk_ch == K_LAST) begin      // p_free: full[proc_buf] is cleared above
                cols_out       <= cols_out + 1'b1;
                proc_buf       <= ~proc_buf;
                proc_on        <= 1'b0;
                pstate         <= P_IDLE;
            end else begin
                pk_ch <= pk_ch + 1'b1;
            end
        end
        default: pstate <= P_IDLE;
        endcase

        post_go      <= (pstate == P_FLUSH) && flushed && (wait_cnt == 3'd2);
        corr_channel <= pk_ch;

        if (rst) begin
            pstate      <= P_IDLE;
            done        <= 1'b0;
            ln_clr      <= 1'b0;
            proc_on     <= 1'b0;
            post_go     <= 1'b0;
        end
    end

    wire unused_ok = &{1'b0, lo_sh[LAG_W-1:1], x1_d[PER_W-1], g_q_dif[MAX_DEG], div_d[S_W+1],
                       ns_full[MAX_DEG+S_W:LAG_W], n_chips[MAX_DEG],
                       g_jj_nx[JJ_W+S_W:JJ_W], ser_jj[JJ_W+S_W:CA_W], g_q_sum[MAX_DEG],
                       div_q};
endmodule

`default_nettype wire
