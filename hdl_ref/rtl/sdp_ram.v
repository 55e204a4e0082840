// sdp_ram -- simple dual-port RAM: one synchronous write port, one synchronous
// read port, both on clk. Read data appears one clock after the address; a read
// of the address being written in the same clock returns the old word. Written
// so that yosys infers block RAM (memory_bram / memory_libmap) on FPGA targets.
// OUTREG = 1 adds the block RAM's output register (data two clocks after the
// address): block RAM clock-to-out is slow (5.8 ns on ECP5), so fast designs use it.
`default_nettype none

module sdp_ram #(
    parameter integer WIDTH  = 16,
    parameter integer DEPTH  = 1024,
    parameter integer OUTREG = 0,               // 1: one more output register (latency 2)
    parameter integer AW     = $clog2(DEPTH)    // derived: address width
) (
    input  wire                     clk,
    input  wire                     we,
    input  wire [AW-1:0]            waddr,
    input  wire [WIDTH-1:0]         wdata,
    input  wire [AW-1:0]            raddr,
    output wire [WIDTH-1:0]         rdata
);
    reg [WIDTH-1:0] mem [0:DEPTH-1];
    reg [WIDTH-1:0] rd0;

    always @(posedge clk) begin
        if (we)
            mem[waddr] <= wdata;
        rd0 <= mem[raddr];
    end

    generate
        if (OUTREG != 0) begin : g_outreg
            reg [WIDTH-1:0] rd1;
            always @(posedge clk)
                rd1 <= rd0;
            assign rdata = rd1;
        end else begin : g_direct
            assign rdata = rd0;
        end
    endgenerate
endmodule

`default_nettype wire
