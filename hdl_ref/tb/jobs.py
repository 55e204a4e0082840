"""The job/result hand-over the cocotb benches here share with ``cosim.run_job``.

``run_job`` writes the job as JSON to the file named by ``HDL_REF_JOB`` and reads the
bench's result from ``HDL_REF_RESULT`` (written whole, through a temporary file, so a
crashed simulation leaves no half result).
"""

from __future__ import annotations

import json
import os
from collections.abc import Awaitable, Callable
from typing import Any

import cocotb
from cocotb.clock import Clock
from cocotb.triggers import RisingEdge

__all__ = ["play_stream_cases", "read_job", "write_result"]


def read_job() -> dict[str, Any]:
    """The job named by ``HDL_REF_JOB``."""
    with open(os.environ["HDL_REF_JOB"]) as f:
        return json.load(f)


def write_result(result: dict[str, Any]) -> None:
    """Write ``result`` to ``HDL_REF_RESULT`` atomically."""
    tmp = os.environ["HDL_REF_RESULT"] + ".tmp"
    with open(tmp, "w") as f:
        json.dump(result, f)
    os.replace(tmp, os.environ["HDL_REF_RESULT"])


async def play_stream_cases(dut: Any, run_case: Callable[[Any, dict], Awaitable[dict]],
                            period_ns: int) -> None:
    """The streaming chains' bench (rx_chain, rx_top): clock, reset for two clocks with
    ``start`` and ``s_valid`` low, then ``run_case`` on every case of the job in order."""
    job = read_job()
    cocotb.start_soon(Clock(dut.clk, period_ns, unit="ns").start())
    dut.rst.value = 1
    dut.start.value = 0
    for name in ("stop", "clear_err"):      # rx_top only
        if hasattr(dut, name):
            getattr(dut, name).value = 0
    dut.s_valid.value = 0
    dut.s_data.value = 0
    for _ in range(2):
        await RisingEdge(dut.clk)
    dut.rst.value = 0
    await RisingEdge(dut.clk)
    write_result({"cases": [await run_case(dut, case) for case in job["cases"]]})
