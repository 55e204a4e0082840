// out_scale -- out = sat_out_bits(round(raw / 2^out_shift)), pipelined in three stages.
//
// Bit for bit the scaling of docs/firmware.md section 3 (firmware_model.receiver._scale):
//   truncate    floor(raw / 2^s)
//   half_up     floor(raw / 2^s + 1/2)
//   convergent  round half to even
// then saturation to a signed `out_bits` word.
// Stage 1: floor shift and remainder (low s bits); stage 2: round-up decision
// and increment; stage 3: saturation. Latency 3 clocks, one word per clock.
// The constants that depend only on the configuration (remainder mask, half
// LSB, saturation rails) are registered: shift, rounding and out_bits must be
// stable from one clock before the first word (rx_top holds them from start).
// The shift is clamped to RAW_W + 1, which gives the same result for every
// larger shift (the quotient is 0 or -1 and the remainder below one half).
`default_nettype none

module out_scale #(
    parameter integer RAW_W = 32,       // signed input width
    parameter integer OUT_W = 32,       // output word width (out_bits <= OUT_W)
    parameter integer TAG_W = 8,        // side band carried along (address, flags)
    parameter integer SH_W  = 6,        // out_shift 0..2^SH_W-1
    parameter integer OB_W  = 6,        // out_bits 2..OUT_W
    // ---- derived, do not override ----
    parameter integer EXT_W = ((RAW_W > OUT_W) ? RAW_W : OUT_W) + 2
) (
    input  wire                     clk,
    input  wire                     in_v,
    input  wire signed [RAW_W-1:0]  in_raw,
    input  wire [TAG_W-1:0]         in_tag,
    input  wire [SH_W-1:0]          shift,
    input  wire [1:0]               rounding,   // 0 truncate, 1 half_up, 2 convergent
    input  wire [OB_W-1:0]          out_bits,
    output reg                      out_v,
    output reg  signed [OUT_W-1:0]  out_word,
    output reg  [TAG_W-1:0]         out_tag
);
    wire signed [EXT_W-1:0] rx    = {{(EXT_W-RAW_W){in_raw[RAW_W-1]}}, in_raw};
    wire [SH_W-1:0]         sh_c  = ({{(32-SH_W){1'b0}}, shift} > RAW_W + 1)
                                    ? RAW_W[SH_W-1:0] + 1'b1 : shift;
    reg  [SH_W-1:0]         k_sh;                   // registered configuration constants
    reg  [EXT_W-1:0]        k_low, k_half;
    reg                     k_zero;
    reg  signed [EXT_W-1:0] smax, smin;

    // ---- stage 1: floor quotient and remainder ----
    reg                     s1_v;
    reg  [TAG_W-1:0]        s1_tag;
    reg  signed [EXT_W-1:0] s1_q;
    reg  [EXT_W-1:0]        s1_rem;
    reg  [EXT_W-1:0]        s1_half;    // 2^(s-1), 0 for s = 0
    reg                     s1_zero;    // s = 0: no rounding

    // ---- stage 2: rounded ----
    reg                     s2_v;
    reg  [TAG_W-1:0]        s2_tag;
    reg  signed [EXT_W-1:0] s2_y;

    wire r_gt = s1_rem > s1_half;
    wire r_eq = s1_rem == s1_half;
    wire r_up = !s1_zero && (((rounding == 2'd1) && (r_gt || r_eq)) ||
                             ((rounding == 2'd2) && (r_gt || (r_eq && s1_q[0]))));


    always @(posedge clk) begin
        k_sh   <= sh_c;
        k_low  <= ({{(EXT_W-1){1'b0}}, 1'b1} << sh_c) - 1'b1;
        k_half <= (sh_c == {SH_W{1'b0}}) ? {EXT_W{1'b0}}
                  : ({{(EXT_W-1){1'b0}}, 1'b1} << (sh_c - 1'b1));
        k_zero <= (sh_c == {SH_W{1'b0}});
        smax   <= ({{(EXT_W-1){1'b0}}, 1'b1} << (out_bits - 1'b1)) - {{(EXT_W-1){1'b0}}, 1'b1};
        smin   <= ~(({{(EXT_W-1){1'b0}}, 1'b1} << (out_bits - 1'b1)) - {{(EXT_W-1){1'b0}}, 1'b1});

        s1_v    <= in_v;
        s1_tag  <= in_tag;
        s1_q    <= rx >>> k_sh;
        s1_rem  <= rx & k_low;
        s1_half <= k_half;
        s1_zero <= k_zero;

        s2_v    <= s1_v;
        s2_tag  <= s1_tag;
        s2_y    <= s1_q + {{(EXT_W-1){1'b0}}, r_up};

        out_v    <= s2_v;
        out_tag  <= s2_tag;
        out_word <= (s2_y > smax) ? smax[OUT_W-1:0]
                  : (s2_y < smin) ? smin[OUT_W-1:0] : s2_y[OUT_W-1:0];
    end
endmodule

`default_nettype wire
