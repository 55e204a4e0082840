"""cocotb bench for ``gold_gen``: records the chip outputs clock by clock.

For each case of the job (HDL_REF_JOB) it loads the seeds, then for every clock
c drives ``en = case["en"][c]`` (and ``load = case["load"][c]`` when the case has
``"load"``: a load in the same clock as an enable) and records ``chip``, ``chip_raw``,
``chip_index`` and ``period`` as seen during that clock (sampled at the falling
edge, when the registers are settled). The caller compares with the model.
"""

from __future__ import annotations

import cocotb
from cocotb.clock import Clock
from cocotb.triggers import FallingEdge, RisingEdge

from cdma_lidar.hdl_ref.tb.jobs import read_job, write_result

__all__ = ["play_job"]


@cocotb.test()
async def play_job(dut) -> None:
    """Play the job named by HDL_REF_JOB; write the recorded outputs to HDL_REF_RESULT."""
    job = read_job()
    cocotb.start_soon(Clock(dut.clk, 10, unit="ns").start())
    results = []
    for case in job["cases"]:
        await FallingEdge(dut.clk)
        for name, value in case["ports"].items():
            getattr(dut, name).value = int(value)
        dut.load.value = 1
        dut.en.value = 0
        await RisingEdge(dut.clk)
        dut.load.value = 0
        rec: dict[str, list[int]] = {"chip": [], "chip_raw": [], "chip_index": [], "period": []}
        loads = case.get("load", [0] * len(case["en"]))
        for en, load in zip(case["en"], loads, strict=True):
            await FallingEdge(dut.clk)
            for key, sink in rec.items():
                sink.append(int(getattr(dut, key).value))
            dut.en.value = int(en)
            dut.load.value = int(load)
        results.append(rec)
    write_result({"cases": results})
