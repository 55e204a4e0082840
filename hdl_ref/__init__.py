"""Reference Verilog RTL of the code generator and receive chain, with its co-simulation.

``hdl_ref/rtl/*.v`` holds the RTL (``lfsr_fib``, ``gold_gen``, ``sdp_ram``, ``cfg_latch``,
``out_scale``, ``rx_post``, ``rx_chain``, ``rx_top``); :mod:`cdma_lidar.hdl_ref.cosim` builds
it with Icarus Verilog and plays cocotb benches (:mod:`cdma_lidar.hdl_ref.tb`),
:mod:`cdma_lidar.hdl_ref.stimuli` makes ADC columns, ``python -m cdma_lidar.hdl_ref.lint``
runs Verilator's lint, ``python -m cdma_lidar.hdl_ref.synth`` produces the yosys resource
tables of ``docs/hdl.md``, ``python -m cdma_lidar.hdl_ref.mutate`` reports which test kills
each deliberate fault and :mod:`cdma_lidar.hdl_ref.engine` runs ``rx_top`` under Verilator
as a receive chain (``virtual://SCENE?engine=rtl``).
cocotb is imported only when a simulation is built or run; ``firmware_model`` never
imports it.
"""

__all__: list[str] = []
