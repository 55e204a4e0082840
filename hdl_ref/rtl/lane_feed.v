`default_nettype none

// lane_feed -- one channel's registered copy of what its L lanes read every clock: the
// stage-2 box sum of the processing buffer's S bank words (its own buffer select and S
// mask), the stage-2 valid, the "all" flag and the run's clear. rx_top keeps one per
// channel, so no net reaches the K L lane adders from one register; each copy is fed by
// registers only (the RAM output registers, proc_buf, s_on, vq, aq), and keep_hierarchy
// stops synthesis from merging the copies.
//
// Timing, the same as rx_top's central stage 2: `q` is stage 1b's `rdq` (loaded every
// clock: it is read only in the clock after `vq`, that is after `vr`), `box` is `box2`,
// `v` is `v2`, `a` is `a2` and `clr` is `ln_clr`. `pb` and `on` are one clock behind
// proc_buf and s_on; both change only while no stream is in the pipeline (proc_buf at a
// column's end, at least 4 clocks before the next stream's first RAM word; s_on while
// the configuration is latched), so they are equal whenever `q` and `box` are read.
(* keep_hierarchy *)
module lane_feed #(
    parameter integer MAX_S = 4,
    parameter integer AVG_W = 16,
    parameter integer BOX_W = 18
) (
    input  wire                    clk,
    input  wire                    rst,
    input  wire [2*MAX_S*AVG_W-1:0] rd,     // bank (b, s) at (b*MAX_S + s)*AVG_W
    input  wire                    proc_buf,
    input  wire [MAX_S-1:0]        s_on,    // bank s is summed (s < S)
    input  wire                    vq,
    input  wire                    aq,
    input  wire                    clr_nx,
    output reg signed [BOX_W-1:0]  box,
    output reg                     v,
    output reg                     a,
    output reg                     clr
);
    reg                   pb;
    reg [MAX_S-1:0]       on;
    reg [MAX_S*AVG_W-1:0] q;
    reg signed [BOX_W-1:0] sum;
    integer i;
    always @(*) begin
        sum = {BOX_W{1'b0}};
        for (i = 0; i < MAX_S; i = i + 1)
            if (on[i])
                sum = sum + {{(BOX_W-AVG_W){q[i*AVG_W + AVG_W-1]}}, q[i*AVG_W +: AVG_W]};
    end
    always @(posedge clk) begin
        pb  <= proc_buf;
        on  <= s_on;
        q   <= pb ? rd[MAX_S*AVG_W +: MAX_S*AVG_W] : rd[0 +: MAX_S*AVG_W];
        box <= sum;
        v   <= !rst && vq;
        a   <= aq;
        clr <= !rst && clr_nx;
    end
endmodule

`default_nettype wire
