// rx_adc_top_pnr -- place-and-route harness of the receive chain from the ADC pins
// (synthesis only, not simulated): adc_pins (the DDR pins through the ECP5 I/O gearing
// and the FIFO into clk) feeding rx_top_pnr (rx_top with its configuration shifted in and
// its results folded, docs/hdl.md). The pins are real and placed by adc_pins.lpf; the
// only change from rx_adc_top's PINS = 1 path is rx_top_pnr's register on each side of
// the handshake, which rx_top_pnr places beside its pads. What the table measures: the
// pins' clocks (dco, sclk) and clk, with rx_top, the FIFO and the gearing on one die.
`default_nettype none

module rx_adc_top_pnr #(
    parameter integer K       = 4,
    parameter integer L       = 2,
    parameter integer P_IN    = 4,
    parameter integer MAX_DEG = 11,
    parameter integer MAX_S   = 4,
    parameter integer MAX_UID = 1,
    parameter integer MAX_R   = 16,
    parameter integer MAX_G   = 64,
    parameter integer MAX_P   = 1,
    parameter integer NGHOST  = 1,
    parameter integer ADC_W   = 12,
    parameter integer OUT_W   = 32,
    parameter integer FIFO_AW = 4
) (
    input  wire              dco,           // the converter's DDR data clock (125 MHz)
    input  wire [ADC_W-1:0]  d,             // its data pins, one bit a pin, DDR
    input  wire              clk,
    input  wire              rst,
    input  wire              start,
    input  wire              stop,
    input  wire              clear_err,
    input  wire              cfg_sin,
    input  wire              cfg_shift,
    output wire              res_valid,
    output wire [31:0]       fold,
    output wire              busy,
    output wire              done,
    output wire              err_overrun,
    output wire              err_overflow
);
    generate
        if (P_IN != 4) begin : g_p_in_not_4
            rx_adc_top_pnr_needs_p_in_4 bad ();
        end
    endgenerate

    wire                  s_valid, s_ready;
    wire [4*ADC_W-1:0]    s_data;
    adc_pins #(.ADC_W(ADC_W), .AW(FIFO_AW)) pins (
        .dco(dco), .d(d), .clk(clk), .rst(rst), .run(busy), .m_valid(s_valid),
        .m_data(s_data), .m_ready(s_ready), .clear_ovf(clear_err), .err_overflow(err_overflow)
    );

    /* verilator lint_off UNUSEDSIGNAL */
    wire s_refused, err_refused;   // the FIFO absorbs refusals: a loss is err_overflow
    /* verilator lint_on UNUSEDSIGNAL */
    rx_top_pnr #(.K(K), .L(L), .P_IN(P_IN), .MAX_DEG(MAX_DEG), .MAX_S(MAX_S),
                 .MAX_UID(MAX_UID), .MAX_R(MAX_R), .MAX_G(MAX_G), .MAX_P(MAX_P),
                 .NGHOST(NGHOST), .ADC_W(ADC_W), .OUT_W(OUT_W)) rx (
        .clk(clk), .rst(rst), .start(start), .stop(stop), .clear_err(clear_err),
        .cfg_sin(cfg_sin), .cfg_shift(cfg_shift), .s_valid(s_valid), .s_data(s_data),
        .s_ready(s_ready), .s_refused(s_refused), .err_refused(err_refused),
        .res_valid(res_valid), .fold(fold), .busy(busy), .done(done),
        .err_overrun(err_overrun)
    );
endmodule

`default_nettype wire
