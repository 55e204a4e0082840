// cfg_latch -- the configuration register of both tops (rx_chain, rx_top): every
// cfg_* port of docs/hdl.md sampled in the clock of `load` (a top's `start` in
// IDLE) and held until the next. SEED_W is MAX_DEG for one channel (rx_chain) and
// K * MAX_DEG for K channels (rx_top). Widths are the tops' derived parameters,
// passed down.
`default_nettype none

module cfg_latch #(
    parameter integer MAX_DEG = 11,
    parameter integer MAX_UID = 1,
    parameter integer NGHOST  = 1,
    parameter integer SEED_W  = 11,
    parameter integer DEG_W   = 4,
    parameter integer S_W     = 3,
    parameter integer R_W     = 5,
    parameter integer UID_W   = 1,
    parameter integer LAG_W   = 14,
    parameter integer G_W     = 7,
    parameter integer P_W     = 1,
    parameter integer SH_W    = 6,
    parameter integer OB_W    = 6
) (
    input  wire                         clk,
    input  wire                         load,
    input  wire [DEG_W-1:0]             cfg_degree,
    input  wire [MAX_DEG-1:0]           cfg_taps_u,
    input  wire [MAX_DEG-1:0]           cfg_taps_v,
    input  wire [SEED_W-1:0]            cfg_seed_u,
    input  wire [SEED_W-1:0]            cfg_seed_v,
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
    output reg  [DEG_W-1:0]             c_degree,
    output reg  [MAX_DEG-1:0]           c_taps_u,
    output reg  [MAX_DEG-1:0]           c_taps_v,
    output reg  [SEED_W-1:0]            c_seed_u,
    output reg  [SEED_W-1:0]            c_seed_v,
    output reg  [S_W-1:0]               c_spc,
    output reg  [R_W-1:0]               c_averages,
    output reg  [UID_W-1:0]             c_uid_bits,
    output reg  [MAX_UID-1:0]           c_uid,
    output reg  [LAG_W-1:0]             c_gate_start,
    output reg  [G_W-1:0]               c_gate_len,
    output reg  [G_W-1:0]               c_excl,
    output reg  [NGHOST*LAG_W-1:0]      c_gh_start,
    output reg  [NGHOST*LAG_W-1:0]      c_gh_len,
    output reg  [SH_W-1:0]              c_shift,
    output reg  [1:0]                   c_round,
    output reg  [OB_W-1:0]              c_out_bits,
    output reg  [P_W-1:0]               c_peaks
);
    always @(posedge clk)
        if (load) begin
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
        end
endmodule

`default_nettype wire
