"""The paper's operating point: the preset, ``point=paper``, the contract, intervals, verdicts,
eq. 9's detector, the docs generated from a run."""

from __future__ import annotations

import json

import numpy as np
import pytest

from cdma_lidar.errors import ConfigError
from cdma_lidar.scene import load_scene
from cdma_lidar.study import catalogue, fig2c, fig2d, fig2e, fig2f, fig11, paper, paperdocs
from cdma_lidar.study.engine import run_study
from cdma_lidar.study.mai import sga_error_rate
from cdma_lidar.study.paperlab import (
    ASSUMPTIONS,
    crossing_ci,
    entry,
    judge,
    printed_value,
    wilson,
)


def test_paper_lab_preset_is_what_the_paper_states():
    spec = load_scene("paper-lab").instrument
    assert spec.chip_rate_hz == 62.5e6 and spec.code_length == 2047 and spec.channels == 40
    assert spec.detector_bandwidth_hz == 400e6 and spec.sequential_mixing
    assert spec.grooves_per_mm == 600.0 and spec.averages == 1
    assert any(not p.stated for p in ASSUMPTIONS) and all(p.source for p in ASSUMPTIONS)


def test_printed_values_and_verdicts():
    assert printed_value("> 125") == (">", 125.0)
    assert printed_value("2/3") == ("=", pytest.approx(2 / 3))
    assert printed_value("millimetre-level") is None
    assert judge("> 125", 120, [110, 130]) == "consistent"  # the interval holds 125
    assert judge("> 125", 130, [125, 140]) == "reproduced"  # the lower bound reaches it
    assert judge("> 125", 113, [100, 120]) == "differs"
    assert judge("> 1200", 1400, [1300, None]) == "reproduced"
    assert judge("> 1200", 1400, [None, 1500]) == "consistent"  # an open end bounds nothing
    assert judge(0.2568, 0.25, [0.23, 0.27]) == "consistent"
    assert judge(0.2568, 0.25681, [0.25676, 0.25684]) == "reproduced"  # within 0.00005
    assert judge(0.2568, 0.017, [0.016, 0.018]) == "differs"
    assert judge(122, 122.085, None) == "reproduced" and judge(122, 125.0, None) == "differs"
    assert judge(2.4, 2.398, None) == "reproduced" and judge(0.03, 0.0302, None) == "reproduced"
    assert judge(66.0, 66.4, None) == "reproduced" and judge(66.0, 66.6, None) == "differs"
    assert judge(None, 3.0, None) is None
    assert judge(32.5, 14.5, [None, None]) == "consistent"  # bounded by nothing


def test_entry_keeps_the_contract():
    h = entry(112.0, "> 125", "channels", ci95=(None, 144.0), paper_point=120.0,
              paper_point_ci95=(100.0, 150.0), cause="x")
    assert {"ours", "paper", "unit", "paper_point", "ci95", "verdict"} <= set(h)
    assert h["ci95"] == [None, 144.0] and h["verdict"] == "consistent" and h["cause"] == "x"
    assert entry(float("nan"), None, "m")["ours"] is None


def test_crossing_interval_counts_the_grid_step_and_the_trials():
    k = [100, 110, 120, 130]
    # 1000 trials: the rate is known well; the crossing lies between 110 and 120
    assert crossing_ci(k, [0.02, 0.05, 0.2, 0.4], 1000) == (110.0, 120.0)
    # 40 trials: 2/40 could be above 10 %, so only the grid's first point is below for sure
    lo, hi = crossing_ci(k, [0.0, 0.05, 0.2, 0.4], 40)
    assert lo == 100.0 and hi in (120.0, 130.0)
    # never above 10 %: unbounded above; always above: unbounded below
    assert crossing_ci(k, [0.0] * 4, 1000)[1] is None
    assert crossing_ci(k, [0.5] * 4, 1000) == (None, 100.0)
    lo, hi = wilson(0, 40)
    assert lo == 0.0 and 0.08 < hi < 0.1


def test_signed_detector_never_errs_more_in_the_approximation():
    for db in (10.0, 13.0, 16.0):
        assert sga_error_rate(10 ** (db / 10), 2044, detector="signed") < \
            sga_error_rate(10 ** (db / 10), 2044)
    with pytest.raises(ConfigError, match="detector"):
        sga_error_rate(10.0, 10, detector="max")


@pytest.mark.parametrize("study", [fig2c.STUDY, fig2d.STUDY, fig2e.STUDY, fig2f.STUDY,
                                   fig11.STUDY])
def test_point_is_checked(tmp_path, study):
    with pytest.raises(ConfigError, match="point"):
        run_study(study, tmp_path, overrides={"point": "lab"}, workers=0, progress=False)


