"""The extremes study: every kernel bit-exact with the reference, refusals and big cases as rows."""

from __future__ import annotations

import numpy as np
import pytest

from cdma_lidar.errors import ConfigError
from cdma_lidar.rounding import ROUNDING_MODES
from cdma_lidar.study.engine import run_study
from cdma_lidar.study.extremes import CASES, STUDY, _grid, extremes_task

SMALL = {"cases": "sat-8bit,shift-edge,uid-16,all-max"}


def test_small_cases_are_bit_exact_in_every_rounding_mode(tmp_path):
    res = run_study(STUDY, tmp_path, overrides=SMALL, workers=0, progress=False)
    assert not res.failures and len(res.table) == 4 * len(ROUNDING_MODES)
    for row in res.table.rows:
        if row["case"] == "all-max":
            assert row["status"] == "derived" and row["samples"] == 1024 * 64 * (2**20 - 1)
            assert row["raw_bits"] <= 63
            continue
        assert row["status"] == "ok" and row["bit_exact"] is True, row
        assert row["mismatches"] in ("", None)
        assert row["fast_time_s"] > 0 and row["peak_memory_mib"] > 0
    sat = res.table.where(case="sat-8bit")
    assert np.all(sat.column("saturated_fraction") > 0.5)  # heavy saturation indeed
    assert res.summary["points_not_bit_exact"]["ours"] == 0
    assert res.summary["points_bit_exact"]["ours"] == 9
    assert "| sat-8bit | convergent | ok | True |" in (tmp_path / "extremes.md").read_text()


def test_a_refused_configuration_is_a_row_with_the_reason():
    # a gate longer than the period (N*S = 127*4 = 508 lags) is outside what the RTL allows
    params = {"case": "custom", "degree": 7, "S": 4, "R": 64, "out_bits": 32, "out_shift": 0,
              "gate_len": 509, "uid_bits": 1, "rounding": "truncate"}
    row = extremes_task(params, np.random.SeedSequence(1))
    assert row["status"] == "refused" and "gate_len must be 1..508" in row["reason"]


def test_the_full_grid_covers_every_case_and_rounding_and_bad_names_are_refused():
    points = _grid(STUDY.options(False))
    assert {(p["case"], p["rounding"]) for p in points} == \
        {(c, r) for c in CASES for r in ROUNDING_MODES}
    assert max(p["degree"] for p in points) == 20 and max(p["S"] for p in points) == 64
    assert max(p["R"] for p in points) == 1024
    with pytest.raises(ConfigError, match="cases"):
        _grid(STUDY.options(True, {"cases": "nope"}))
    with pytest.raises(ConfigError, match="rounding"):
        _grid(STUDY.options(True, {"rounding": "up"}))
