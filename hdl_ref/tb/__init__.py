"""cocotb benches for the reference RTL (run inside the simulator by ``hdl_ref.cosim.run_job``)."""