def test_paper_point_settings():
    opts = fig2c.STUDY.options(True, {"point": "paper"})
    (p,) = fig2c.STUDY.grid(opts)
    assert (p["scene"], p["distance"], p["averages"], p["S"], p["method"]) == \
        ("paper-lab", 10.0, 1, 50, "none")
    assert p["sequential_mixing"] is False  # one channel: nothing is mixed
    pts = fig2d.STUDY.grid(fig2d.STUDY.options(True, {"point": "paper"}))
    assert {q["detector_bandwidth_mhz"] for q in pts} == {400.0}
    pts = fig2f.STUDY.grid(fig2f.STUDY.options(True, {"point": "paper"}))
    assert {(q["scene"], q["sequential_mixing"]) for q in pts} == {("paper-lab", True)}
    assert fig11.detector_for(fig11.STUDY.options(True, {"point": "paper"})) == "signed"
    assert fig11.detector_for(fig11.STUDY.options(True, {"detector": "signed"})) == "signed"


def test_composite_runs_the_paper_point_and_merges_it(tmp_path):
    res = run_study(paper.STUDY, tmp_path / "p", quick=True, workers=0, progress=False,
                    overrides={"studies": "fig2c", "sub_set": "fig2c.repeats=40"})
    h = res.summary["fig2c.resolution_2sigma_m"]
    at_paper = json.loads((tmp_path / "p" / "fig2c-paper" / "summary.json").read_text())
    default = json.loads((tmp_path / "p" / "fig2c" / "summary.json").read_text())
    assert h["paper_point"] == at_paper["resolution_2sigma_m"]["ours"]
    assert h["ours"] == default["resolution_2sigma_m"]["ours"]
    assert h["kind"] == "calibrated" and "verdict" not in h  # the joint fit used 25.68 cm
    assert h["calibration_residual_db"] == res.summary["calibration"]["residuals"][
        "fig2c_resolution"]["db"]
    assert h["paper_point"] > 5 * h["ours"]  # 10 m without averaging against 5 m with R = 10
    assert "paper's point: paper-lab at 10 m" in h["cause"] and "default: flat-wall" in h["cause"]
    run = json.loads((tmp_path / "p" / "fig2c-paper" / "run.json").read_text())
    assert run["replicates"] == 4 and run["settings"]["point"] == "paper"
    report = (tmp_path / "p" / "report.md").read_text()
    assert paper.PAPER_WORDS[("fig2c", "resolution_2sigma_m")] in report


def test_docs_blocks_are_generated_and_checked(tmp_path):
    h = paper.classify("fig2d", "resolution_m_at_200mhz",
                       entry(0.017, "millimeter-level", "m", ci95=(0.016, 0.018),
                             paper_point=0.005, paper_point_ci95=(0.004, 0.006)))
    counts = {"reproduced": 1, "consistent": 0, "differs": 0, "no_verdict": 0,
              "prediction": 1, "formula": 0, "calibrated": 0, "input": 0, "not_covered": 5}
    summary = {"fig2d.resolution_m_at_200mhz": h, "counts": counts}
    run = {"quick": True, "settings": {"seed": 7, "point": "both"}}
    (tmp_path / "run").mkdir()
    (tmp_path / "run" / "summary.json").write_text(json.dumps(summary))
    (tmp_path / "run" / "run.json").write_text(json.dumps(run))
    docs = tmp_path / "docs"
    docs.mkdir()
    for rel, names in paperdocs.DOCS.items():
        (tmp_path / rel).write_text("intro\n" + "".join(
            f"<!-- generated:{n} by x -->\nold\n<!-- end:{n} -->\n" for n in names))
    args = [str(tmp_path / "run"), "--root", str(tmp_path)]
    assert paperdocs.main([*args, "--check"]) == 1  # "old" is stale
    assert paperdocs.main(args) == 0
    assert paperdocs.main([*args, "--check"]) == 0
    text = (docs / "paper.md").read_text()
    assert "| Fig. 2d, eq. 28 | `fig2d.resolution_m_at_200mhz` | millimeter-level | " \
        "0.005 [0.004, 0.006] | 0.017 [0.016, 0.018] | prediction | **reproduced** |" in text
    assert "**1 predictions: 1 reproduced, 0 consistent, 0 differ." in text
    assert "(seed 7, point=both)" in text and "No calibration in this run." in text
    assert "| samples per chip | 4 (paper-lab" in text  # generated from the presets
    summary["counts"]["reproduced"] = 2
    (tmp_path / "run" / "summary.json").write_text(json.dumps(summary))
    assert paperdocs.main([*args, "--check"]) == 1
    assert paperdocs.main([str(tmp_path / "nowhere"), "--check"]) == 2


