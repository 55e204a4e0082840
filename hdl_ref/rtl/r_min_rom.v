// r_min_rom -- the smallest number of averages R with which rx_top keeps up with a
// fixed-rate source (docs/hdl.md, "R_MIN"), for every degree and samples_per_chip.
//
// rx_top keeps up (no back-pressure) when process + 1 <= R n N S / P_IN, with
//   process = groups n (N + L - 1) + K L + 17 + K (P (G + 4) + G + 7)
//   groups  = sum over phases ph < min(S, G + 2) of ceil(ceil((G + 2 - ph) / S) / L)
// (cosim.top_timing). process / (n N S) grows with the gate G and the peaks P and
// shrinks with the UID periods n, so the bound is taken at G = MAX_G, P = MAX_P,
// n = 1: any configuration of the build with R >= r_min(degree, S) keeps up.
// r_min = MAX_R + 1 (no R fits) where the build cannot run the configuration at all:
// degree < 3 or > MAX_DEG, S = 0, S > MAX_S, S not a multiple of P_IN, or K L > N - 2
// (the result serializer, docs/hdl.md). The Python side is cosim.top_r_min, tested to
// agree over a sweep of builds. R_MIN (the localparam) is the build's headline value:
// the largest degree at S = MAX_S.
`default_nettype none

module r_min_rom #(
    parameter integer K       = 4,
    parameter integer L       = 2,
    parameter integer P_IN    = 1,
    parameter integer MAX_DEG = 11,
    parameter integer MAX_S   = 4,
    parameter integer MAX_R   = 16,
    parameter integer MAX_G   = 64,
    parameter integer MAX_P   = 1,
    parameter integer DEG_W   = $clog2(MAX_DEG + 1),
    parameter integer S_W     = $clog2(MAX_S + 1),
    parameter integer R_W     = $clog2(MAX_R + 1)
) (
    input  wire [DEG_W-1:0] degree,
    input  wire [S_W-1:0]   spc,
    output wire [R_W:0]     r_min       // MAX_R + 1: refused whatever R
);
    function integer r_min_of(input integer deg, input integer s);
        integer n, ph, groups, clocks, r;
        begin
            n = (1 << deg) - 1;
            if (deg < 3 || deg > MAX_DEG || s < 1 || s > MAX_S || (s % P_IN) != 0
                || K * L > n - 2) begin
                r = MAX_R + 1;
            end else begin
                groups = 0;
                for (ph = 0; ph < s && ph < MAX_G + 2; ph = ph + 1)
                    groups = groups + ((MAX_G + 2 - ph + s - 1) / s + L - 1) / L;
                clocks = groups * (n + L - 1) + K * L + 17
                          + K * (MAX_P * (MAX_G + 4) + MAX_G + 7);
                // R n N S / P_IN >= process + 1 at n = 1 (clocks: process)
                r = ((clocks + 1) * P_IN + n * s - 1) / (n * s);
                if (r > MAX_R)
                    r = MAX_R + 1;
            end
            r_min_of = r;
        end
    endfunction

    /* verilator lint_off UNUSEDPARAM */
    localparam integer R_MIN = r_min_of(MAX_DEG, MAX_S);   // read by the benches
    /* verilator lint_on UNUSEDPARAM */
    localparam integer ND = 1 << DEG_W, NS_ = 1 << S_W, RW1 = R_W + 1;

    wire [ND*NS_*RW1-1:0] table_;
    genvar gd, gs;
    generate
        for (gd = 0; gd < ND; gd = gd + 1) begin : g_deg
            for (gs = 0; gs < NS_; gs = gs + 1) begin : g_spc
                localparam integer RM = r_min_of(gd, gs);
                localparam [RW1-1:0] RMV = RM[RW1-1:0];
                assign table_[(gd * NS_ + gs) * RW1 +: RW1] = RMV;
            end
        end
    endgenerate
    assign r_min = table_[{degree, spc} * RW1 +: RW1];
endmodule

`default_nettype wire
