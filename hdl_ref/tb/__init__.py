"""cocotb benches for the reference RTL (run inside the simulator by ``cdma_lidar.hdl_ref.cosim.run_job``)."""
