// adc_rx -- ADC input deserialiser and clock-domain crossing into the fabric clock.
//
//   adc_clk domain (one sample a clock)        |  clk domain (fabric, P_IN samples a clock)
//                                              |
//   adc_data --> pack P_IN samples --> word ---+--> mem[2^AW] (written in adc_clk,
//   adc_valid    (the earliest at bits [0 +:   |    read in clk)  --> m_data, m_valid
//                 ADC_W])                      |                      <-- m_ready
//   wbin/wgray (write pointer, Gray) ---- 2 flops ---> rq2_wgray: empty
//   wq2_rgray  <--- 2 flops ------------- rbin/rgray (read pointer, Gray)
//   full, ovf (sticky) ------------------ 2 flops ---> err_overflow
//   clear pulse <-- 2 flops + edge <----- clr_tog (toggles on clear_ovf)
//
// An asynchronous FIFO in the textbook form (C. Cummings, "Simulation and Synthesis
// Techniques for Asynchronous FIFO Design", SNUG 2002): AW + 1 bit pointers, each
// crossing as a registered Gray code through two flip-flops, so at most one bit of a
// crossing pointer changes per clock and the receiver sees the old or the new value;
// empty and full are computed from the next pointer and registered (a pointer seen
// late only makes the FIFO look fuller or emptier than it is: never a lost or repeated
// word). A word completed while the FIFO is full is not written: the sticky ovf is set
// in that adc_clk clock, crosses to clk as err_overflow (2 flops), and holds until
// clear_ovf (a one-clock pulse in clk, carried as a toggle; an overflow in the clock the
// clear arrives wins). Nothing is dropped without the flag. Resets are synchronous, one
// per domain (adc_rst in adc_clk, rst in clk), asserted together.
`default_nettype none

module adc_rx #(
    parameter integer ADC_W = 12,
    parameter integer P_IN  = 4,
    parameter integer AW    = 4         // FIFO depth 2^AW words of P_IN samples (AW >= 2)
) (
    input  wire                   adc_clk,
    input  wire                   adc_rst,
    input  wire                   adc_valid,   // one sample in this adc_clk clock
    input  wire [ADC_W-1:0]       adc_data,

    input  wire                   clk,
    input  wire                   rst,
    output wire                   m_valid,
    output wire [P_IN*ADC_W-1:0]  m_data,      // sample k of the word at [k*ADC_W +: ADC_W]
    input  wire                   m_ready,
    input  wire                   clear_ovf,   // clk: clears err_overflow (one-clock pulse)
    output wire                   err_overflow,// clk: sticky, a word was lost
    output wire                   adc_full     // adc_clk: a word completed now is not written
);
    localparam integer WW = P_IN * ADC_W;
    localparam integer CW = (P_IN > 1) ? $clog2(P_IN) : 1;
    localparam [31:0]  P_M1 = P_IN - 1;
    localparam [CW-1:0] LAST = P_M1[CW-1:0];

    generate
        if (AW < 2) begin : g_aw_too_small
            adc_rx_needs_aw_of_at_least_2 bad ();
        end
    endgenerate

    reg [WW-1:0] mem [0:(1 << AW)-1];

    // ---------------- adc_clk domain: pack, write, full, overflow ----------------
    reg  [CW-1:0] cnt;
    reg  [AW:0]   wbin, wgray;
    reg  [AW:0]   wq1_rgray, wq2_rgray;
    reg           full, ovf;
    reg  [2:0]    clr_sync;
    wire          word = adc_valid && (cnt == LAST);
    wire [WW-1:0] wdata;
    wire          push = word && !full;
    wire [AW:0]   wbin_nx  = wbin + {{AW{1'b0}}, push};
    wire [AW:0]   wgray_nx = (wbin_nx >> 1) ^ wbin_nx;
    wire          clr_adc  = clr_sync[2] ^ clr_sync[1];

    generate
        if (P_IN > 1) begin : g_pack
            reg [WW-ADC_W-1:0] pack;        // the clock's earlier samples
            always @(posedge adc_clk)
                if (adc_valid && !word)
                    pack[cnt * ADC_W +: ADC_W] <= adc_data;
            assign wdata = {adc_data, pack};
        end else begin : g_one
            assign wdata = adc_data;
        end
    endgenerate

    always @(posedge adc_clk) begin
        if (push)
            mem[wbin[AW-1:0]] <= wdata;
        wq1_rgray <= rgray;                 // read pointer into adc_clk: two flip-flops
        wq2_rgray <= wq1_rgray;
        clr_sync  <= adc_rst ? 3'b000 : {clr_sync[1:0], clr_tog};
        if (adc_rst) begin
            cnt   <= {CW{1'b0}};
            wbin  <= {(AW+1){1'b0}};
            wgray <= {(AW+1){1'b0}};
            full  <= 1'b0;
            ovf   <= 1'b0;
        end else begin
            if (adc_valid)
                cnt <= word ? {CW{1'b0}} : cnt + 1'b1;
            wbin  <= wbin_nx;
            wgray <= wgray_nx;
            full  <= (wgray_nx == {~wq2_rgray[AW:AW-1], wq2_rgray[AW-2:0]});
            ovf   <= (ovf && !clr_adc) || (word && full);
        end
    end

    // ---------------- clk domain: read, empty, flag ----------------
    reg  [AW:0] rbin, rgray;
    reg  [AW:0] rq1_wgray, rq2_wgray;
    reg         empty;
    reg         clr_tog;
    reg  [1:0]  ovf_sync;
    wire        pop      = m_ready && !empty;
    wire [AW:0] rbin_nx  = rbin + {{AW{1'b0}}, pop};
    wire [AW:0] rgray_nx = (rbin_nx >> 1) ^ rbin_nx;

    always @(posedge clk) begin
        rq1_wgray <= wgray;                 // write pointer into clk: two flip-flops
        rq2_wgray <= rq1_wgray;
        ovf_sync  <= rst ? 2'b00 : {ovf_sync[0], ovf};   // the flag into clk: two flip-flops
        if (rst) begin
            rbin    <= {(AW+1){1'b0}};
            rgray   <= {(AW+1){1'b0}};
            empty   <= 1'b1;
            clr_tog <= 1'b0;
        end else begin
            rbin    <= rbin_nx;
            rgray   <= rgray_nx;
            empty   <= (rgray_nx == rq2_wgray);
            clr_tog <= clr_tog ^ clear_ovf;
        end
    end

    assign m_valid      = !empty;
    assign m_data       = mem[rbin[AW-1:0]];
    assign err_overflow = ovf_sync[1];
    assign adc_full     = full;
endmodule

`default_nettype wire
