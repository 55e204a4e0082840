// adc_pins -- the ADC's DDR pins into words of 4 samples in the ECP5's I/O gearing, and
// the asynchronous FIFO (adc_rx) into the fabric clock.
//
//   dco (125 MHz) --> ECLKSYNCB --> eclk (edge clock) --> CLKDIVF DIV 2.0 --> sclk (62.5 MHz)
//   d[b] (DDR pin) --> IDDRX2F (eclk, sclk) --> Q0..Q3: bit b of samples 0..3 of the word
//   run (clk) --> 3 sclk flops --> the FIFO's write enable (one word every sclk clock)
//   {gap, word} (sclk) --> adc_rx, one word per write (the FIFO of the one-sample path)
//                      --> m_data (clk); a taken word with its gap bit --> err_overflow
//
// The converter sends sample n on the rising edge of its data clock `dco` and sample n + 1
// on the falling edge, one bit per pin (a 250 MS/s ADC: dco at 125 MHz). Each data pin
// goes to one IDDRX2F (ADC_W of them): clocked by eclk = dco and sclk = eclk / 2, it gives
// 4 consecutive samples of its bit per sclk clock, Q0 the earliest. Bit b of Q_k lands at
// [k*ADC_W + b] of the word, so sample k of the word is [k*ADC_W +: ADC_W], the layout of
// adc_rx's packer (and of rx_top's s_data). Nothing in the fabric runs faster than sclk.
//
// Word alignment: a fixed phase, no ALIGNWD. The converter has no frame pin, so no sample
// is "first" until the acquisition starts: the word boundary is wherever CLKDIVF put it
// after configuration (its RST and ALIGNWD are tied low), and the acquisition begins on a
// word boundary by construction, because it begins on an sclk clock. `run` (rx_top's busy,
// clk domain) crosses into sclk through two flip-flops (run_s) and one more (run_d) that
// waits for the IDDRX2F's latency: the first word written is the one whose Q0 the converter
// launched on the first dco falling edge after the sclk edge at which run_s rose (through
// the behavioural models of hdl_ref/tb/ecp5_gearing_models.v: a transmitter started by
// that sclk edge lines up with the acquisition's sample 0; on a board the primitives' own
// latency is calibrated with the range offset). Words are written while run_d is high,
// one every sclk clock, into adc_rx's FIFO (a full FIFO writes nothing).
//
// Overflow: the converter never stops, so words arrive that nobody wants (while rx_top
// processes its last column, and while it is idle, when the FIFO is drained). A lost word
// matters only if the consumer takes a later one: a word that is not written (FIFO full)
// sets `lost`, the next word written carries it as a gap bit through the FIFO, and
// err_overflow (sticky until clear_ovf, an overflow in the clearing clock wins) rises when
// the consumer takes (m_valid && m_ready) a word with the gap bit. The flag needs no
// crossing of its own: it rides with the data. While `run` is low the FIFO is drained
// (read without m_ready): a start must wait for the words of the last capture to pass
// (2^AW + 8 clk clocks after run falls, with sclk and clk near the same rate).
//
// Resets: rst (clk) reaches sclk through two flip-flops, as in the one-sample path.
`default_nettype none

module adc_pins #(
    parameter integer ADC_W = 12,
    parameter integer AW    = 4         // FIFO depth 2^AW words of 4 samples (AW >= 2)
) (
    input  wire                   dco,          // the converter's data clock (DDR)
    input  wire [ADC_W-1:0]       d,            // one bit per pin, two's complement samples

    input  wire                   clk,
    input  wire                   rst,
    input  wire                   run,          // clk: capture words (rx_top's busy)
    output wire                   m_valid,
    output wire [4*ADC_W-1:0]     m_data,       // sample k of the word at [k*ADC_W +: ADC_W]
    input  wire                   m_ready,
    input  wire                   clear_ovf,    // clk: clears err_overflow (one-clock pulse)
    output wire                   err_overflow  // clk: sticky, a word was lost
);
    localparam integer WW = 4 * ADC_W;

    wire eclk, sclk;
    ECLKSYNCB esync (.ECLKI(dco), .STOP(1'b0), .ECLKO(eclk));
    CLKDIVF #(.DIV("2.0")) div (.CLKI(eclk), .RST(1'b0), .ALIGNWD(1'b0), .CDIVX(sclk));

    wire [WW-1:0] q;
    genvar b;
    generate
        for (b = 0; b < ADC_W; b = b + 1) begin : g_bit
            IDDRX2F ddr (.D(d[b]), .SCLK(sclk), .ECLK(eclk), .RST(1'b0), .ALIGNWD(1'b0),
                         .Q0(q[b]), .Q1(q[ADC_W + b]), .Q2(q[2*ADC_W + b]),
                         .Q3(q[3*ADC_W + b]));
        end
    endgenerate

    // ---- sclk domain: reset and run through two flip-flops, run_d one clock later ----
    reg [1:0] rst_s;
    reg       run_q, run_s, run_d, lost;
    wire      full;
    always @(posedge sclk) begin
        rst_s <= {rst_s[0], rst};
        run_q <= run;                       // no logic before the first flip-flop
        run_s <= !rst_s[1] && run_q;
        run_d <= !rst_s[1] && run_s;
        lost  <= run_d && full;             // this clock's word is not written
    end

    // clk: a registered copy of run drives the drain, so rx_top's busy, wherever the
    // placer puts its source, reaches the FIFO's read side through one flip-flop: the
    // drain starts and stops one clock after busy changes (the FIFO is empty when busy
    // rises, since a start waits for the drain, and its first word is clocks away)
    reg run_c;
    always @(posedge clk)
        run_c <= !rst && run;

    // one word a clock: adc_rx with one "sample" of 4 ADC_W bits (no packing) and the
    // gap bit on top: "the word before this one was lost"
    wire [WW:0] word;
    /* verilator lint_off UNUSEDSIGNAL */
    wire        any_loss;                   // adc_rx's flag: also the words nobody wanted
    /* verilator lint_on UNUSEDSIGNAL */
    adc_rx #(.ADC_W(WW + 1), .P_IN(1), .AW(AW)) fifo (
        .adc_clk(sclk), .adc_rst(rst_s[1]), .adc_valid(run_d), .adc_data({lost, q}),
        .clk(clk), .rst(rst), .m_valid(m_valid), .m_data(word), .m_ready(m_ready || !run_c),
        .clear_ovf(clear_ovf), .err_overflow(any_loss), .adc_full(full)
    );
    assign m_data = word[WW-1:0];

    // ---- clk domain: a word taken after a lost one is the overflow (sticky) ----
    reg ovf;
    always @(posedge clk)
        ovf <= !rst && ((ovf && !clear_ovf) || (m_valid && m_ready && word[WW]));
    assign err_overflow = ovf;
endmodule

`default_nettype wire
