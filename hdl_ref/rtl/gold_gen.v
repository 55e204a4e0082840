// gold_gen -- Gold code generator with UID polarity per code period.
//
// Two free-running Fibonacci LFSRs (lfsr_fib) of the same degree m produce the
// m-sequences u and v; their XOR is the Gold chip. Loading the seeds given by
// the model's jump-ahead, firmware_model.gold.gold_seeds(poly_u, poly_v, k),
// makes the pair output Gold member k (u[n] ^ v[(n - k) mod N]) from chip 0,
// with N = 2^m - 1 chips per code period. Member N (u alone) uses an all-zero
// v seed, member N+1 (v alone) an all-zero u seed.
//
// UID polarity: code period p (0..uid_bits-1, then repeating) is sent with its
// chips XORed with bit p of `uid` (polarity reversal of the whole period).
//
//   chip     = u ^ v ^ uid[period]     (bit 0 -> +1, bit 1 -> -1 on the wire)
//   chip_raw = u ^ v                   (the unmodulated Gold chip)
//
// Timing: outputs describe the current chip (combinational from registers);
// each clock with en=1 advances one chip, load (priority) restarts at chip 0 of
// period 0. Throughput one chip per clock, no latency after load.
`default_nettype none

module gold_gen #(
    parameter integer MAX_DEG = 11,                     // widest LFSR
    parameter integer MAX_UID = 8                       // most UID bits (code periods)
) (
    input  wire                         clk,
    input  wire                         load,
    input  wire                         en,
    input  wire [MAX_DEG-1:0]           seed_u,         // bit k-1 = stage k
    input  wire [MAX_DEG-1:0]           seed_v,
    input  wire [MAX_DEG-1:0]           taps_u,         // bit e-1 per exponent e
    input  wire [MAX_DEG-1:0]           taps_v,
    input  wire [$clog2(MAX_DEG+1)-1:0] degree,
    input  wire [MAX_UID-1:0]           uid,            // bit p = polarity of period p
    input  wire [$clog2(MAX_UID+1)-1:0] uid_bits,       // 1..MAX_UID periods per UID word
    output wire                         chip,
    output wire                         chip_raw,
    output reg  [MAX_DEG-1:0]           chip_index,     // 0..N-1
    output reg  [$clog2(MAX_UID+1)-1:0] period          // 0..uid_bits-1
);
    localparam integer UID_W = $clog2(MAX_UID + 1);

    wire u, v;
    wire [MAX_DEG-1:0] state_u, state_v;

    lfsr_fib #(.MAX_DEG(MAX_DEG)) lfsr_u (
        .clk(clk), .load(load), .en(en), .seed(seed_u), .taps(taps_u),
        .degree(degree), .out(u), .state(state_u)
    );
    lfsr_fib #(.MAX_DEG(MAX_DEG)) lfsr_v (
        .clk(clk), .load(load), .en(en), .seed(seed_v), .taps(taps_v),
        .degree(degree), .out(v), .state(state_v)
    );

    // Last chip index of a period: N - 1 = 2^degree - 2.
    wire [MAX_DEG:0]   n_last  = ({{MAX_DEG{1'b0}}, 1'b1} << degree)
                                 - {{(MAX_DEG-1){1'b0}}, 2'd2};
    wire [MAX_UID-1:0] uid_sel = {{(MAX_UID-1){1'b0}}, 1'b1} << period;
    wire               flip    = |(uid & uid_sel);

    always @(posedge clk) begin
        if (load) begin
            chip_index <= {MAX_DEG{1'b0}};
            period     <= {UID_W{1'b0}};
        end else if (en) begin
            if ({1'b0, chip_index} == n_last) begin
                chip_index <= {MAX_DEG{1'b0}};
                period     <= (period == uid_bits - 1'b1) ? {UID_W{1'b0}} : period + 1'b1;
            end else begin
                chip_index <= chip_index + 1'b1;
            end
        end
    end

    assign chip_raw = u ^ v;
    assign chip     = u ^ v ^ flip;

    // The full LFSR states are not needed here; keep lint quiet about them.
    wire unused_ok = &{1'b0, state_u, state_v};
endmodule

`default_nettype wire
