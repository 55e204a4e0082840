"""cocotb benches for the reference RTL.

They run inside the simulator, started by ``cdma_lidar.hdl_ref.cosim.run_job``.
"""
