`default_nettype none

// gen_strobe -- one registered copy of the generators' load and enable (rx_top keeps one
// per GEN_GRP channels; keep_hierarchy stops synthesis from merging the copies).
(* keep_hierarchy *)
module gen_strobe (
    input  wire clk,
    input  wire rst,
    input  wire load_nx,
    input  wire en_nx,
    output reg  load,
    output reg  en
);
    always @(posedge clk) begin
        load <= !rst && load_nx;
        en   <= !rst && en_nx;
    end
endmodule

`default_nettype wire
