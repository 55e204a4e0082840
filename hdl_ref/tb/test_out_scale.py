"""cocotb bench for ``out_scale``: batches of raw words under one (shift, rounding, out_bits).

Run through :func:`cdma_lidar.hdl_ref.cosim.run_job`. Per batch the bench sets the
configuration, waits two clocks (the module registers its constants), streams
the raw words one per clock and records every ``out_word`` in order.
"""

from __future__ import annotations

import cocotb
from cocotb.clock import Clock
from cocotb.triggers import RisingEdge

from cdma_lidar.hdl_ref.tb.jobs import read_job, write_result

__all__ = ["play_job"]


@cocotb.test()
async def play_job(dut) -> None:
    """Play the job named by HDL_REF_JOB; write the words to HDL_REF_RESULT."""
    job = read_job()
    cocotb.start_soon(Clock(dut.clk, 10, unit="ns").start())
    mask = (1 << len(dut.in_raw)) - 1
    out_bits = len(dut.out_word)
    dut.in_v.value = 0
    dut.in_raw.value = 0
    dut.in_tag.value = 0
    for _ in range(4):  # flush the pipeline's power-up X
        await RisingEdge(dut.clk)
    results = []
    for batch in job["batches"]:
        dut.shift.value = batch["shift"]
        dut.rounding.value = batch["rounding"]
        dut.out_bits.value = batch["out_bits"]
        for _ in range(2):
            await RisingEdge(dut.clk)
        words: list[int] = []
        raws = batch["raws"]
        pending = len(raws)
        i = 0
        while pending:
            if i < len(raws):
                dut.in_v.value = 1
                dut.in_raw.value = raws[i] & mask
                dut.in_tag.value = i & 0xFF
            else:
                dut.in_v.value = 0
            i += 1
            await RisingEdge(dut.clk)
            if dut.out_v.value:  # value of the clock that just ended
                word = int(dut.out_word.value)
                words.append(word - (1 << out_bits) if word >> (out_bits - 1) else word)
                pending -= 1
        dut.in_v.value = 0
        results.append(words)
    write_result({"batches": results})
