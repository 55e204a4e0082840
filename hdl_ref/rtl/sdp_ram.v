// sdp_ram -- simple dual-port RAM: one synchronous write port, one synchronous
// read port, both on clk. Read data appears one clock after the address; a read
// of the address being written in the same clock returns the old word. Written
// so that yosys infers block RAM (memory_bram / memory_libmap) on FPGA targets.
`default_nettype none

module sdp_ram #(
    parameter integer WIDTH = 16,
    parameter integer DEPTH = 1024,
    parameter integer AW    = $clog2(DEPTH)     // derived: address width
) (
    input  wire                     clk,
    input  wire                     we,
    input  wire [AW-1:0]            waddr,
    input  wire [WIDTH-1:0]         wdata,
    input  wire [AW-1:0]            raddr,
    output reg  [WIDTH-1:0]         rdata
);
    reg [WIDTH-1:0] mem [0:DEPTH-1];

    always @(posedge clk) begin
        if (we)
            mem[waddr] <= wdata;
        rdata <= mem[raddr];
    end
endmodule

`default_nettype wire
