"""The tradeoff study: its grid, one small run, the Pareto front."""

from __future__ import annotations

import numpy as np
import pytest
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
    pareto_front,
)

#: flat-wall only: the baseline, S=2 x R=1 and the integer lag (3 points, about a second).
SMALL = {"scenes": "flat-wall", "S": "2", "R": "1", "degree": "11", "adc_bits": "12",
         "gate": "128", "method": "none", "fidelity": "exact"}


def test_full_grid_has_at_least_50_configurations_on_both_scenes():
    points = _grid(STUDY.options(False))
    assert len(points) >= 50
    assert {p["scene"] for p in points} == {"paper-scene1", "flat-wall"}
    for axis, lo, hi in (("S", 1, 16), ("R", 1, 100), ("degree", 9, 15), ("adc_bits", 8, 16)):
        values = {p[axis] for p in points}
        assert min(values) == lo and max(values) == hi, axis
    assert {p["method"] for p in points} == {"none", "parabolic", "triangle"}
    assert {p["fidelity"] for p in points} == set(FIDELITY_LEVELS)
    assert sum(all(p[k] == v for k, v in BASELINE.items()) for p in points) == 2
    assert len(_grid(STUDY.options(True))) < len(points)


@pytest.mark.parametrize("key, value, needle", [
    ("degree", "12", "preferred pairs"), ("S", "0", "S must be"), ("method", "cubic", "method"),
    ("fidelity", "magic", "fidelity"), ("scenes", "no-such-scene", "scene"),
])
def test_bad_axis_values_are_refused_naming_the_axis(key, value, needle):
    with pytest.raises(ConfigError, match=needle):
        _grid(STUDY.options(True, {key: value}))


def test_a_small_run_measures_error_time_memory_and_draws_the_front(tmp_path):
    res = run_study(STUDY, tmp_path, quick=True, overrides=SMALL, workers=0, progress=False)
    assert not res.failures and len(res.table) == 3
    rows = {r["setting"]: r for r in res.table.rows}
    assert set(rows) == {"paper baseline", "S=2, R=1", "method=none"}
    base = rows["paper baseline"]
    assert base["status"] == "ok" and base["valid_fraction"] > 0.9
    assert 0 < base["median_error_m"] < base["p95_error_m"] < 0.3
    assert base["false_pixels"] == 0  # the wall fills every pixel
    # the integer lag is off by up to half a sample (0.6 m at S = 4): far worse
    assert rows["method=none"]["median_error_m"] > 3 * base["median_error_m"]
    for col in MACHINE_COLUMNS[:-1]:
        assert base[col] > 0
    assert base["receive_time_per_frame_s"] < base["scan_time_per_frame_s"]
    assert any(r["on_pareto_front"] for r in res.table.rows)
    assert (tmp_path / "pareto.png").stat().st_size > 1000
    assert "| flat-wall |" in (tmp_path / "pareto.md").read_text()
    table = read_csv(tmp_path / "results.csv")
    assert table.columns[:8] == ["scene", "S", "R", "degree", "adc_bits", "gate", "method",
                                 "fidelity"]


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
