"""Reference Verilog RTL of the code generator and receive chain, with its co-simulation."""