def test_docs_in_the_repository_have_their_blocks():
    from pathlib import Path

    root = Path(paperdocs.__file__).resolve().parents[1]
    for rel, names in paperdocs.DOCS.items():
        text = (root / rel).read_text()
        for n in names:
            assert f"<!-- generated:{n} " in text and f"<!-- end:{n} -->" in text
        assert "shared/seed" not in text
    assert catalogue.get_study("paper") is paper.STUDY


def test_clusters_count_histogram_runs():
    from cdma_lidar.study.fig3 import clusters

    rng = np.random.default_rng(1)
    three = np.concatenate([rng.normal(m, 0.01, n) for m, n in ((4.85, 500), (5.0, 100),
                                                                 (5.15, 400))])
    assert clusters(three, 0.025) == 3
    stray = np.concatenate([three, rng.uniform(4.85, 5.15, 8)])  # a few between the depths
    assert clusters(stray, 0.025) == 3
    assert clusters(rng.normal(5.0, 0.01, 300), 0.025) == 1
    assert clusters(np.array([np.nan]), 0.025) == 0


def test_composite_at_the_paper_point_only(tmp_path):
    res = run_study(paper.STUDY, tmp_path / "p", quick=True, workers=0, progress=False,
                    overrides={"studies": "fig2c,eq26", "point": "paper",
                               "sub_set": "fig2c.repeats=30"})
    h = res.summary["fig2c.resolution_2sigma_m"]
    assert h["paper_point"] == h["ours"] and "paper-lab at 10 m" in h["cause"]
    assert not (tmp_path / "p" / "fig2c-paper").exists()
    angle = res.summary["eq26.angular_resolution_deg"]
    assert angle["kind"] == "formula" and angle["agrees"] and "verdict" not in angle
    eq25 = res.summary["eq26.aligned_averaging_noise_ratio"]
    assert eq25["ci95"][0] <= 1.0 <= eq25["ci95"][1] and eq25["verdict"] == "consistent"
    assert eq25["kind"] == "prediction" and eq25["criterion"].startswith("eq. 25")
    with pytest.raises(ConfigError, match="point"):
        run_study(paper.STUDY, tmp_path / "q", overrides={"point": "lab"}, workers=0,
                  progress=False)


def test_ghost_windows_remove_the_misjudged_pixels(tmp_path):
    from cdma_lidar.study import note5

    res = run_study(note5.STUDY, tmp_path, workers=0, progress=False)
    row = next(r for r in res.table.where(case="removal").rows if r["ghost_ratio"] == 1.0)
    assert row["misjudged_before"] > 0 and row["misjudged_after"] == 0
    assert row["correct_before"] < row["correct_after"] <= row["correct_no_ghost"]
    # the criterion (written before the run): the wall comes back within 2 % of the run
    # without a ghost, at every ghost strength; at 1 x the echo it does not
    h = res.summary["ghost_misjudged_after_removal"]
    assert h["criterion"] == note5.REMOVAL_CRITERION
    kept = [r["correct_after"] / r["correct_no_ghost"] for r in res.table.where(
        case="removal").rows]
    assert h["verdict"] == ("reproduced" if min(kept) >= 0.98 else "differs")
    assert sorted(r["ghost_ratio"] for r in res.table.where(case="removal").rows) == \
        [0.25, 0.5, 1.0]
    # Supp. Fig. 8: a ghost of fixed strength loses to the echo at 5 m and beats it at 10 m
    near, far = res.summary["fig8_ghost_fraction_5m"], res.summary["fig8_ghost_fraction_10m"]
    assert near["ci95"][1] < 0.5 < far["ci95"][0]
    assert near["verdict"] == far["verdict"] == "reproduced"
    assert near["paper"] == note5.PAPER_FIG8_NEAR
    assert (tmp_path / "note5.png").is_file()
    rng, corr = note5.correlation_curve(res.table.where(case="fig8").rows[0], channel=20)
    assert abs(rng[np.argmax(corr)] - 5.0) < 1.0  # at 5 m the wall's peak is the highest
    with pytest.raises(ConfigError, match="ghost_m"):
        run_study(note5.STUDY, tmp_path / "bad", overrides={"ghost_m": "8"}, workers=0,
                  progress=False)


@pytest.mark.parametrize("first", ["paper", "catalogue", "paperdocs"])
def test_any_study_module_imports_first(first):
    """paper.py and catalogue.py once imported each other: importing paper first failed."""
    import subprocess
    import sys

    code = (f"import cdma_lidar.study.{first}; from cdma_lidar.study import catalogue, paper; "
            "assert catalogue.get_study('paper') is paper.STUDY; "
            "assert all(catalogue.get_study(n) is s for n, s in paper.PARTS.items())")
    subprocess.run([sys.executable, "-c", code], check=True)
