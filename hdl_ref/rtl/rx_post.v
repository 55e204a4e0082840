// rx_post -- post-processing of one channel's correlation trace, shared by
// rx_chain and rx_top: peaks, the first peak's neighbours, the noise floor,
// the UID signs and match, the saturation flag, and the gate trace on corr_*.
// Bit for bit firmware_model.receiver (docs/firmware.md, docs/hdl.md).
//
// The trace lives in the caller's correlation RAM (read latency 1 clock,
// word {nz[MAX_UID], neg[MAX_UID], out[OUT_W]}, extended gate index
// jj = j + 1 as address: jj = 0 and G + 1 are the two neighbour lags). One
// scan (issue j = 0..G-1 with its lag, ghost and exclusion masks; RAM word;
// magnitude and square; compare or accumulate) serves every pass:
//   passes q = 0..P-1  peak search, strict > (ties to the lowest j);
//   FETCH              the first peak's neighbours (jj = j0 and j0 + 2);
//   noise pass         count, sum, sum of squares of the eligible lags, and
//                      every word out on corr_* (j = 0..G-1 in order).
// Clocks per channel from `go` (or from the previous channel's last clock):
// P (G + 4) + 3 + G + 4; `last` is high in the final one, `res_valid` in the
// next (results held until the next channel starts).
`default_nettype none

module rx_post #(
    parameter integer MAX_G   = 64,
    parameter integer MAX_P   = 1,
    parameter integer MAX_UID = 1,
    parameter integer NGHOST  = 1,
    parameter integer OUT_W   = 32,
    parameter integer LAG_W   = 14,
    // ---- derived: passed down by the top, checked below ----
    parameter integer G_W     = $clog2(MAX_G + 1),
    parameter integer CA_W    = $clog2(MAX_G + 2),
    parameter integer P_W     = $clog2(MAX_P + 1),
    parameter integer OB_W    = 6,
    parameter integer CW      = OUT_W + 2 * MAX_UID,
    parameter integer SUM_W   = OUT_W + G_W,
    parameter integer SQ_W    = 2 * OUT_W + G_W
) (
    input  wire                         clk,
    input  wire                         rst,
    input  wire                         go,         // start a channel (IDLE only)
    input  wire                         more,       // at `last`: another channel follows
    // configuration, stable while busy
    input  wire [LAG_W-1:0]             ns,         // N * S
    input  wire [LAG_W-1:0]             gate_start,
    input  wire [G_W-1:0]               gate_len,
    input  wire [G_W-1:0]               excl,       // peak_exclude W
    input  wire [NGHOST*LAG_W-1:0]      gh_start,
    input  wire [NGHOST*LAG_W-1:0]      gh_len,
    input  wire [P_W-1:0]               peaks,
    input  wire [MAX_UID-1:0]           uid,
    input  wire [MAX_UID-1:0]           uid_mask,   // bit p set for p < uid_bits
    input  wire [OB_W-1:0]              out_bits,
    // correlation RAM read port
    output reg  [CA_W-1:0]              raddr,
    input  wire [CW-1:0]                rdata,
    // outputs
    output wire                         last,       // a channel's final clock
    output wire                         last_nx,    // `last` in the next clock
    output reg                          corr_valid,
    output reg  [G_W-1:0]               corr_index,
    output reg  signed [OUT_W-1:0]      corr_data,
    output reg                          res_valid,
    output reg  [MAX_P-1:0]             res_found,
    output reg  [MAX_P*LAG_W-1:0]       res_lag,
    output reg  [MAX_P*G_W-1:0]         res_index,
    output reg  [MAX_P*OUT_W-1:0]       res_peak,
    output reg  [MAX_P*MAX_UID-1:0]     res_neg,
    output reg  [MAX_P*MAX_UID-1:0]     res_nz,
    output reg  signed [OUT_W-1:0]      res_nb_lo,
    output reg  signed [OUT_W-1:0]      res_nb_hi,
    output reg  [G_W-1:0]               res_noise_count,
    output reg  signed [SUM_W-1:0]      res_noise_sum,
    output reg  [SQ_W-1:0]              res_noise_sumsq,
    output reg  [MAX_UID-1:0]           res_uid_observed,
    output reg                          res_uid_match,
    output reg                          res_saturated
);
    localparam integer MAG_W = OUT_W + 1;

    // The derived widths come from the caller (passed down, computed once there); one
    // that differs from its formula stops the elaboration in every tool (an instance of
    // a module that does not exist) instead of a silent width mismatch.
    generate
        if (G_W != $clog2(MAX_G + 1) || CA_W != $clog2(MAX_G + 2) || P_W != $clog2(MAX_P + 1)
            || CW != OUT_W + 2 * MAX_UID || SUM_W != OUT_W + G_W || SQ_W != 2 * OUT_W + G_W
            || OB_W < $clog2(OUT_W + 1)) begin : g_derived_width_mismatch
            rx_post_derived_width_mismatch bad ();
        end
    endgenerate
    localparam [1:0] T_IDLE = 2'd0, T_SCAN = 2'd1, T_WAIT = 2'd2, T_FETCH = 2'd3;
    localparam [MAX_P-1:0] P_ONE = 1;
    localparam [CA_W-1:0]  CA_TWO = 2;

    reg  [1:0]        state;
    reg               noise;            // the noise pass (else peak pass q_k)
    reg  [P_W-1:0]    q_k;
    reg  [G_W-1:0]    q_j;
    reg  [LAG_W-1:0]  q_lag;
    reg  [1:0]        cnt;
    reg  [MAX_P-1:0]  pk_found;
    reg  [MAX_P*G_W-1:0] pk_j;

    wire [P_W-1:0]    q_k_last = peaks - 1'b1;
    wire [MAX_P-1:0]  q_bit    = P_ONE << q_k;
    wire [G_W-1:0]    q_j_last = gate_len - 1'b1;
    assign last    = (state == T_WAIT) && noise && (cnt == 2'd3);
    assign last_nx = (state == T_WAIT) && noise && (cnt == 2'd2);   // cnt counts up in T_WAIT

    // gate indices as RAM addresses (CA_W is G_W + 1 when MAX_G = 2^k - 1)
    wire [G_W+CA_W-1:0] q_jj = {{CA_W{1'b0}}, q_j} + {{(G_W+CA_W-1){1'b0}}, 1'b1};
    wire [G_W+CA_W-1:0] j0   = {{CA_W{1'b0}}, pk_j[G_W-1:0]};
    always @(*) begin
        if (state == T_FETCH)
            raddr = j0[CA_W-1:0] + ((cnt == 2'd0) ? {CA_W{1'b0}} : CA_TWO);
        else
            raddr = q_jj[CA_W-1:0];
    end

    // ---- masks of the lag being issued ----
    reg ghost, masked;
    integer w, q;
    reg [LAG_W:0] gd;
    reg [G_W-1:0] pj, dj;
    always @(*) begin
        ghost = 1'b0;
        for (w = 0; w < NGHOST; w = w + 1) begin
            // d = (lag - start) mod NS; in the window when d < len
            gd = {1'b0, q_lag} - {1'b0, gh_start[w*LAG_W +: LAG_W]};
            if (gd[LAG_W])
                gd = gd + {1'b0, ns};
            if (gd[LAG_W-1:0] < gh_len[w*LAG_W +: LAG_W])
                ghost = 1'b1;
        end
        masked = ghost;
        for (q = 0; q < MAX_P; q = q + 1) begin
            pj = pk_j[q*G_W +: G_W];
            dj = (q_j > pj) ? q_j - pj : pj - q_j;
            if (pk_found[q] && (noise || (q < {{(32-P_W){1'b0}}, q_k})) && dj <= excl)
                masked = 1'b1;
        end
    end

    // ---- scan pipeline: s1 RAM word, s2 registered, s3 magnitude and square ----
    reg               s1_v, s1_ok, s2_v, s2_ok, s3_v, s3_ok;
    reg  [G_W-1:0]    s1_j, s2_j, s3_j;
    reg  [LAG_W-1:0]  s1_lag, s2_lag, s3_lag;
    reg  [CW-1:0]     s2_word, s3_word;
    reg  [MAG_W-1:0]  s3_mag;
    wire signed [OUT_W-1:0]   s2_out = s2_word[OUT_W-1:0];
    wire signed [OUT_W-1:0]   s3_out = s3_word[OUT_W-1:0];
    // The noise square, pipelined: |out| = h 2^HB + l; stage 4 holds h^2, l^2 (disjoint
    // bits: l^2 < 2^(2 HB)) and h l, and adds 2^(2 HB) h^2 + l^2 + 2^(HB+1) h l to the sum
    // (one clock after stage 3, still before res_valid).
    localparam integer HB = (MAG_W + 1) / 2;
    wire [MAG_W-HB-1:0]       s3_h   = s3_mag[MAG_W-1:HB];
    wire [HB-1:0]             s3_l   = s3_mag[HB-1:0];
    reg                       s4_acc;
    reg  [2*(MAG_W-HB)-1:0]   s4_hh;
    reg  [2*HB-1:0]           s4_ll;
    reg  [MAG_W-1:0]          s4_hl;
    wire [2*MAG_W-1:0]        sq4    = {s4_hh, s4_ll} + ({{(MAG_W-HB){1'b0}}, s4_hl, {HB{1'b0}}} << 1);
    wire signed [OUT_W-1:0]   r_out  = rdata[OUT_W-1:0];

    // ---- best of the peak pass ----
    reg               b_have;
    reg  [MAG_W-1:0]  b_mag;
    reg  [G_W-1:0]    b_j;
    reg  [LAG_W-1:0]  b_lag;
    reg  [CW-1:0]     b_word;
    wire [MAX_UID-1:0]  b_neg = b_word[OUT_W +: MAX_UID] & uid_mask;
    wire [MAX_UID-1:0]  b_nz  = b_word[OUT_W+MAX_UID +: MAX_UID] & uid_mask;
    wire signed [OUT_W-1:0] b_out = b_word[OUT_W-1:0];
    wire [OUT_W:0]      o_max = ({{OUT_W{1'b0}}, 1'b1} << (out_bits - 1'b1)) - 1'b1;
    wire                b_rail = (b_out == o_max[OUT_W-1:0]) || (b_out == ~o_max[OUT_W-1:0]);

    task begin_channel;
        begin
            state    <= T_SCAN;
            noise    <= 1'b0;
            q_k      <= {P_W{1'b0}};
            q_j      <= {G_W{1'b0}};
            q_lag    <= gate_start;
            pk_found <= {MAX_P{1'b0}};
            b_have   <= 1'b0;
        end
    endtask

    always @(posedge clk) begin
        s1_v       <= 1'b0;
        res_valid  <= 1'b0;
        corr_valid <= 1'b0;

        case (state)
        T_IDLE: if (go)
            begin_channel;
        T_SCAN: begin
            if (!noise && q_k == {P_W{1'b0}} && q_j == {G_W{1'b0}}) begin
                // a channel's first clock (the previous channel's res_valid clock)
                res_found <= {MAX_P{1'b0}};
                res_lag   <= {(MAX_P*LAG_W){1'b0}};
                res_index <= {(MAX_P*G_W){1'b0}};
                res_peak  <= {(MAX_P*OUT_W){1'b0}};
                res_neg   <= {(MAX_P*MAX_UID){1'b0}};
                res_nz    <= {(MAX_P*MAX_UID){1'b0}};
            end
            s1_v   <= 1'b1;
            s1_ok  <= !masked;
            s1_j   <= q_j;
            s1_lag <= q_lag;
            q_j    <= q_j + 1'b1;
            q_lag  <= (q_lag == ns - 1'b1) ? {LAG_W{1'b0}} : q_lag + 1'b1;
            if (q_j == q_j_last) begin
                state <= T_WAIT;
                cnt   <= 2'd0;
            end
        end
        T_WAIT: begin
            cnt <= cnt + 1'b1;
            if (cnt == 2'd3) begin
                q_j    <= {G_W{1'b0}};
                q_lag  <= gate_start;
                b_have <= 1'b0;
                if (noise) begin
                    res_valid <= 1'b1;
                    if (more)
                        begin_channel;
                    else
                        state <= T_IDLE;
                end else begin
                    pk_found                        <= pk_found | (b_have ? q_bit : {MAX_P{1'b0}});
                    pk_j[q_k*G_W +: G_W]            <= b_j;
                    res_found                       <= res_found | (b_have ? q_bit : {MAX_P{1'b0}});
                    res_lag[q_k*LAG_W +: LAG_W]     <= b_have ? b_lag : {LAG_W{1'b0}};
                    res_index[q_k*G_W +: G_W]       <= b_have ? b_j : {G_W{1'b0}};
                    res_peak[q_k*OUT_W +: OUT_W]    <= b_have ? b_out : {OUT_W{1'b0}};
                    res_neg[q_k*MAX_UID +: MAX_UID] <= b_have ? b_neg : {MAX_UID{1'b0}};
                    res_nz[q_k*MAX_UID +: MAX_UID]  <= b_have ? b_nz : {MAX_UID{1'b0}};
                    if (q_k == {P_W{1'b0}}) begin
                        res_uid_observed <= b_have ? b_neg : {MAX_UID{1'b0}};
                        res_uid_match    <= b_have && (b_nz == uid_mask)
                                            && (b_neg == (uid & uid_mask));
                        res_saturated    <= b_have && b_rail;
                    end
                    if (q_k == q_k_last) begin
                        state <= T_FETCH;
                        cnt   <= 2'd0;
                    end else begin
                        q_k   <= q_k + 1'b1;
                        state <= T_SCAN;
                    end
                end
            end
        end
        T_FETCH: begin
            cnt <= cnt + 1'b1;
            if (cnt == 2'd1)
                res_nb_lo <= pk_found[0] ? r_out : {OUT_W{1'b0}};
            if (cnt == 2'd2) begin
                res_nb_hi       <= pk_found[0] ? r_out : {OUT_W{1'b0}};
                res_noise_count <= {G_W{1'b0}};
                res_noise_sum   <= {SUM_W{1'b0}};
                res_noise_sumsq <= {SQ_W{1'b0}};
                noise           <= 1'b1;
                state           <= T_SCAN;
            end
        end
        default: state <= T_IDLE;
        endcase

        s2_v    <= s1_v;
        s2_ok   <= s1_ok;
        s2_j    <= s1_j;
        s2_lag  <= s1_lag;
        s2_word <= rdata;
        s3_v    <= s2_v;
        s3_ok   <= s2_ok;
        s3_j    <= s2_j;
        s3_lag  <= s2_lag;
        s3_word <= s2_word;
        s3_mag  <= s2_out[OUT_W-1] ? -{s2_out[OUT_W-1], s2_out} : {1'b0, s2_out};
        s4_acc  <= s3_v && noise && s3_ok;
        s4_hh   <= s3_h * s3_h;
        s4_ll   <= s3_l * s3_l;
        s4_hl   <= s3_h * s3_l;
        if (s4_acc)
            res_noise_sumsq <= res_noise_sumsq + {{(SQ_W-2*OUT_W){1'b0}}, sq4[2*OUT_W-1:0]};
        if (s3_v) begin
            if (noise) begin
                corr_valid <= 1'b1;
                corr_index <= s3_j;
                corr_data  <= s3_out;
                if (s3_ok) begin
                    res_noise_count <= res_noise_count + 1'b1;
                    res_noise_sum   <= res_noise_sum + {{(SUM_W-OUT_W){s3_out[OUT_W-1]}}, s3_out};
                end
            end else if (s3_ok && (!b_have || s3_mag > b_mag)) begin
                b_have <= 1'b1;
                b_mag  <= s3_mag;
                b_j    <= s3_j;
                b_lag  <= s3_lag;
                b_word <= s3_word;
            end
        end

        if (rst) begin
            state      <= T_IDLE;
            noise      <= 1'b0;
            s1_v       <= 1'b0;
            s2_v       <= 1'b0;
            s3_v       <= 1'b0;
            s4_acc     <= 1'b0;
            res_valid  <= 1'b0;
            corr_valid <= 1'b0;
        end
    end

    wire unused_ok = &{1'b0, sq4[2*MAG_W-1:2*OUT_W], o_max[OUT_W], pk_j, q_jj[G_W+CA_W-1:CA_W], j0[G_W+CA_W-1:CA_W]};
endmodule

`default_nettype wire
