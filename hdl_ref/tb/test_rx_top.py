"""cocotb bench for ``rx_top``: plays every case of a job and records every output word.

Run through :func:`cdma_lidar.hdl_ref.cosim.run_job`. A case gives the
configuration ports (``cfg_columns`` of them) and the columns' samples; the
bench streams all columns back to back, one sample per clock whenever
``s_ready`` is high (``s_valid`` low on every ``gap``-th clock when the case has
``"gap"``), and records, clock by clock (a clock's values are read at the rising
edge that ends it): every ``corr_*`` word, every ``res_*`` word at ``res_valid``,
the clocks of ``col_start`` and of every column's last sample, the clocks where
the source offered a sample that was not taken (back-pressure), and
``err_overrun``. Words with X or Z bits are recorded as null. Comparison with
the model happens in the caller.
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
    samples = [x for col in columns for x in col]
    mask = (1 << len(dut.s_data)) - 1
    gap = int(case.get("gap", 0))
    max_clocks = int(case.get("max_clocks", 10_000_000))
    for name, value in ports.items():
        getattr(dut, name).value = int(value)
    dut.start.value = 1
    await RisingEdge(dut.clk)          # this edge takes start: clock 0 follows
    dut.start.value = 0
    corr, res, col_start, last_take, stalls = [], [], [], [], []
    first_take = None
    taken, clock = 0, 0
    res_count = {}
    done = False

    def offer(c: int) -> bool:
        return taken < len(samples) and not (gap and c % gap == gap - 1)

    valid = offer(clock)
    dut.s_valid.value = int(valid)
    dut.s_data.value = samples[0] & mask
    while not done:
        await RisingEdge(dut.clk)      # values read now are those of clock `clock`
        if valid:
            if dut.s_ready.value:
                if first_take is None:
                    first_take = clock
                taken += 1
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
        clock += 1
        valid = offer(clock)
        dut.s_valid.value = int(valid)
        if taken < len(samples):
            dut.s_data.value = samples[taken] & mask
        if clock > max_clocks:
            raise RuntimeError(f"rx_top: no done after {max_clocks} clocks")
    return {
        "corr": corr,
        "res": [r[:3] for r in res],
        "res_clocks": [r[3] for r in res],
        "col_start": col_start,
        "last_take": last_take,
        "first_take": first_take,
        "stalls": stalls,
        "overrun": int(dut.err_overrun.value),
    }


@cocotb.test()
async def play_job(dut) -> None:
    """Play the job named by HDL_REF_JOB; write the words to HDL_REF_RESULT."""
    await play_stream_cases(dut, _run_case, PERIOD_NS)
