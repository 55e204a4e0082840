"""cocotb bench for ``rx_top``: plays every case of a job and records every output word.

Run through :func:`cdma_lidar.hdl_ref.cosim.run_job`. A case gives the configuration
ports (``cfg_columns`` of them) and the columns' samples; the bench streams all columns
back to back, one sample per clock whenever ``s_ready`` is high, ``p`` samples per clock
(``s_valid`` low on every ``gap``-th clock when the case has ``"gap"``; with
``"wait_ready"`` the source offers nothing before it has seen ``s_ready`` high, as a
fixed-rate source should begin; ``stop`` high in clock ``stop_clock``, ``clear_err`` in
``clear_clock``; ``spare`` samples offered after the columns, which must not be taken),
and records, clock by clock (a clock's values are read at the rising edge that ends it):
every ``corr_*`` word, every ``res_*`` word at ``res_valid``, the clocks of
``col_start`` and of every column's last sample, the clocks where the source offered a
sample that was not taken (back-pressure), every clock with ``s_refused``, the samples
taken, the ``done`` clock, and the sticky flags before and after one ``clear_err``
clock. A case whose ``done`` has not come after ``max_clocks`` clocks (the caller's
watchdog: twice the schedule's) ends there with ``hung`` set. Words with X or Z bits are
recorded as null. Comparison with the model happens in the caller.
"""

from __future__ import annotations

import cocotb
from cocotb.triggers import RisingEdge

from cdma_lidar.hdl_ref.tb.jobs import play_stream_cases

__all__ = ["play_job"]

PERIOD_NS = 10
RESULT_PORTS = (
    "res_found", "res_lag", "res_index", "res_peak", "res_neg", "res_nz", "res_nb_lo",
    "res_nb_hi", "res_noise_count", "res_noise_sum", "res_noise_sumsq", "res_uid_observed",
    "res_uid_match", "res_saturated",
)


def _int(signal) -> int | None:
    """The signal's value, or None when it has X or Z bits (recorded, not raised)."""
    value = signal.value
    return int(value) if value.is_resolvable else None


async def _run_case(dut, case: dict) -> dict:
    ports = case["ports"]
    columns = case["columns"]
    per_col = len(columns[0])
    p = int(case.get("p", 1))                      # samples per clock (the build's P_IN)
    samples = [x for col in columns for x in col] + [0] * int(case.get("spare", 0))
    adc_w = len(dut.s_data) // p
    mask = (1 << adc_w) - 1
    gap = int(case.get("gap", 0))
    stop_clock = case.get("stop_clock")
    clear_clock = case.get("clear_clock")
    max_clocks = int(case.get("max_clocks", 10_000_000))
    seen_ready = not case.get("wait_ready", False)
    for name, value in ports.items():
        getattr(dut, name).value = int(value)
    dut.start.value = 1
    await RisingEdge(dut.clk)          # this edge takes start: clock 0 follows
    dut.start.value = 0
    corr, res, col_start, last_take, stalls, refused = [], [], [], [], [], []
    first_take = None
    taken, clock = 0, 0
    res_count = {}
    done, done_clock, hung = False, None, False

    def offer(c: int) -> bool:
        return seen_ready and taken < len(samples) and not (gap and c % gap == gap - 1)

    def drive(c: int) -> bool:
        valid = offer(c)
        dut.s_valid.value = int(valid)
        word = 0
        for k, x in enumerate(samples[taken:taken + p]):
            word |= (x & mask) << (k * adc_w)
        dut.s_data.value = word
        dut.stop.value = int(c == stop_clock)
        dut.clear_err.value = int(c == clear_clock)
        return valid

    valid = drive(clock)
    while not done:
        await RisingEdge(dut.clk)      # values read now are those of clock `clock`
        if dut.s_refused.value:
            refused.append(clock)
        if dut.s_ready.value:
            seen_ready = True
        if valid:
            if dut.s_ready.value:
                if first_take is None:
                    first_take = clock
                taken += p
                if taken % per_col == 0:
                    last_take.append(clock)
            elif first_take is not None:
                stalls.append(clock)
        if dut.corr_valid.value:
            ch = int(dut.corr_channel.value)
            corr.append([len(col_start) - 1, ch, int(dut.corr_index.value),
                         _int(dut.corr_data)])
        if dut.res_valid.value:
            ch = int(dut.res_channel.value)
            col = res_count.get(ch, 0)
            res_count[ch] = col + 1
            res.append([col, ch, {name: _int(getattr(dut, name)) for name in RESULT_PORTS},
                        clock])
        if dut.col_start.value:
            col_start.append(clock)
        if dut.done.value:
            done = True
            done_clock = clock
        clock += 1
        valid = drive(clock)
        if clock > max_clocks:
            hung = True
            break
    dut.s_valid.value = 0
    dut.stop.value = 0
    dut.clear_err.value = 0
    flags = {"overrun": _int(dut.err_overrun), "refused": _int(dut.err_refused)}
    # software clears the sticky flags: one clear_err clock, then both are low
    dut.clear_err.value = 1
    await RisingEdge(dut.clk)
    dut.clear_err.value = 0
    await RisingEdge(dut.clk)
    cleared = int(dut.err_overrun.value) | int(dut.err_refused.value)
    return {
        "corr": corr,
        "res": [r[:3] for r in res],
        "res_clocks": [r[3] for r in res],
        "col_start": col_start,
        "last_take": last_take,
        "first_take": first_take,
        "stalls": stalls,
        "refused": refused,
        "taken": taken,
        "done": done_clock,
        "overrun": flags["overrun"],
        "err_refused": flags["refused"],
        "cleared": cleared,
        "hung": hung,
    }


@cocotb.test()
async def play_job(dut) -> None:
    """Play the job named by HDL_REF_JOB; write the words to HDL_REF_RESULT."""
    await play_stream_cases(dut, _run_case, PERIOD_NS)
