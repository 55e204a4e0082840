// ecp5_gearing_models -- behavioural simulation models of three Lattice ECP5 I/O gearing
// primitives, for Icarus Verilog and Verilator (no delays). OUR models, written from the
// behaviour Lattice documents in FPGA-TN-02035 ("ECP5 and ECP5-5G High-Speed I/O
// Interface"), not Lattice's simulation library: Yosys ships these cells as black boxes
// only (techlibs/ecp5 cells_bb.v), and synthesis and place and route use the real cells.
// Their latencies are ours; the order of the bits (Q0 the earliest) is Lattice's.
//
//   ECLKSYNCB  ECLKO = ECLKI, held low while STOP.
//   CLKDIVF    DIV "2.0" only: CDIVX = CLKI / 2, toggling on CLKI's rising edges and 0
//              after configuration (GSR) and while RST; a rising CLKI edge with ALIGNWD
//              high does not toggle it (the divided clock slips one CLKI period, which
//              rotates every IDDRX2F's word by 2 bits; unused here).
//   IDDRX2F    D sampled on every ECLK edge, rising and falling. At the ECLK rising edge
//              at which SCLK falls (SCLK is high before it), Q0..Q3 take the 4 bits of
//              the two ECLK periods before it, Q0 the earliest: D at the rising edge
//              one ECLK period before SCLK's rising edge, then the falling edge, the
//              rising edge with SCLK's, the falling edge. So Q changes half an SCLK
//              period before the SCLK rising edge that samples it in the fabric (no race
//              between the two clocks in a zero-delay simulation). RST clears Q.
`default_nettype none
/* verilator lint_off DECLFILENAME */
/* verilator lint_off UNUSEDPARAM */

module ECLKSYNCB (
    input  wire ECLKI,
    input  wire STOP,
    output wire ECLKO
);
    assign ECLKO = ECLKI && !STOP;
endmodule

module CLKDIVF #(
    parameter GSR = "DISABLED",
    parameter DIV = "2.0"
) (
    input  wire CLKI,
    input  wire RST,
    input  wire ALIGNWD,
    output reg  CDIVX
);
    generate
        if (DIV != "2.0") begin : g_div_not_modelled
            CLKDIVF_model_has_div_2_only bad ();
        end
    endgenerate
    initial CDIVX = 1'b0;
    always @(posedge CLKI)
        CDIVX <= !RST && (CDIVX ^ !ALIGNWD);
endmodule

module IDDRX2F #(
    parameter GSR = "ENABLED"
) (
    input  wire D,
    input  wire SCLK,
    input  wire ECLK,
    input  wire RST,
    /* verilator lint_off UNUSEDSIGNAL */
    input  wire ALIGNWD,                 // word alignment is CLKDIVF's: unused here
    /* verilator lint_on UNUSEDSIGNAL */
    output reg  Q0,
    output reg  Q1,
    output reg  Q2,
    output reg  Q3
);
    reg r, f, pr, pf;                    // the last rising and falling samples, and before
    always @(negedge ECLK)
        f <= D;
    always @(posedge ECLK) begin
        r  <= D;
        pr <= r;
        pf <= f;
        if (RST)
            {Q3, Q2, Q1, Q0} <= 4'b0000;
        else if (SCLK)
            {Q3, Q2, Q1, Q0} <= {f, r, pf, pr};
    end
endmodule

/* verilator lint_on UNUSEDPARAM */
/* verilator lint_on DECLFILENAME */
`default_nettype wire
