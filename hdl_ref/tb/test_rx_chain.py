"""cocotb bench for ``rx_chain``: plays every case of a job and records the output words.

Run through :func:`cdma_lidar.hdl_ref.cosim.run_job` (never imported by the model). For each
case it drives the configuration ports, pulses ``start``, streams the samples
one per clock while ``s_ready`` is high (or with ``s_valid`` low on every
``gap``-th clock when the case has ``"gap"``), records every ``corr_*`` word as it
appears and, at ``done``, every result port. Clock counts (start to first
sample, last sample to done) are measured in simulated clocks; a case that has not
finished in twice its documented clocks fails the run (watchdog). Comparison with
the model happens in the caller (tests/hdl_ref).
"""

from __future__ import annotations

import cocotb
from cocotb.triggers import ClockCycles, First, ReadOnly, RisingEdge
from cocotb.utils import get_sim_time

from cdma_lidar.hdl_ref.cosim import rx_latency_clocks
from cdma_lidar.hdl_ref.tb.jobs import play_stream_cases

__all__ = ["play_job"]

PERIOD_NS = 10
RESULT_PORTS = (
    "res_found", "res_lag", "res_index", "res_peak", "res_neg", "res_nz", "res_nb_lo",
    "res_nb_hi", "res_noise_count", "res_noise_sum", "res_noise_sumsq", "res_uid_observed",
    "res_uid_match", "res_saturated",
)


async def _monitor_corr(dut, sink: list) -> None:
    """Append (j, word) for every clock with corr_valid."""
    while True:
        await RisingEdge(dut.clk)
        await ReadOnly()
        if dut.corr_valid.value:
            sink.append([int(dut.corr_index.value), int(dut.corr_data.value)])


async def _run_case(dut, case: dict) -> dict:
    ports = case["ports"]
    samples = case["samples"]
    mask = (1 << len(dut.s_data)) - 1
    corr: list = []
    monitor = cocotb.start_soon(_monitor_corr(dut, corr))
    for name, value in ports.items():
        getattr(dut, name).value = int(value)
    dut.start.value = 1
    await RisingEdge(dut.clk)
    t_start = get_sim_time("ns")
    dut.start.value = 0
    # optional source gaps: s_valid low on every clock c with c % gap == gap - 1
    gap = int(case.get("gap", 0))
    clock = 0
    valid = not (gap and clock % gap == gap - 1)
    dut.s_valid.value = int(valid)
    dut.s_data.value = samples[0] & mask
    taken = 0
    t_first = t_last = t_start
    # watchdog: twice the clocks of the documented latency, plus 100 (a hang fails in seconds)
    budget = 2 * sum(rx_latency_clocks(ports, gap).values()) + 100
    while taken < len(samples):
        if clock > budget:
            monitor.cancel()
            raise RuntimeError(f"rx_chain: samples still not taken after {budget} clocks")
        await RisingEdge(dut.clk)
        if valid and dut.s_ready.value:  # values before this edge: the edge took the sample
            if taken == 0:
                t_first = get_sim_time("ns")
            taken += 1
            if taken < len(samples):
                dut.s_data.value = samples[taken] & mask
        clock += 1
        valid = not (gap and clock % gap == gap - 1)
        dut.s_valid.value = int(valid)
    t_last = get_sim_time("ns")
    dut.s_valid.value = 0
    if isinstance(await First(RisingEdge(dut.done), ClockCycles(dut.clk, budget)), ClockCycles):
        monitor.cancel()
        raise RuntimeError(f"rx_chain: no done {budget} clocks after the last sample")
    await ReadOnly()
    t_done = get_sim_time("ns")
    res = {name: int(getattr(dut, name).value) for name in RESULT_PORTS}
    # ReadOnly of the clock that raised done: leave it before touching inputs again
    await RisingEdge(dut.clk)
    monitor.cancel()
    return {
        "corr": corr,
        "res": res,
        "clocks": {
            "start_to_ready": round((t_first - t_start) / PERIOD_NS),
            "first_to_last": round((t_last - t_first) / PERIOD_NS),
            "last_to_done": round((t_done - t_last) / PERIOD_NS),
        },
    }


@cocotb.test()
async def play_job(dut) -> None:
    """Play the job named by HDL_REF_JOB; write the words to HDL_REF_RESULT."""
    await play_stream_cases(dut, _run_case, PERIOD_NS)
