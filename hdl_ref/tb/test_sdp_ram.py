"""cocotb bench for ``sdp_ram``: plays write and read commands, records ``rdata`` per clock.

The job's single case gives per clock ``we``, ``waddr``, ``wdata`` and ``raddr``
(driven after the falling edge, taken by the next rising edge); ``rdata`` is read
at every falling edge. Comparison with the model (read-old on a read of the word
being written) happens in the caller.
"""

from __future__ import annotations

import cocotb
from cocotb.clock import Clock
from cocotb.triggers import FallingEdge

from cdma_lidar.hdl_ref.tb.jobs import read_job, write_result

__all__ = ["play_job"]


@cocotb.test()
async def play_job(dut) -> None:
    """Play the job named by HDL_REF_JOB; write ``rdata`` of every clock to HDL_REF_RESULT."""
    case = read_job()["cases"][0]
    cocotb.start_soon(Clock(dut.clk, 10, unit="ns").start())
    rdata = []
    for we, waddr, wdata, raddr in zip(case["we"], case["waddr"], case["wdata"], case["raddr"],
                                       strict=True):
        await FallingEdge(dut.clk)
        value = dut.rdata.value
        rdata.append(int(value) if value.is_resolvable else None)
        dut.we.value, dut.waddr.value = we, waddr
        dut.wdata.value, dut.raddr.value = wdata, raddr
    write_result({"cases": [{"rdata": rdata}]})
