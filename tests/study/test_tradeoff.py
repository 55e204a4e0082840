"""The tradeoff study: its grid, a small run, the two fronts, their reproducibility, ``ask``."""

from __future__ import annotations

import math

import numpy as np
import pytest
from cli_helpers import one_line_error
from cli_helpers import run_cli as _run
from hypothesis import given
from hypothesis import strategies as st

from cdma_lidar.errors import ConfigError
from cdma_lidar.study.engine import read_csv, run_study
from cdma_lidar.study.tradeoff import (
    BASELINE,
    FIDELITY_LEVELS,
    MACHINE_COLUMNS,
    STUDY,
    _grid,
    acquisition_time_s,
    ask,
    pareto_front,
    simulation_work,
)

#: flat-wall only: the baseline, S=2 x R=1, R=1 at both fidelity levels and the integer
#: lag (5 points, 2 frames each, a few seconds).
SMALL = {"scenes": "flat-wall", "S": "2", "R": "1", "degree": "11", "chip_mhz": "62.5",
         "K": "40", "power_mw": "2.5", "near_far": "0", "adc_bits": "12", "gate": "128",
         "method": "none", "fidelity": "exact,accumulated", "replicates": "2"}

PARAMS = ["scene", *BASELINE]


@pytest.fixture(scope="module")
def small_run(tmp_path_factory):
    out = tmp_path_factory.mktemp("tradeoff")
    return run_study(STUDY, out, quick=True, overrides=SMALL, workers=0, progress=False)


def test_full_grid_covers_every_axis_on_scenes_at_two_distances():
    points = _grid(STUDY.options(False))
    assert len(points) >= 50
    assert {p["scene"] for p in points} == {"paper-scene1", "flat-wall", "flat-wall?distance=15"}
    for axis, lo, hi in (("S", 1, 16), ("R", 1, 100), ("degree", 9, 15), ("adc_bits", 8, 16),
                         ("chip_mhz", 31.25, 125), ("K", 10, 40), ("power_mw", 1.25, 5),
                         ("near_far", 0, 2)):
        values = {p[axis] for p in points}
        assert min(values) == lo and max(values) == hi, axis
    assert {p["method"] for p in points} == {"none", "parabolic", "triangle"}
    assert {(p["fidelity"], p["R"]) for p in points} >= {(f, r) for f in FIDELITY_LEVELS
                                                         for r in (1, 3, 10, 30, 100)}
    assert sum(all(p[k] == v for k, v in BASELINE.items()) for p in points) == 3
    assert len(_grid(STUDY.options(True))) < len(points)


@pytest.mark.parametrize("key, value, needle", [
    ("degree", "12", "preferred pairs"), ("S", "0", "S must be"), ("method", "cubic", "method"),
    ("fidelity", "magic", "fidelity"), ("scenes", "no-such-scene", "scene"),
    ("chip_mhz", "0", "chip_mhz"), ("power_mw", "-1", "power_mw"), ("K", "0", "K must be"),
    ("near_far", "-1", "near_far must be"),
])
def test_bad_axis_values_are_refused_naming_the_axis(key, value, needle):
    with pytest.raises(ConfigError, match=needle):
        _grid(STUDY.options(True, {key: value}))


