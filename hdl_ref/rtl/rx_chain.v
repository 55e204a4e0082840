// rx_chain -- one receive channel of the CDMA LiDAR: coherent averaging,
// UID despreading, lag-gated circular correlation against the channel's Gold
// code, output scaling, peak and noise-floor detection. Bit for bit equal to
// firmware_model.receiver.reference for one channel (K = 1); the formats are
// those of docs/firmware.md.
//
// Definitions (NS = N * S samples per code period, n = uid_bits):
//   avg[p][i]  = sum_r sample[r, p, i]                       (no division)
//   per_p(lag) = sum_i ref[i] * avg[p][(i + lag) mod NS]      ref[i] = +1/-1 for chip bit 0/1
//   raw(lag)   = sum_p (-1)^uid[p] * per_p(lag)               (UID despreading)
//   out(lag)   = sat_out_bits(round(raw / 2^out_shift))
//   lag_j      = (gate_start + j) mod NS, j = 0..gate_len-1
//
// Architecture: sequential, one add/subtract per clock (the reference is
// +-1, so the "multiply" of the MAC is a sign). Phases:
//   ACCUM  accept averages * n * NS samples, one per clock (s_valid/s_ready),
//          read-modify-write into the averaging RAM (n * NS words);
//   CORR   for the gate_len + 2 lags gate_start-1 .. gate_start+gate_len
//          (the two extra lags are the peak's possible neighbours) stream the
//          averaging RAM against the Gold generator: n * NS clocks per lag;
//          per lag the out word (out_scale: rounded, saturated, the module
//          rx_top uses) and the signs of the n per-period sums go to the
//          correlation RAM;
//   POST   rx_post (shared with rx_top): `peaks` passes over the correlation
//          RAM, the first peak's two neighbours, one noise pass (count, sum,
//          sum of squares) that also streams the gate words on corr_*.
// Latency (clock edges, checked by the co-simulation for every case):
//   start -> first sample taken:   3
//   last sample taken -> done:     (gate_len + 2) * n * NS + peaks * (gate_len + 4)
//                                  + gate_len + 14
// Throughput while averaging: one sample per clock (docs/hdl.md).
//
// All configuration inputs are sampled at `start` (one-clock pulse in IDLE)
// and must be valid then; the result outputs are held from `done` until the
// next `start`.
`default_nettype none

module rx_chain #(
    parameter integer MAX_DEG   = 11,   // largest code degree m (N = 2^m - 1 chips)
    parameter integer MAX_S     = 4,    // largest samples per chip S
    parameter integer MAX_UID   = 4,    // largest uid_bits n (code periods per frame)
    parameter integer MAX_R     = 16,   // largest averages R (frames)
    parameter integer MAX_G     = 64,   // largest gate_len (lags)
    parameter integer MAX_P     = 1,    // largest number of reported peaks
    parameter integer NGHOST    = 2,    // ghost-window slots (length 0 = unused)
    parameter integer ADC_W     = 16,   // width of s_data (adc_bits <= ADC_W, sign-extended)
    parameter integer OUT_W     = 32,   // width of out words (out_bits <= OUT_W)
    // ---- derived, do not override ----
    parameter integer DEG_W     = $clog2(MAX_DEG + 1),
    parameter integer MAX_NS    = ((1 << MAX_DEG) - 1) * MAX_S,
    parameter integer LAG_W     = $clog2(MAX_NS + 1),       // lags 0..NS-1 and lengths 0..NS
    parameter integer S_W       = $clog2(MAX_S + 1),
    parameter integer UID_W     = $clog2(MAX_UID + 1),
    parameter integer R_W       = $clog2(MAX_R + 1),
    parameter integer G_W       = $clog2(MAX_G + 1),
    parameter integer P_W       = $clog2(MAX_P + 1),
    parameter integer SH_W      = 6,                          // out_shift 0..63
    parameter integer OB_W      = 6,                          // out_bits 1..OUT_W
    parameter integer CNT_W     = G_W,                        // noise_count
    parameter integer SUM_W     = OUT_W + G_W,                // noise_sum
    parameter integer SQ_W      = 2 * OUT_W + G_W             // noise_sumsq
) (
    input  wire                         clk,
    input  wire                         rst,            // synchronous, active high

    // ---- configuration, sampled at start ----
    input  wire                         start,
    input  wire [DEG_W-1:0]             cfg_degree,     // m
    input  wire [MAX_DEG-1:0]           cfg_taps_u,     // bit e-1 per exponent e of poly_u
    input  wire [MAX_DEG-1:0]           cfg_taps_v,
    input  wire [MAX_DEG-1:0]           cfg_seed_u,     // from gold_seeds(), stage 1 = bit 0
    input  wire [MAX_DEG-1:0]           cfg_seed_v,
    input  wire [S_W-1:0]               cfg_spc,        // samples_per_chip S, 1..MAX_S
    input  wire [R_W-1:0]               cfg_averages,   // R, 1..MAX_R
    input  wire [UID_W-1:0]             cfg_uid_bits,   // n, 1..MAX_UID
    input  wire [MAX_UID-1:0]           cfg_uid,        // bit p = polarity of period p
    input  wire [LAG_W-1:0]             cfg_gate_start, // 0..NS-1 samples
    input  wire [G_W-1:0]               cfg_gate_len,   // 1..MAX_G lags
    input  wire [G_W-1:0]               cfg_peak_exclude, // W, lags
    input  wire [NGHOST*LAG_W-1:0]      cfg_ghost_start,  // slot w at [w*LAG_W +: LAG_W]
    input  wire [NGHOST*LAG_W-1:0]      cfg_ghost_len,    // 0 = slot unused
    input  wire [SH_W-1:0]              cfg_out_shift,
    input  wire [1:0]                   cfg_rounding,   // 0 truncate, 1 half_up, 2 convergent
    input  wire [OB_W-1:0]              cfg_out_bits,   // 2..OUT_W
    input  wire [P_W-1:0]               cfg_peaks,      // 1..MAX_P

    // ---- ADC samples: frame r, then period p, then sample i ----
    input  wire                         s_valid,
    input  wire signed [ADC_W-1:0]      s_data,
    output wire                         s_ready,

    // ---- correlation stream: one word per gate lag, j = 0..gate_len-1 ----
    output wire                         corr_valid,
    output wire [G_W-1:0]               corr_index,     // j
    output wire signed [OUT_W-1:0]      corr_data,      // out(lag_j)

    // ---- results, valid from done until the next start ----
    output wire                         busy,
    output wire                         done,           // one-clock pulse
    output wire [MAX_P-1:0]             res_found,      // peak q exists
    output wire [MAX_P*LAG_W-1:0]       res_lag,        // peak q lag (samples) at [q*LAG_W]
    output wire [MAX_P*G_W-1:0]         res_index,      // peak q gate index j
    output wire [MAX_P*OUT_W-1:0]       res_peak,       // peak q out value (signed)
    output wire [MAX_P*MAX_UID-1:0]     res_neg,        // per-period sum c_p < 0 at peak q
    output wire [MAX_P*MAX_UID-1:0]     res_nz,         // per-period sum != 0 at peak q
    output wire signed [OUT_W-1:0]      res_nb_lo,      // out at peak lag - 1
    output wire signed [OUT_W-1:0]      res_nb_hi,      // out at peak lag + 1
    output wire [CNT_W-1:0]             res_noise_count,
    output wire signed [SUM_W-1:0]      res_noise_sum,
    output wire [SQ_W-1:0]              res_noise_sumsq,
    output wire [MAX_UID-1:0]           res_uid_observed,
    output wire                         res_uid_match,
    output wire                         res_saturated   // peak 0's out word at a rail
);
    // ------------------------------------------------------------------
    // Widths
    // ------------------------------------------------------------------
    generate   // a derived parameter overridden by mistake stops the elaboration
        if (DEG_W != $clog2(MAX_DEG + 1) || MAX_NS != ((1 << MAX_DEG) - 1) * MAX_S
            || LAG_W != $clog2(MAX_NS + 1) || S_W != $clog2(MAX_S + 1)
            || UID_W != $clog2(MAX_UID + 1) || R_W != $clog2(MAX_R + 1)
            || G_W != $clog2(MAX_G + 1) || P_W != $clog2(MAX_P + 1)
            || CNT_W != G_W || SUM_W != OUT_W + G_W || SQ_W != 2 * OUT_W + G_W)
        begin : g_derived_width_mismatch
            rx_chain_derived_width_mismatch bad ();
        end
    endgenerate
    localparam integer AVG_W  = ADC_W + $clog2(MAX_R);              // sum of R samples
    localparam integer PER_W  = AVG_W + $clog2(MAX_NS) + 1;         // per-period correlation
    localparam integer RAW_W  = PER_W + $clog2(MAX_UID);            // despread correlation
    localparam integer ADDR_W = $clog2(MAX_UID * MAX_NS);
    localparam integer JJ_W   = G_W + 1;                             // extended gate index
    localparam integer CA_W   = $clog2(MAX_G + 2);                   // correlation RAM address
    localparam integer CW     = OUT_W + 2 * MAX_UID;                 // correlation RAM word

    localparam [2:0] S_IDLE  = 3'd0, S_INIT1 = 3'd1, S_INIT2 = 3'd2, S_ACCUM = 3'd3,
                     S_DRAIN = 3'd4, S_CORR  = 3'd5, S_CWAIT = 3'd6, S_POST  = 3'd7;

    reg [2:0] state;

    // ------------------------------------------------------------------
    // Configuration registers
    // ------------------------------------------------------------------
    wire [DEG_W-1:0]        c_degree;
    wire [MAX_DEG-1:0]      c_taps_u, c_taps_v, c_seed_u, c_seed_v;
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
    cfg_latch #(.MAX_DEG(MAX_DEG), .MAX_UID(MAX_UID), .NGHOST(NGHOST), .SEED_W(MAX_DEG),
                .DEG_W(DEG_W), .S_W(S_W), .R_W(R_W), .UID_W(UID_W), .LAG_W(LAG_W), .G_W(G_W),
                .P_W(P_W), .SH_W(SH_W), .OB_W(OB_W)) cfg (
        .clk(clk), .load(state == S_IDLE && start),
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

    reg [LAG_W-1:0]        ns;          // N * S
    reg [ADDR_W:0]         nns;         // n * N * S
    wire [MAX_DEG:0]       n_chips = ({{MAX_DEG{1'b0}}, 1'b1} << c_degree) - {{MAX_DEG{1'b0}}, 1'b1};
    wire [MAX_DEG+S_W:0]   ns_full = n_chips * {{MAX_DEG{1'b0}}, c_spc};
    wire [MAX_UID-1:0]     uid_mask = ({{(MAX_UID-1){1'b0}}, 1'b1} << c_uid_bits)
                                      - {{(MAX_UID-1){1'b0}}, 1'b1};

    // Modular helpers on lags 0..NS-1.
    function [LAG_W-1:0] lag_inc(input [LAG_W-1:0] x, input [LAG_W-1:0] m);
        lag_inc = (x == m - 1'b1) ? {LAG_W{1'b0}} : x + 1'b1;
    endfunction

    // ------------------------------------------------------------------
    // Averaging RAM (n * NS words of AVG_W bits)
    // ------------------------------------------------------------------
    reg  [ADDR_W-1:0] ram_raddr;
    wire [AVG_W-1:0]  ram_rdata;
    reg               ram_we;
    reg  [ADDR_W-1:0] ram_waddr;
    reg  [AVG_W-1:0]  ram_wdata;

    sdp_ram #(.WIDTH(AVG_W), .DEPTH(MAX_UID * MAX_NS)) avg_ram (
        .clk(clk), .we(ram_we), .waddr(ram_waddr), .wdata(ram_wdata),
        .raddr(ram_raddr), .rdata(ram_rdata)
    );

    // ---- ACCUM: frame counter and address; one sample per clock ----
    reg  [ADDR_W:0]   a_addr;       // 0 .. n*NS-1 within a frame
    reg  [R_W-1:0]    a_frame;      // 0 .. R-1
    wire              a_take = (state == S_ACCUM) && s_valid;
    reg               w_v, w_first;
    reg  [ADDR_W-1:0] w_addr;
    reg  signed [ADC_W-1:0] w_x;

    assign s_ready = (state == S_ACCUM);
    assign busy    = (state != S_IDLE);

    wire signed [AVG_W-1:0] w_x_ext = {{(AVG_W-ADC_W+1){w_x[ADC_W-1]}}, w_x[ADC_W-2:0]};

    always @(*) begin
        ram_we    = w_v;
        ram_waddr = w_addr;
        ram_wdata = w_first ? w_x_ext : ram_rdata + w_x_ext;
    end

    // ------------------------------------------------------------------
    // Gold generator for the reference (no UID polarity: despreading is
    // applied to the per-period sums)
    // ------------------------------------------------------------------
    reg               gen_load, gen_en;
    wire              chip_u, chip_v;
    wire [MAX_DEG-1:0] st_u, st_v;

    lfsr_fib #(.MAX_DEG(MAX_DEG)) ref_u (
        .clk(clk), .load(gen_load), .en(gen_en), .seed(c_seed_u), .taps(c_taps_u),
        .degree(c_degree), .out(chip_u), .state(st_u)
    );
    lfsr_fib #(.MAX_DEG(MAX_DEG)) ref_v (
        .clk(clk), .load(gen_load), .en(gen_en), .seed(c_seed_v), .taps(c_taps_v),
        .degree(c_degree), .out(chip_v), .state(st_v)
    );
    wire ref_chip = chip_u ^ chip_v;

    // ------------------------------------------------------------------
    // CORR: issue counters (stage 0)
    // ------------------------------------------------------------------
    reg  [LAG_W-1:0]  k_i;          // sample index in the period, 0..NS-1
    reg  [S_W-1:0]    k_s;          // sample within the chip, 0..S-1
    reg  [UID_W-1:0]  k_p;          // period, 0..n-1
    reg  [ADDR_W:0]   k_base;       // k_p * NS
    reg  [LAG_W-1:0]  k_a;          // (lag + k_i) mod NS
    reg  [LAG_W-1:0]  k_lag;        // current lag
    reg  [JJ_W-1:0]   k_jj;         // extended gate index 0..G+1 (lag_j = lag of jj-1)
    wire              k_last_i = (k_i == ns - 1'b1);
    wire              k_last_p = (k_p == c_uid_bits - 1'b1);
    wire [JJ_W-1:0]   jj_last  = {1'b0, c_gate_len} + 1'b1;
    wire [LAG_W-1:0]  k_lag_nx = lag_inc(k_lag, ns);
    wire [ADDR_W:0]   k_addr   = k_base + {{(ADDR_W+1-LAG_W){1'b0}}, k_a};

    // stage 1 (RAM data valid)
    reg               c1_v, c1_chip, c1_first, c1_last, c1_lastp;
    reg  [UID_W-1:0]  c1_p;
    reg  [JJ_W-1:0]   c1_jj;
    reg  signed [PER_W-1:0] per_acc;
    reg  signed [RAW_W-1:0] tot_acc;
    reg  [MAX_UID-1:0] sg_neg, sg_nz;

    wire signed [PER_W-1:0] c1_x    = {{(PER_W-AVG_W){ram_rdata[AVG_W-1]}}, ram_rdata};
    wire signed [PER_W-1:0] c1_term = c1_chip ? -c1_x : c1_x;
    wire signed [PER_W-1:0] per_sum = (c1_first ? {PER_W{1'b0}} : per_acc) + c1_term;
    wire signed [RAW_W-1:0] per_ext = {{(RAW_W-PER_W+1){per_sum[PER_W-1]}}, per_sum[PER_W-2:0]};
    wire [MAX_UID-1:0]      p_sel   = {{(MAX_UID-1){1'b0}}, 1'b1} << c1_p;
    wire                    p_flip  = |(c_uid & p_sel);
    wire signed [RAW_W-1:0] tot_sum = ((c1_p == {UID_W{1'b0}}) ? {RAW_W{1'b0}} : tot_acc)
                                      + (p_flip ? -per_ext : per_ext);
    wire [MAX_UID-1:0]      neg_nx  = ((c1_p == {UID_W{1'b0}}) ? {MAX_UID{1'b0}} : sg_neg)
                                      | (per_sum[PER_W-1] ? p_sel : {MAX_UID{1'b0}});
    wire [MAX_UID-1:0]      nz_nx   = ((c1_p == {UID_W{1'b0}}) ? {MAX_UID{1'b0}} : sg_nz)
                                      | ((per_sum != {PER_W{1'b0}}) ? p_sel : {MAX_UID{1'b0}});

    // stage 2 (raw correlation of one lag) -> out_scale (round, saturate: 3 clocks, the
    // module rx_top uses) -> correlation RAM write
    reg               c2_v;
    reg  [JJ_W-1:0]   c2_jj;
    reg  signed [RAW_W-1:0] c2_raw;
    reg  [MAX_UID-1:0] c2_neg, c2_nz;

    localparam integer TAG_W = 2 * MAX_UID + JJ_W;
    wire                    c3_v;
    wire signed [OUT_W-1:0] c3_out;
    wire [TAG_W-1:0]        c3_tag;
    out_scale #(.RAW_W(RAW_W), .OUT_W(OUT_W), .TAG_W(TAG_W), .SH_W(SH_W), .OB_W(OB_W)) scale (
        .clk(clk), .in_v(c2_v), .in_raw(c2_raw), .in_tag({c2_nz, c2_neg, c2_jj}),
        .shift(c_shift), .rounding(c_round), .out_bits(c_out_bits),
        .out_v(c3_v), .out_word(c3_out), .out_tag(c3_tag)
    );
    wire [JJ_W-1:0]   c3_jj   = c3_tag[JJ_W-1:0];
    wire [CW-1:0]     c3_word = {c3_tag[TAG_W-1:JJ_W], c3_out};

    // ------------------------------------------------------------------
    // Correlation RAM: word = {nz[MAX_UID], neg[MAX_UID], out[OUT_W]},
    // address jj = j + 1 (jj 0 and G+1 are the neighbour lags)
    // ------------------------------------------------------------------
    wire [CA_W-1:0]   cr_raddr;
    wire [CW-1:0]     cr_rdata;

    sdp_ram #(.WIDTH(CW), .DEPTH(MAX_G + 2)) corr_ram (
        .clk(clk), .we(c3_v), .waddr(c3_jj[CA_W-1:0]), .wdata(c3_word),
        .raddr(cr_raddr), .rdata(cr_rdata)
    );

    // ------------------------------------------------------------------
    // Post-processing: peaks, neighbours, noise floor, UID (rx_post, shared with rx_top)
    // ------------------------------------------------------------------
    reg  [2:0]        wait_cnt;
    wire              post_go = (state == S_CWAIT) && (wait_cnt == 3'd5);
    wire              post_last;
    /* verilator lint_off UNUSEDSIGNAL */
    wire              post_last_nx;     // rx_top's early buffer release; one channel here
    /* verilator lint_on UNUSEDSIGNAL */

    rx_post #(.MAX_G(MAX_G), .MAX_P(MAX_P), .MAX_UID(MAX_UID), .NGHOST(NGHOST),
              .OUT_W(OUT_W), .LAG_W(LAG_W), .G_W(G_W), .CA_W(CA_W), .P_W(P_W), .OB_W(OB_W),
              .CW(CW), .SUM_W(SUM_W), .SQ_W(SQ_W)) post (
        .clk(clk), .rst(rst), .go(post_go), .more(1'b0),
        .ns(ns), .gate_start(c_gate_start), .gate_len(c_gate_len), .excl(c_excl),
        .gh_start(c_gh_start), .gh_len(c_gh_len), .peaks(c_peaks), .uid(c_uid),
        .uid_mask(uid_mask), .out_bits(c_out_bits),
        .raddr(cr_raddr), .rdata(cr_rdata), .last(post_last), .last_nx(post_last_nx),
        .corr_valid(corr_valid), .corr_index(corr_index), .corr_data(corr_data),
        .res_valid(done), .res_found(res_found), .res_lag(res_lag),
        .res_index(res_index), .res_peak(res_peak), .res_neg(res_neg), .res_nz(res_nz),
        .res_nb_lo(res_nb_lo), .res_nb_hi(res_nb_hi), .res_noise_count(res_noise_count),
        .res_noise_sum(res_noise_sum), .res_noise_sumsq(res_noise_sumsq),
        .res_uid_observed(res_uid_observed), .res_uid_match(res_uid_match),
        .res_saturated(res_saturated)
    );

    // ------------------------------------------------------------------
    // Main sequencer
    // ------------------------------------------------------------------
    always @(posedge clk) begin
        w_v        <= 1'b0;
        c1_v       <= 1'b0;
        c2_v       <= 1'b0;

        // ---- averaging write-back pipeline ----
        if (a_take) begin
            w_v     <= 1'b1;
            w_addr  <= a_addr[ADDR_W-1:0];
            w_first <= (a_frame == {R_W{1'b0}});
            w_x     <= s_data;
        end

        // ---- correlation pipeline, stage 1 ----
        if (c1_v) begin
            per_acc <= per_sum;
            if (c1_last) begin
                tot_acc <= tot_sum;
                sg_neg  <= neg_nx;
                sg_nz   <= nz_nx;
                if (c1_lastp) begin
                    c2_v    <= 1'b1;
                    c2_jj   <= c1_jj;
                    c2_raw  <= tot_sum;
                    c2_neg  <= neg_nx;
                    c2_nz   <= nz_nx;
                end
            end
        end
        case (state)
        S_IDLE: if (start) begin
            state        <= S_INIT1;
        end
        S_INIT1: begin
            ns    <= ns_full[LAG_W-1:0];
            state <= S_INIT2;
        end
        S_INIT2: begin
            nns     <= ns * c_uid_bits;
            a_addr  <= {(ADDR_W+1){1'b0}};
            a_frame <= {R_W{1'b0}};
            state   <= S_ACCUM;
        end
        S_ACCUM: if (a_take) begin
            if (a_addr == nns - 1'b1) begin
                a_addr  <= {(ADDR_W+1){1'b0}};
                a_frame <= a_frame + 1'b1;
                if (a_frame == c_averages - 1'b1)
                    state <= S_DRAIN;
            end else begin
                a_addr <= a_addr + 1'b1;
            end
        end
        S_DRAIN: begin
            // last write-back happens now; set up the first lag gate_start - 1
            k_i      <= {LAG_W{1'b0}};
            k_s      <= {S_W{1'b0}};
            k_p      <= {UID_W{1'b0}};
            k_base   <= {(ADDR_W+1){1'b0}};
            k_jj     <= {JJ_W{1'b0}};
            k_lag    <= (c_gate_start == {LAG_W{1'b0}}) ? ns - 1'b1 : c_gate_start - 1'b1;
            k_a      <= (c_gate_start == {LAG_W{1'b0}}) ? ns - 1'b1 : c_gate_start - 1'b1;
            state    <= S_CORR;
        end
        S_CORR: begin
            c1_v     <= 1'b1;
            c1_chip  <= ref_chip;
            c1_first <= (k_i == {LAG_W{1'b0}});
            c1_last  <= k_last_i;
            c1_lastp <= k_last_p;
            c1_p     <= k_p;
            c1_jj    <= k_jj;
            k_s      <= (k_s == c_spc - 1'b1) ? {S_W{1'b0}} : k_s + 1'b1;
            if (k_last_i) begin
                k_i <= {LAG_W{1'b0}};
                if (k_last_p) begin
                    k_p    <= {UID_W{1'b0}};
                    k_base <= {(ADDR_W+1){1'b0}};
                    k_lag  <= k_lag_nx;
                    k_a    <= k_lag_nx;
                    k_jj   <= k_jj + 1'b1;
                    if (k_jj == jj_last) begin
                        state    <= S_CWAIT;
                        wait_cnt <= 3'd0;
                    end
                end else begin
                    k_p    <= k_p + 1'b1;
                    k_base <= k_base + {{(ADDR_W+1-LAG_W){1'b0}}, ns};
                    k_a    <= k_lag;
                end
            end else begin
                k_i <= k_i + 1'b1;
                k_a <= lag_inc(k_a, ns);
            end
        end
        S_CWAIT: begin
            // let stages 1..3 drain, then post-process
            wait_cnt <= wait_cnt + 1'b1;
            if (post_go)
                state <= S_POST;
        end
        S_POST: if (post_last)
            state <= S_IDLE;
        default: state <= S_IDLE;
        endcase

        if (rst) begin
            state      <= S_IDLE;
            w_v        <= 1'b0;
            c1_v       <= 1'b0;
            c2_v       <= 1'b0;
        end
    end

    // Generator control and RAM read address (combinational)
    always @(*) begin
        gen_load  = (state == S_DRAIN);     // chip 0 in the first CORR clock
        gen_en    = (state == S_CORR) && (k_s == c_spc - 1'b1);
        ram_raddr = (state == S_CORR) ? k_addr[ADDR_W-1:0] : a_addr[ADDR_W-1:0];
    end

    // Sink for bits that are wider than any legal value needs (lint).
    // (c3_jj carries G_W + 1 bits; the RAM needs clog2(MAX_G + 2) of them)
    wire unused_ok = &{1'b0, st_u, st_v, k_addr[ADDR_W], c3_jj,
                       ns_full[MAX_DEG+S_W:LAG_W]};
endmodule

`default_nettype wire
