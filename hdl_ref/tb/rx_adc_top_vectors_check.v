// rx_adc_top_vectors_check -- the fixed-rate ADC bench's stimulus and checks, without
// clocks or delays: plays `cdma-lidar hdl vectors` files into rx_adc_top and compares.
// Its two clocks come from outside, so one copy serves both simulators:
// rx_adc_top_vectors_tb.v (Icarus, Verilog delays) and rx_adc_top_vectors_main.cpp
// (Verilator without --timing, a picosecond loop in C++). Compile with -I <vector folder>
// (params.vh) and run with +VEC=<folder>/ [+GAP_EVERY=<n> +GAP_LEN=<clocks>] [+RUNS=<n>
// [+RESTART=<clocks>]].
//
// The ADC source cannot wait: from the first adc_clk edge after rx_adc_top is started, one
// sample every adc_clk clock, every sample of adc.hex, then nothing; with GAP_EVERY,
// adc_valid drops for GAP_LEN adc_clk clocks after every GAP_EVERY samples (a converter
// whose data-valid pauses). With -DVEC_PINS (rx_adc_top's PINS = 1, P_IN = 4) adc_clk is
// the converter's DDR data clock and the source sends one sample on every edge of it, never
// stopping (zeros before and after adc.hex): sample 0 leaves on the first falling edge at
// which adc_pins' run_s reads 1, as from a transmitter started by that sclk edge (adc_pins.v,
// "Word alignment"); no gaps. Prints one line
//   rx_adc_top vectors: PASS <words> words compared, <n> samples taken
// or FAIL (first differences before it; "overflow" when err_overflow rises, "no done"
// after VEC_MAX_CLOCKS fabric clocks, twice the model's schedule), or
//   rx_adc_top vectors: REFUSED (err_config)
// when the configuration is refused at start (busy never rises), and calls $finish.
`default_nettype none
`include "params.vh"
`ifndef VEC_P
`define VEC_P 1
`endif
`ifndef VEC_MAX_CLOCKS
`define VEC_MAX_CLOCKS 100000000
`endif

module rx_adc_top_vectors_check (
    input wire adc_clk,
    input wire clk
);
    localparam integer K = `VEC_K, MAX_DEG = `VEC_MAX_DEG, MAX_S = `VEC_MAX_S;
    localparam integer MAX_UID = `VEC_MAX_UID, MAX_R = `VEC_MAX_R, MAX_G = `VEC_MAX_G;
    localparam integer MAX_P = `VEC_MAX_P, NGHOST = `VEC_NGHOST;
    localparam integer ADC_W = `VEC_ADC_W, OUT_W = `VEC_OUT_W;
    localparam integer DEG_W = $clog2(MAX_DEG + 1);
    localparam integer MAX_NS = ((1 << MAX_DEG) - 1) * MAX_S;
    localparam integer LAG_W = $clog2(MAX_NS + 1);
    localparam integer S_W = $clog2(MAX_S + 1), UID_W = $clog2(MAX_UID + 1);
    localparam integer R_W = $clog2(MAX_R + 1), G_W = $clog2(MAX_G + 1);
    localparam integer P_W = $clog2(MAX_P + 1), K_W = (K > 1) ? $clog2(K) : 1;
    localparam integer NRP = `VEC_N_RES_PORTS;
    localparam integer P = `VEC_P;
`ifdef VEC_PINS
    localparam integer PINS = 1;
`else
    localparam integer PINS = 0;
