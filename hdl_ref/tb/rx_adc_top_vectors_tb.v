// rx_adc_top_vectors_tb -- the fixed-rate ADC bench under Icarus: two unrelated clocks
// from Verilog delays around rx_adc_top_vectors_check (the stimulus and the checks, where
// the files, plusargs and the verdict line are described).
//
// Plain Verilog-2005, no Python: compile with -I <vector folder> (params.vh) and run with
//   +VEC=<folder>/ [+ADC_PS=4000] [+FAB_PS=<ps>] [+PHASE_PS=<ps>] [+GAP_EVERY=<n>
//   +GAP_LEN=<clocks>]
// (ADC and fabric clock periods and the fabric clock's start offset, picoseconds; the
// fabric period defaults to P_IN samples: P_IN ADC periods, P_IN / 2 with -DVEC_PINS, where
// the ADC clock is the DDR data clock).
`timescale 1ns/1ps
`default_nettype none

module rx_adc_top_vectors_tb;
    reg clk = 1'b0, adc_clk = 1'b0;
    integer adc_ps = 4000, fab_ps = 0, phase_ps = 0;
    realtime adc_half, fab_half;

    rx_adc_top_vectors_check check (.adc_clk(adc_clk), .clk(clk));

    initial begin
        if (!$value$plusargs("ADC_PS=%d", adc_ps)) adc_ps = 4000;
        if (!$value$plusargs("FAB_PS=%d", fab_ps))   // P_IN samples: 2 per DDR clock
            fab_ps = (check.PINS ? check.P / 2 : check.P) * adc_ps;
        if (!$value$plusargs("PHASE_PS=%d", phase_ps)) phase_ps = 0;
        adc_half = adc_ps / 2000.0;
        fab_half = fab_ps / 2000.0;
        fork
            forever #(adc_half) adc_clk = ~adc_clk;
            begin
                #(phase_ps / 1000.0);
                forever #(fab_half) clk = ~clk;
            end
        join
    end
endmodule

`default_nettype wire
