// r_min_tb -- prints r_min_rom's table: "R_MIN <value>", then "<degree> <spc> <r_min>" for
// every degree and samples_per_chip code of the build (parameters set with iverilog -P).
// tests/hdl_ref/test_adc_top.py compares every line with cdma_lidar.hdl_ref.adc_top.r_min.
`timescale 1ns/1ps
`default_nettype none

module r_min_tb #(
    parameter integer K = 4, L = 2, P_IN = 1, MAX_DEG = 11, MAX_S = 4, MAX_R = 16,
    parameter integer MAX_G = 64, MAX_P = 1
);
    localparam integer DEG_W = $clog2(MAX_DEG + 1), S_W = $clog2(MAX_S + 1);
    localparam integer R_W = $clog2(MAX_R + 1);
    reg  [DEG_W-1:0] degree = {DEG_W{1'b0}};
    reg  [S_W-1:0]   spc = {S_W{1'b0}};
    wire [R_W:0]     r_min;
    r_min_rom #(.K(K), .L(L), .P_IN(P_IN), .MAX_DEG(MAX_DEG), .MAX_S(MAX_S), .MAX_R(MAX_R),
                .MAX_G(MAX_G), .MAX_P(MAX_P)) dut (.degree(degree), .spc(spc), .r_min(r_min));
    integer d, s;
    initial begin
        $display("R_MIN %0d", dut.R_MIN);
        for (d = 0; d < (1 << DEG_W); d = d + 1)
            for (s = 0; s < (1 << S_W); s = s + 1) begin
                degree = d;
                spc = s;
                #1 $display("%0d %0d %0d", d, s, r_min);
            end
        $finish;
    end
endmodule

`default_nettype wire