def test_acquisition_time_and_simulation_work_are_counted_exactly():
    assert acquisition_time_s(160, 10, 1, 11, 62.5e6) == 160 * 10 * 2047 / 62.5e6
    assert acquisition_time_s(16, 3, 2, 9, 31.25e6) == 16 * 3 * 2 * 511 / 31.25e6
    n = 8188
    echo = 4 * 6 * (n // 2 + 1) + 2 * n * 13
    assert simulation_work(6, n, 10, "exact") == echo + 11 * n
    assert simulation_work(6, n, 10, "accumulated") == echo + 2 * n
    assert simulation_work(6, n, 10, "accumulated", tabulated=True) == 2 * 6 * n + 2 * n
    assert simulation_work(6, n, 10, "exact", tabulated=True) == echo + 11 * n
    assert simulation_work(6, n, 10, "repetitions") == echo + 20 * n
    assert simulation_work(0, n, 10, "exact") == 11 * n  # nothing lit: no echo, no FFT


def test_a_small_run_measures_both_trades_and_writes_the_report(small_run, tmp_path):
    res = small_run
    assert not res.failures and len(res.table) == 5
    rows = {r["setting"]: r for r in res.table.rows}
    assert set(rows) == {"paper baseline", "S=2, R=1", "R=1", "R=1, fidelity=accumulated",
                         "method=none"}
    base = rows["paper baseline"]
    assert base["status"] == "ok" and base["valid_fraction"] > 0.9
    assert 0 < base["median_error_m"] < base["p95_error_m"] < 0.3
    assert base["p95_error_m_ci95"] > 0  # two frames: a 95 % interval
    assert base["false_pixels"] == 0  # the wall fills every pixel
    assert base["acquisition_time_per_frame_s"] == 16 * 10 * 2047 / 62.5e6
    assert rows["R=1"]["acquisition_time_per_frame_s"] == 16 * 2047 / 62.5e6
    assert base["adc_rate_hz"] == 250e6 and rows["S=2, R=1"]["adc_rate_hz"] == 125e6
    # every column's repetition sum drawn from its law: L + (R-1) L + L per column
    lit = 16 * 40
    assert base["simulation_work_per_frame"] == (4 * lit * 4095 + 16 * 2 * 8188 * 13
                                                 + 16 * 11 * 8188)
    # accumulated draws as many values as exact at R = 1 but echoes from tables: two
    # axpys per lit channel instead of the Fourier synthesis and its inverse FFT
    assert (rows["R=1, fidelity=accumulated"]["simulation_work_per_frame"]
            == 2 * lit * 8188 + 16 * 2 * 8188)
    assert (rows["R=1"]["simulation_work_per_frame"]
            == 4 * lit * 4095 + 16 * 2 * 8188 * 13 + 16 * 2 * 8188)
    # the integer lag is off by up to half a sample (0.6 m at S = 4): far worse
    assert rows["method=none"]["median_error_m"] > 3 * base["median_error_m"]
    for col in MACHINE_COLUMNS:
        assert base[col] > 0
    # the instrument's front: exact rows only; the modeller's: the configuration at both levels
    assert rows["R=1, fidelity=accumulated"]["on_pareto_front"] is False
    assert any(r["on_pareto_front"] for r in res.table.rows)
    assert rows["R=1"]["fidelity_p95_error_m"] == 0
    acc = rows["R=1, fidelity=accumulated"]
    assert acc["fidelity_p95_error_m"] == pytest.approx(
        acc["p95_error_m"] - rows["R=1"]["p95_error_m"])
    # exact has no error and accumulated costs less work: neither dominates the other
    assert acc["simulation_work_per_frame"] < rows["R=1"]["simulation_work_per_frame"]
    assert rows["R=1"]["on_modeller_front"] and acc["on_modeller_front"]
    assert not rows["paper baseline"]["on_modeller_front"]  # run at one level only
    assert (res.out / "pareto.png").stat().st_size > 1000
    report = (res.out / "pareto.md").read_text()
    assert report.index("Fastest configuration") < report.index("Pareto front")
    assert "| flat-wall | 0.05 |" in report
    table = read_csv(res.out / "results.csv")
    assert table.columns[:len(PARAMS)] == PARAMS
    assert {"acquisition_time_per_frame_s", "simulation_work_per_frame"} <= set(table.columns)


def test_the_near_far_loop_lights_the_far_wall(tmp_path):
    """At 15 m and 2.5 mW half the wall is below the SNR_XC threshold; two frames of the
    host's near-far loop (power raised where SNR_XC is low, up to the 0.2 W cap) light
    most of it, at no acquisition time (the loop runs on every frame)."""
    over = {**SMALL, "scenes": "flat-wall?distance=15", "S": "4", "R": "10",
            "method": "triangle", "fidelity": "exact", "near_far": "0,2", "replicates": "1"}
    res = run_study(STUDY, tmp_path, quick=True, overrides=over, workers=0, progress=False)
    rows = {r["setting"]: r for r in res.table.rows}
    base, loop = rows["paper baseline"], rows["near_far=2"]
    assert base["valid_fraction"] < 0.7 and loop["valid_fraction"] > base["valid_fraction"] + 0.2
    assert loop["acquisition_time_per_frame_s"] == base["acquisition_time_per_frame_s"]


def test_the_fronts_are_identical_with_and_without_dask_workers(small_run, tmp_path):
    """Both fronts rest on counted axes and seeded results: a second run on two Dask worker
    processes (a loaded machine, other timings) gives the same fronts and the same
    values in every column that does not measure the machine."""
    again = run_study(STUDY, tmp_path, quick=True, overrides=SMALL, workers=2, progress=False)
    a, b = small_run.table, again.table
    machine = {c for c in a.columns
               if c.removesuffix("_ci95").removesuffix("_best") in MACHINE_COLUMNS}
    assert a.columns == b.columns
    for col in a.columns:
        if col in machine:
            continue
        for ra, rb in zip(a.rows, b.rows, strict=True):
            va, vb = ra[col], rb[col]
            same = va == vb or (isinstance(va, float) and math.isnan(va) and math.isnan(vb))
            assert same, (col, ra["setting"], va, vb)
    assert [r["on_pareto_front"] for r in a.rows] == [r["on_pareto_front"] for r in b.rows]
    assert [r["on_modeller_front"] for r in a.rows] == [r["on_modeller_front"] for r in b.rows]


def test_ask_answers_the_fastest_configuration_and_the_runner_up(small_run):
    out = small_run.out
    loose = ask(out, 1.0, min_valid=0.5)
    assert loose.scene == "flat-wall" and loose.candidates == 4  # every exact row
    # R = 1 is ten times faster than R = 10; of the two R = 1 rows the lower p95 wins
    r1 = sorted((r for r in small_run.table.rows if r["R"] == 1 and r["fidelity"] == "exact"),
                key=lambda r: r["p95_error_m"])
    assert loose.best["setting"] == r1[0]["setting"]
    assert loose.runner_up["setting"] == r1[1]["setting"]
    tight = ask(out, 1e-4)
    assert tight.best is None and tight.runner_up is None
    assert "no configuration meets it" in tight.describe()
    assert "±" in loose.describe()  # the 95 % intervals over the two frames
    with pytest.raises(ConfigError, match="scene"):
        ask(out, 0.05, scene="paper-scene1")
    with pytest.raises(ConfigError, match="max_p95"):
        ask(out, -1)


def test_study_ask_exit_status_and_one_line_errors(small_run, capsys, tmp_path):
    out = str(small_run.out)
    code, text, _ = _run(capsys, "study", "ask", "tradeoff", out, "--max-p95", "1",
                         "--min-valid", "0.5")
    assert code == 0 and "fastest:" in text and "runner-up:" in text
    assert len(text.splitlines()) == 3
    code, text, _ = _run(capsys, "study", "ask", "tradeoff", out, "--max-p95", "0.0001",
                         "--scene", "flat-wall")
    assert code == 1 and "no configuration meets it" in text
    for argv, needle in (
        (["study", "ask", "tradeoff", str(tmp_path), "--max-p95", "0.05"], "no results.csv"),
        (["study", "ask", "tradeoff", out, "--max-p95", "0.05", "--scene", "x"], "--scene"),
        (["study", "ask", "extremes", out, "--max-p95", "0.05"], "only 'tradeoff'"),
        (["study", "ask", "tradeoff", out, "--max-p95", "-2"], "max_p95"),
        (["study", "ask", "tradeoff", out], "--max-p95"),
    ):
        assert needle in one_line_error(capsys, *argv)


@given(st.lists(st.tuples(st.floats(0.01, 10), st.floats(0.001, 1), st.booleans()),
                min_size=1, max_size=30))
def test_pareto_front_is_exactly_the_undominated_eligible_points(points):
    t, e, ok = (np.array(x) for x in zip(*points, strict=True))
    front = pareto_front(t, e, ok)
    for i in range(len(t)):
        dominated = any(ok[j] and t[j] <= t[i] and e[j] <= e[i] and (t[j] < t[i] or e[j] < e[i])
                        for j in range(len(t)))
        assert front[i] == (bool(ok[i]) and not dominated)
    if ok.any():
        assert front.any()
