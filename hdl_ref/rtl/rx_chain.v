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
//          per lag the rounded, saturated out word and the signs of the n
//          per-period sums go to the correlation RAM and out on corr_*;
//   PEAK   `peaks` passes of gate_len clocks over the correlation RAM;
//   FETCH  read the first peak's two neighbours;
//   NOISE  one pass of gate_len clocks (count, sum, sum of squares).
// Latency (clock edges, checked by the co-simulation for every case):
//   start -> first sample taken:   3
//   last sample taken -> done:     (gate_len + 2) * n * NS + peaks * (gate_len + 2)
//                                  + gate_len + 11
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
    output reg                          corr_valid,
    output reg  [G_W-1:0]               corr_index,     // j
    output reg  signed [OUT_W-1:0]      corr_data,      // out(lag_j)

    // ---- results, valid from done until the next start ----
    output wire                         busy,
    output reg                          done,           // one-clock pulse
    output reg  [MAX_P-1:0]             res_found,      // peak q exists
    output reg  [MAX_P*LAG_W-1:0]       res_lag,        // peak q lag (samples) at [q*LAG_W]
    output reg  [MAX_P*G_W-1:0]         res_index,      // peak q gate index j
    output reg  [MAX_P*OUT_W-1:0]       res_peak,       // peak q out value (signed)
    output reg  [MAX_P*MAX_UID-1:0]     res_neg,        // per-period sum c_p < 0 at peak q
    output reg  [MAX_P*MAX_UID-1:0]     res_nz,         // per-period sum != 0 at peak q
    output reg  signed [OUT_W-1:0]      res_nb_lo,      // out at peak lag - 1
    output reg  signed [OUT_W-1:0]      res_nb_hi,      // out at peak lag + 1
    output reg  [CNT_W-1:0]             res_noise_count,
    output reg  signed [SUM_W-1:0]      res_noise_sum,
    output reg  [SQ_W-1:0]              res_noise_sumsq,
    output reg  [MAX_UID-1:0]           res_uid_observed,
    output reg                          res_uid_match,
    output reg                          res_saturated   // peak 0's out word at a rail
);
    // ------------------------------------------------------------------
    // Widths
    // ------------------------------------------------------------------
    localparam integer AVG_W  = ADC_W + $clog2(MAX_R);              // sum of R samples
    localparam integer PER_W  = AVG_W + $clog2(MAX_NS) + 1;         // per-period correlation
    localparam integer RAW_W  = PER_W + $clog2(MAX_UID);            // despread correlation
    localparam integer EXT_W  = ((RAW_W > OUT_W) ? RAW_W : OUT_W) + 2;
    localparam integer ADDR_W = $clog2(MAX_UID * MAX_NS);
    localparam integer JJ_W   = G_W + 1;                             // extended gate index
    localparam integer CA_W   = $clog2(MAX_G + 2);                   // correlation RAM address
    localparam [JJ_W-1:0] JJ_TWO = 2;
    localparam integer CW     = OUT_W + 2 * MAX_UID;                 // correlation RAM word
    localparam integer MAG_W  = OUT_W + 1;                           // |out|

    localparam [3:0] S_IDLE  = 4'd0,  S_INIT1 = 4'd1, S_INIT2 = 4'd2, S_ACCUM = 4'd3,
                     S_DRAIN = 4'd4,  S_CORR  = 4'd5, S_CWAIT = 4'd6, S_PEAK  = 4'd7,
                     S_PWAIT = 4'd8,  S_FETCH = 4'd9, S_NOISE = 4'd10, S_NWAIT = 4'd11,
                     S_DONE  = 4'd12;

    reg [3:0] state;

    // ------------------------------------------------------------------
    // Configuration registers
    // ------------------------------------------------------------------
    reg [DEG_W-1:0]        c_degree;
    reg [MAX_DEG-1:0]      c_taps_u, c_taps_v, c_seed_u, c_seed_v;
    reg [S_W-1:0]          c_spc;
    reg [R_W-1:0]          c_averages;
    reg [UID_W-1:0]        c_uid_bits;
    reg [MAX_UID-1:0]      c_uid;
    reg [LAG_W-1:0]        c_gate_start;
    reg [G_W-1:0]          c_gate_len, c_excl;
    reg [NGHOST*LAG_W-1:0] c_gh_start, c_gh_len;
    reg [SH_W-1:0]         c_shift;
    reg [1:0]              c_round;
    reg [OB_W-1:0]         c_out_bits;
    reg [P_W-1:0]          c_peaks;

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

    // stage 2 (raw correlation of one lag) -> rounding and saturation
    reg               c2_v;
    reg  [JJ_W-1:0]   c2_jj;
    reg  signed [RAW_W-1:0] c2_raw;
    reg  [MAX_UID-1:0] c2_neg, c2_nz;

    wire signed [EXT_W-1:0] rx      = {{(EXT_W-RAW_W){c2_raw[RAW_W-1]}}, c2_raw};
    wire [SH_W-1:0]         sh_c    = ({{(32-SH_W){1'b0}}, c_shift} > RAW_W + 1)
                                      ? RAW_W[SH_W-1:0] + 1'b1 : c_shift;
    wire signed [EXT_W-1:0] rq      = rx >>> sh_c;                    // floor
    wire signed [EXT_W-1:0] rrem    = rx - (rq <<< sh_c);             // 0 .. 2^sh - 1
    wire [EXT_W-1:0]        rhalf   = (sh_c == {SH_W{1'b0}}) ? {EXT_W{1'b0}}
                                      : ({{(EXT_W-1){1'b0}}, 1'b1} << (sh_c - 1'b1));
    wire                    r_gt    = $unsigned(rrem) > rhalf;
    wire                    r_eq    = $unsigned(rrem) == rhalf;
    wire                    r_up    = (sh_c != {SH_W{1'b0}}) &&
                                      (((c_round == 2'd1) && (r_gt || r_eq)) ||
                                       ((c_round == 2'd2) && (r_gt || (r_eq && rq[0]))));
    wire signed [EXT_W-1:0] ry      = rq + {{(EXT_W-1){1'b0}}, r_up};
    wire signed [EXT_W-1:0] smax    = ({{(EXT_W-1){1'b0}}, 1'b1} << (c_out_bits - 1'b1))
                                      - {{(EXT_W-1){1'b0}}, 1'b1};
    wire signed [EXT_W-1:0] smin    = ~smax;
    wire signed [EXT_W-1:0] rsat    = (ry > smax) ? smax : (ry < smin) ? smin : ry;

    // stage 3: correlation RAM write and stream
    reg               c3_v;
    reg  [JJ_W-1:0]   c3_jj;
    reg  [CW-1:0]     c3_word;

    // ------------------------------------------------------------------
    // Correlation RAM: word = {nz[MAX_UID], neg[MAX_UID], out[OUT_W]},
    // address jj = j + 1 (jj 0 and G+1 are the neighbour lags)
    // ------------------------------------------------------------------
    reg  [JJ_W-1:0]   cr_raddr;
    wire [CW-1:0]     cr_rdata;

    sdp_ram #(.WIDTH(CW), .DEPTH(MAX_G + 2)) corr_ram (
        .clk(clk), .we(c3_v), .waddr(c3_jj[CA_W-1:0]), .wdata(c3_word),
        .raddr(cr_raddr[CA_W-1:0]), .rdata(cr_rdata)
    );
    wire signed [OUT_W-1:0] cr_out  = cr_rdata[OUT_W-1:0];
    wire [MAG_W-1:0]        cr_mag  = cr_out[OUT_W-1] ? -{cr_out[OUT_W-1], cr_out}
                                                      : {1'b0, cr_out};

    // ------------------------------------------------------------------
    // PEAK / NOISE scan: issue j with its lag; ghost and exclusion masks
    // ------------------------------------------------------------------
    reg  [G_W-1:0]    q_j;              // gate index being issued
    reg  [LAG_W-1:0]  q_lag;            // lag_j
    reg  [P_W-1:0]    q_k;              // peak being searched
    reg  [MAX_P-1:0]  pk_found;
    reg  [MAX_P*G_W-1:0] pk_j;

    reg ghost;                          // lag_j in any ghost window
    reg excl;                           // |j - j_q| <= W for a found peak q (< q_k when searching)
    integer w, q;
    reg [LAG_W:0] gd;
    reg [G_W-1:0] pj, dj;
    always @(*) begin
        ghost = 1'b0;
        for (w = 0; w < NGHOST; w = w + 1) begin
            // d = (lag - start) mod NS; in the window when d < len
            gd = {1'b0, q_lag} - {1'b0, c_gh_start[w*LAG_W +: LAG_W]};
            if (gd[LAG_W])
                gd = gd + {1'b0, ns};
            if (gd[LAG_W-1:0] < c_gh_len[w*LAG_W +: LAG_W])
                ghost = 1'b1;
        end
        excl = 1'b0;
        for (q = 0; q < MAX_P; q = q + 1) begin
            pj = pk_j[q*G_W +: G_W];
            dj = (q_j > pj) ? q_j - pj : pj - q_j;
            if (pk_found[q] && ((state == S_NOISE) || (q < {{(32-P_W){1'b0}}, q_k}))
                && dj <= c_excl)
                excl = 1'b1;
        end
    end

    reg               s1_v, s1_ok;      // scan stage 1 (corr RAM data valid)
    reg  [G_W-1:0]    s1_j;
    reg  [LAG_W-1:0]  s1_lag;
    reg               b_have;
    reg  [MAG_W-1:0]  b_mag;
    reg  [G_W-1:0]    b_j;
    reg  [LAG_W-1:0]  b_lag;
    reg  [CW-1:0]     b_word;
    reg  [2:0]        wait_cnt;
    reg  [1:0]        f_cnt;

    wire signed [2*OUT_W-1:0] sq = cr_out * cr_out;
    wire [MAX_UID-1:0]  b_neg = b_word[OUT_W +: MAX_UID] & uid_mask;
    wire [MAX_UID-1:0]  b_nz  = b_word[OUT_W+MAX_UID +: MAX_UID] & uid_mask;
    wire signed [OUT_W-1:0] b_out = b_word[OUT_W-1:0];
    wire [OUT_W:0]      o_max = ({{OUT_W{1'b0}}, 1'b1} << (c_out_bits - 1'b1)) - 1'b1;
    wire                b_rail = (b_out == o_max[OUT_W-1:0]) || (b_out == ~o_max[OUT_W-1:0]);

    wire [P_W-1:0]    q_k_last = c_peaks - 1'b1;
    localparam [MAX_P-1:0] P_ONE = 1;
    wire [MAX_P-1:0]  q_bit    = P_ONE << q_k;       // one-hot of the peak being searched
    wire [G_W-1:0]    q_j_last = c_gate_len - 1'b1;

    // ------------------------------------------------------------------
    // Main sequencer
    // ------------------------------------------------------------------
    always @(posedge clk) begin
        done       <= 1'b0;
        corr_valid <= 1'b0;
        w_v        <= 1'b0;
        c1_v       <= 1'b0;
        c2_v       <= 1'b0;
        c3_v       <= 1'b0;
        s1_v       <= 1'b0;

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
        // ---- stage 2: rounding, saturation ----
        if (c2_v) begin
            c3_v    <= 1'b1;
            c3_jj   <= c2_jj;
            c3_word <= {c2_nz, c2_neg, rsat[OUT_W-1:0]};
        end
        // ---- stage 3: stream gate lags ----
        if (c3_v && c3_jj != {JJ_W{1'b0}} && c3_jj != jj_last) begin
            corr_valid <= 1'b1;
            corr_index <= c3_jj[G_W-1:0] - 1'b1;
            corr_data  <= c3_word[OUT_W-1:0];
        end

        case (state)
        S_IDLE: if (start) begin
            c_degree     <= cfg_degree;
            c_taps_u     <= cfg_taps_u;
            c_taps_v     <= cfg_taps_v;
            c_seed_u     <= cfg_seed_u;
            c_seed_v     <= cfg_seed_v;
            c_spc        <= cfg_spc;
            c_averages   <= cfg_averages;
            c_uid_bits   <= cfg_uid_bits;
            c_uid        <= cfg_uid;
            c_gate_start <= cfg_gate_start;
            c_gate_len   <= cfg_gate_len;
            c_excl       <= cfg_peak_exclude;
            c_gh_start   <= cfg_ghost_start;
            c_gh_len     <= cfg_ghost_len;
            c_shift      <= cfg_out_shift;
            c_round      <= cfg_rounding;
            c_out_bits   <= cfg_out_bits;
            c_peaks      <= cfg_peaks;
            res_found    <= {MAX_P{1'b0}};
            res_lag      <= {(MAX_P*LAG_W){1'b0}};
            res_index    <= {(MAX_P*G_W){1'b0}};
            res_peak     <= {(MAX_P*OUT_W){1'b0}};
            res_neg      <= {(MAX_P*MAX_UID){1'b0}};
            res_nz       <= {(MAX_P*MAX_UID){1'b0}};
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
            // let stages 1..3 drain, then start the first peak pass
            wait_cnt <= wait_cnt + 1'b1;
            if (wait_cnt == 3'd3) begin
                state    <= S_PEAK;
                q_k      <= {P_W{1'b0}};
                q_j      <= {G_W{1'b0}};
                q_lag    <= c_gate_start;
                pk_found <= {MAX_P{1'b0}};
                b_have   <= 1'b0;
            end
        end
        S_PEAK: begin
            s1_v   <= 1'b1;
            s1_ok  <= !ghost && !excl;
            s1_j   <= q_j;
            s1_lag <= q_lag;
            q_j    <= q_j + 1'b1;
            q_lag  <= lag_inc(q_lag, ns);
            if (q_j == q_j_last) begin
                state    <= S_PWAIT;
                wait_cnt <= 3'd0;
            end
        end
        S_PWAIT: begin
            wait_cnt <= wait_cnt + 1'b1;
            if (wait_cnt == 3'd1) begin
                // record peak q_k
                pk_found                      <= pk_found | (b_have ? q_bit : {MAX_P{1'b0}});
                pk_j[q_k*G_W +: G_W]          <= b_j;
                res_found                     <= res_found | (b_have ? q_bit : {MAX_P{1'b0}});
                res_lag[q_k*LAG_W +: LAG_W]   <= b_lag;
                res_index[q_k*G_W +: G_W]     <= b_j;
                // a missing peak reports value 0 and no signs (docs/firmware.md 4)
                res_peak[q_k*OUT_W +: OUT_W]    <= b_have ? b_word[OUT_W-1:0] : {OUT_W{1'b0}};
                res_neg[q_k*MAX_UID +: MAX_UID] <= b_have ? b_neg : {MAX_UID{1'b0}};
                res_nz[q_k*MAX_UID +: MAX_UID]  <= b_have ? b_nz : {MAX_UID{1'b0}};
                if (q_k == {P_W{1'b0}}) begin
                    res_uid_observed <= b_have ? b_neg : {MAX_UID{1'b0}};
                    res_uid_match    <= b_have && (b_nz == uid_mask)
                                        && (b_neg == (c_uid & uid_mask));
                    res_saturated    <= b_have && b_rail;
                end
                q_j    <= {G_W{1'b0}};
                q_lag  <= c_gate_start;
                b_have <= 1'b0;
                if (q_k == q_k_last) begin
                    state <= S_FETCH;
                    f_cnt <= 2'd0;
                end else begin
                    q_k   <= q_k + 1'b1;
                    state <= S_PEAK;
                end
            end
        end
        S_FETCH: begin
            // neighbours of peak 0: addresses j0 (lag-1) and j0+2 (lag+1)
            f_cnt <= f_cnt + 1'b1;
            if (f_cnt == 2'd1)
                res_nb_lo <= pk_found[0] ? cr_out : {OUT_W{1'b0}};
            if (f_cnt == 2'd2) begin
                res_nb_hi       <= pk_found[0] ? cr_out : {OUT_W{1'b0}};
                res_noise_count <= {CNT_W{1'b0}};
                res_noise_sum   <= {SUM_W{1'b0}};
                res_noise_sumsq <= {SQ_W{1'b0}};
                state           <= S_NOISE;
            end
        end
        S_NOISE: begin
            s1_v   <= 1'b1;
            s1_ok  <= !ghost && !excl;
            s1_j   <= q_j;
            s1_lag <= q_lag;
            q_j    <= q_j + 1'b1;
            q_lag  <= lag_inc(q_lag, ns);
            if (q_j == q_j_last) begin
                state    <= S_NWAIT;
                wait_cnt <= 3'd0;
            end
        end
        S_NWAIT: begin
            wait_cnt <= wait_cnt + 1'b1;
            if (wait_cnt == 3'd1)
                state <= S_DONE;
        end
        S_DONE: begin
            done  <= 1'b1;
            state <= S_IDLE;
        end
        default: state <= S_IDLE;
        endcase

        // ---- scan stage 1: best |out| (lowest j on ties) or noise sums ----
        if (s1_v && s1_ok) begin
            if (state == S_PEAK || state == S_PWAIT) begin
                if (!b_have || cr_mag > b_mag) begin
                    b_have <= 1'b1;
                    b_mag  <= cr_mag;
                    b_j    <= s1_j;
                    b_lag  <= s1_lag;
                    b_word <= cr_rdata;
                end
            end else begin
                res_noise_count <= res_noise_count + 1'b1;
                res_noise_sum   <= res_noise_sum + {{(SUM_W-OUT_W){cr_out[OUT_W-1]}}, cr_out};
                res_noise_sumsq <= res_noise_sumsq
                                   + {{(SQ_W-2*OUT_W){1'b0}}, sq[2*OUT_W-1:0]};
            end
        end

        if (rst) begin
            state      <= S_IDLE;
            done       <= 1'b0;
            corr_valid <= 1'b0;
            w_v        <= 1'b0;
            c1_v       <= 1'b0;
            c2_v       <= 1'b0;
            c3_v       <= 1'b0;
            s1_v       <= 1'b0;
        end
    end

    // Generator control and RAM read address (combinational)
    always @(*) begin
        gen_load  = (state == S_DRAIN);     // chip 0 in the first CORR clock
        gen_en    = (state == S_CORR) && (k_s == c_spc - 1'b1);
        ram_raddr = (state == S_CORR) ? k_addr[ADDR_W-1:0] : a_addr[ADDR_W-1:0];
        case (state)
        S_FETCH: cr_raddr = (f_cnt == 2'd0) ? {1'b0, pk_j[G_W-1:0]}
                                            : {1'b0, pk_j[G_W-1:0]} + JJ_TWO;
        default: cr_raddr = {1'b0, q_j} + 1'b1;
        endcase
    end

    // Sink for bits that are wider than any legal value needs (lint).
    // (c3_jj and cr_raddr carry G_W + 1 bits; the RAM needs clog2(MAX_G + 2) of them)
    wire unused_ok = &{1'b0, st_u, st_v, s1_lag, k_addr[ADDR_W], rsat[EXT_W-1:OUT_W], o_max[OUT_W],
                       c3_jj, cr_raddr,
                       ns_full[MAX_DEG+S_W:LAG_W]};
endmodule

`default_nettype wire