`endif

    reg [`VEC_CFG_W-1:0] cfg_mem  [0:`VEC_N_CFG-1];
    reg [ADC_W-1:0]      adc_mem  [0:`VEC_N_ADC-1];
    reg [OUT_W-1:0]      corr_mem [0:`VEC_N_CORR-1];
    reg [`VEC_RES_W-1:0] res_mem  [0:`VEC_N_RES-1];

    reg rst = 1'b1, start = 1'b0;
    reg adc_valid = 1'b0;
    reg [ADC_W-1:0] adc_data = {ADC_W{1'b0}};
    wire corr_valid, res_valid, busy, done, col_start, err_overrun, err_overflow, err_config;
    wire [K_W-1:0] corr_channel, res_channel;
    wire [G_W-1:0] corr_index;
    wire [OUT_W-1:0] corr_data;
    wire [MAX_P-1:0] res_found;
    wire [MAX_P*LAG_W-1:0] res_lag;
    wire [MAX_P*G_W-1:0] res_index;
    wire [MAX_P*OUT_W-1:0] res_peak;
    wire [MAX_P*MAX_UID-1:0] res_neg, res_nz;
    wire [OUT_W-1:0] res_nb_lo, res_nb_hi;
    wire [G_W-1:0] res_noise_count;
    wire [OUT_W+G_W-1:0] res_noise_sum;
    wire [2*OUT_W+G_W-1:0] res_noise_sumsq;
    wire [MAX_UID-1:0] res_uid_observed;
    wire res_uid_match, res_saturated;

    rx_adc_top #(.K(K), .L(`VEC_L), .P_IN(P), .MAX_DEG(MAX_DEG), .MAX_S(MAX_S),
                 .MAX_UID(MAX_UID), .MAX_R(MAX_R), .MAX_G(MAX_G), .MAX_P(MAX_P),
                 .NGHOST(NGHOST), .ADC_W(ADC_W), .OUT_W(OUT_W), .PINS(PINS)) dut (
        .adc_clk(adc_clk), .adc_valid(adc_valid), .adc_data(adc_data),
        .clk(clk), .rst(rst), .start(start), .stop(1'b0), .clear_err(1'b0),
        .cfg_columns(cfg_mem[0][15:0]), .cfg_degree(cfg_mem[1][DEG_W-1:0]),
        .cfg_taps_u(cfg_mem[2][MAX_DEG-1:0]), .cfg_taps_v(cfg_mem[3][MAX_DEG-1:0]),
        .cfg_seed_u(cfg_mem[4][K*MAX_DEG-1:0]), .cfg_seed_v(cfg_mem[5][K*MAX_DEG-1:0]),
        .cfg_spc(cfg_mem[6][S_W-1:0]), .cfg_averages(cfg_mem[7][R_W-1:0]),
        .cfg_uid_bits(cfg_mem[8][UID_W-1:0]), .cfg_uid(cfg_mem[9][MAX_UID-1:0]),
        .cfg_gate_start(cfg_mem[10][LAG_W-1:0]), .cfg_gate_len(cfg_mem[11][G_W-1:0]),
        .cfg_peak_exclude(cfg_mem[12][G_W-1:0]),
        .cfg_ghost_start(cfg_mem[13][NGHOST*LAG_W-1:0]),
        .cfg_ghost_len(cfg_mem[14][NGHOST*LAG_W-1:0]),
        .cfg_out_shift(cfg_mem[15][5:0]), .cfg_rounding(cfg_mem[16][1:0]),
        .cfg_out_bits(cfg_mem[17][5:0]), .cfg_peaks(cfg_mem[18][P_W-1:0]),
        .corr_valid(corr_valid), .corr_channel(corr_channel), .corr_index(corr_index),
        .corr_data(corr_data),
        .res_valid(res_valid), .res_channel(res_channel), .res_found(res_found),
        .res_lag(res_lag), .res_index(res_index), .res_peak(res_peak), .res_neg(res_neg),
        .res_nz(res_nz), .res_nb_lo(res_nb_lo), .res_nb_hi(res_nb_hi),
        .res_noise_count(res_noise_count), .res_noise_sum(res_noise_sum),
        .res_noise_sumsq(res_noise_sumsq), .res_uid_observed(res_uid_observed),
        .res_uid_match(res_uid_match), .res_saturated(res_saturated),
        .busy(busy), .done(done), .col_start(col_start), .err_overrun(err_overrun),
        .err_overflow(err_overflow), .err_config(err_config)
    );

    integer n_adc = 0, n_corr = 0, n_res = 0, errors = 0, words = 0, taken = 0, p;
    reg [`VEC_RES_W-1:0] got [0:NRP-1];
    reg [8*512-1:0] dir;
    reg started = 1'b0;

    task check(input [`VEC_RES_W-1:0] have, input [`VEC_RES_W-1:0] want, input integer line,
               input [8*8-1:0] what);
        begin
            words = words + 1;
            if (have !== want) begin
                errors = errors + 1;
                if (errors <= 10)
                    $display("rx_adc_top vectors: %0s line %0d: got %h, expected %h", what,
                             line, have, want);
            end
        end
    endtask

    integer gap_every = 0, gap_len = 0;
    initial begin
        if (!$value$plusargs("VEC=%s", dir))
            dir = "";
        if (!$value$plusargs("GAP_EVERY=%d", gap_every)) gap_every = 0;
        if (!$value$plusargs("GAP_LEN=%d", gap_len)) gap_len = 0;
        if (!$value$plusargs("RUNS=%d", runs)) runs = 1;
        if (!$value$plusargs("RESTART=%d", restart)) restart = 24;
        $readmemh({dir, "config.hex"}, cfg_mem);
        $readmemh({dir, "adc.hex"}, adc_mem);
        $readmemh({dir, "corr.hex"}, corr_mem);
        $readmemh({dir, "results.hex"}, res_mem);
    end

    // the ADC: one sample every adc_clk clock once started, never waiting (but pausing
    // GAP_LEN clocks after every GAP_EVERY samples when asked)
    integer gap_left = 0;
`ifdef VEC_PINS
    // the DDR pins: a sample on every edge from the acquisition's first one on (a macro,
    // not a generate branch: Verilator resolves the reference to run_s in either)
    reg go = 1'b0, armed = 1'b1;
    always @(posedge adc_clk or negedge adc_clk) begin
        if (!adc_clk && !rst) begin
            if (!dut.g_pins.pins.run_s) begin
                armed = 1'b1;
            end else if (armed) begin           // an acquisition starts: sample 0 now
                go = 1'b1;
                armed = 1'b0;
                n_adc = 0;
            end
        end
        if (go && n_adc < `VEC_N_ADC) begin
            adc_data <= adc_mem[n_adc];
            n_adc = n_adc + 1;
        end else begin
            adc_data <= {ADC_W{1'b0}};
        end
    end
`else
    always @(posedge adc_clk) begin
        if (gap_left > 0) begin
            adc_valid <= 1'b0;
            gap_left = gap_left - 1;
        end else begin
            adc_valid <= started && (n_adc < `VEC_N_ADC);
            if (started && n_adc < `VEC_N_ADC) begin
                adc_data <= adc_mem[n_adc];
                n_adc = n_adc + 1;
                if (gap_every > 0 && n_adc % gap_every == 0)
                    gap_left = gap_len;
            end
        end
    end
`endif

    // the fabric side: reset for 8 clocks, start in the 11th, busy by the 15th (with the
    // DDR pins IDLE = 40 clocks later: the converter runs from reset on, and none of the
    // words it sends before start may reach rx_top); with +RUNS=<n> (DDR pins only) the
    // acquisition is started again +RESTART=<n> clocks (24) after each done, the same samples
    // from the pins and the same words expected (adc_pins.v: a start waits 2^FIFO_AW + 8
    // clocks for the last capture's words to be drained); watchdog
    localparam integer IDLE = PINS ? 40 : 0;
    integer clocks = 0, start_at = 10 + IDLE, runs = 1, run_no = 0, total = 0, restart = 24;
    always @(posedge clk) begin
        clocks = clocks + 1;
        if (clocks == 8) rst <= 1'b0;
        start <= (clocks == start_at);
        if (clocks == start_at + 4) begin
            if (!busy) begin
                $display("rx_adc_top vectors: %0s", err_config ? "REFUSED (err_config)"
                                                                : "FAIL not started");
                $finish;
            end
            started <= 1'b1;
        end
        if (clocks - start_at > `VEC_MAX_CLOCKS + 100) begin
            $display("rx_adc_top vectors: FAIL no done in %0d clocks (watchdog; corr %0d of %0d, results %0d of %0d)",
                     clocks - 1, n_corr, `VEC_N_CORR, n_res, `VEC_N_RES);
            $finish;
        end
        if (err_overflow) begin
            $display("rx_adc_top vectors: FAIL overflow (err_overflow) after %0d samples taken of %0d",
                     taken, `VEC_N_ADC);
            $finish;
        end
    end
    // sinks
    always @(posedge clk) begin
        if (dut.s_valid && dut.s_ready)
            taken = taken + P;
        if (corr_valid) begin
            check({{(`VEC_RES_W-OUT_W){1'b0}}, corr_data},
                  {{(`VEC_RES_W-OUT_W){1'b0}}, corr_mem[n_corr]}, n_corr + 1, "corr");
            n_corr = n_corr + 1;
        end
        if (res_valid) begin
            got[0] = res_found;  got[1] = res_lag;  got[2] = res_index;  got[3] = res_peak;
            got[4] = res_neg;    got[5] = res_nz;   got[6] = res_nb_lo;  got[7] = res_nb_hi;
            got[8] = res_noise_count;  got[9] = res_noise_sum;  got[10] = res_noise_sumsq;
            got[11] = res_uid_observed;  got[12] = res_uid_match;  got[13] = res_saturated;
            for (p = 0; p < NRP; p = p + 1)
                check(got[p], res_mem[n_res + p], n_res + p + 1, "results");
            n_res = n_res + NRP;
        end
        if (done || err_overrun) begin
            if (n_corr != `VEC_N_CORR || n_res != `VEC_N_RES || err_overrun
                || taken != `VEC_N_ADC)
                errors = errors + 1;
            total = total + taken;
            if (errors == 0 && run_no + 1 < runs) begin     // the next acquisition
                run_no = run_no + 1;
                taken = 0;
                n_corr = 0;
                n_res = 0;
                start_at = clocks + restart;
            end else begin
                if (errors == 0)
                    $display("rx_adc_top vectors: PASS %0d words compared, %0d samples taken",
                             words, total);
                else
                    $display("rx_adc_top vectors: FAIL %0d of %0d words differ (corr %0d of %0d, results %0d of %0d, samples %0d of %0d)",
                             errors, words, n_corr, `VEC_N_CORR, n_res, `VEC_N_RES, taken,
                             `VEC_N_ADC);
                $finish;
            end
        end
    end
endmodule

`default_nettype wire
