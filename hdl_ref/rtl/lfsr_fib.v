// lfsr_fib -- Fibonacci linear feedback shift register with seed load and enable.
//
// Stages are numbered 1..degree; state[k-1] holds stage k. On every enabled
// clock the new stage-1 bit is the XOR of the stages named by the polynomial's
// exponents and every other stage moves up by one. The output is stage
// `degree`, so chip n is the output after n enabled clocks from the seed:
//
//        +-------------- XOR of tapped stages <----------------+
//        |                                                      |
//        v                                                      |
//     [ s1 ] -> [ s2 ] -> ... -> [ s(degree) ] ---> out (chip)  |
//        |         |                  |                         |
//        +---------+------ taps ------+-------------------------+
//
// Polynomial x^11 + x^2 + 1 (exponents (11, 2)) is taps = (1 << 10) | (1 << 1)
// and degree = 11. The polynomial and degree are run-time inputs (configuration
// registers), so one build serves every polynomial up to MAX_DEG; stages above
// `degree` are never tapped nor output. Seeds are bit strings stage 1 first:
// seed bit 0 is stage 1.
//
// Timing: `out` is combinational from the state register; load has priority
// over en; there is no reset (load a seed first). Throughput one chip per clock.
`default_nettype none

module lfsr_fib #(
    parameter integer MAX_DEG = 11                      // widest register (stages)
) (
    input  wire                         clk,
    input  wire                         load,           // state <= seed
    input  wire                         en,             // advance one chip
    input  wire [MAX_DEG-1:0]           seed,           // bit k-1 = stage k
    input  wire [MAX_DEG-1:0]           taps,           // bit e-1 set for each exponent e
    input  wire [$clog2(MAX_DEG+1)-1:0] degree,         // 2..MAX_DEG, highest exponent
    output wire                         out,            // stage `degree` = current chip
    output wire [MAX_DEG-1:0]           state
);
    reg  [MAX_DEG-1:0] st;
    wire               fb = ^(st & taps);

    always @(posedge clk) begin
        if (load)
            st <= seed;
        else if (en)
            st <= {st[MAX_DEG-2:0], fb};
    end

    // One-hot select of stage `degree`.
    wire [MAX_DEG-1:0] top = {{(MAX_DEG-1){1'b0}}, 1'b1} << (degree - 1'b1);
    assign out   = |(st & top);
    assign state = st;
endmodule

`default_nettype wire
