"""fig11's grid refinement: a capacity read off a grid is refined until a grid point lies
inside its 95 % interval (the trials, not the grid's step, set its width)."""

from __future__ import annotations

import json

from cdma_lidar.study.engine import Table, read_csv, run_study
from cdma_lidar.study.fig11 import STUDY, refine_points
from cdma_lidar.study.paperlab import crossing_ci


def _table(points: list[tuple[int, int, float, int]], fidelity: str = "full") -> Table:
    cols = ["degree", "channels", "fidelity", "error_rate_signed", "trials_run"]
    return Table(cols, [dict(zip(cols, (d, k, fidelity, e, n), strict=True))
                        for d, k, e, n in points])


def test_refine_points_splits_an_interval_with_no_grid_point_inside():
    two = [(11, 100, 0.0, 1000), (11, 200, 0.5, 1000)]
    assert refine_points(_table(two)) == {11: [150]}
    # a point inside the interval (undecided at 10 %): the trials set the width, no more
    assert refine_points(_table([*two, (11, 150, 0.1, 1000)])) == {}
    # decided above: the interval is [100, 150] with nothing inside, split again
    assert refine_points(_table([*two, (11, 150, 0.3, 1000)])) == {11: [125]}
    # each degree on its own; a grid that never crosses, adjacent counts, the SGA: nothing
    assert refine_points(_table([*two, (13, 300, 0.0, 1000), (13, 600, 0.02, 1000)])) == \
        {11: [150]}
    assert refine_points(_table([(11, 100, 0.0, 1000), (11, 101, 0.5, 1000)])) == {}
    assert refine_points(_table(two, fidelity="sga")) == {}
    # the interval is eq. 9's (signed): the receiver's |corr| column is not read
    t = _table(two)
    t.add_column("error_rate", [0.5, 0.9])
    assert refine_points(t) == {11: [150]}


def test_fig11_refines_the_capacity_interval_of_its_grid(tmp_path):
    """Order 11 at S = 4 from a coarse grid (40, 400): each round runs the midpoint of the
    signed capacity's interval into its own folder, and the summary reads the capacity off
    every point run (a few seconds)."""
    small = {"channels_order11": (40, 400), "channels_order13": (), "channels_order15": (),
             "trials": "64", "S": "4", "point": "paper"}
    coarse = run_study(STUDY, tmp_path / "coarse", overrides={**small, "refine_rounds": 0},
                       workers=0, progress=False)
    assert coarse.summary["workable_channels_order11"]["paper_point_ci95"] == [40, 400]
    assert not (tmp_path / "coarse" / "fig11-refined-1").exists()
    res = run_study(STUDY, tmp_path / "fine", overrides={**small, "refine_rounds": 3},
                    workers=0, progress=False)
    rounds = sorted((tmp_path / "fine").glob("fig11-refined-*"))
    assert 1 <= len(rounds) <= 3
    ks = [40, 400]
    for i, folder in enumerate(rounds, 1):
        assert folder.name == f"fig11-refined-{i}"
        run = json.loads((folder / "run.json").read_text())
        assert run["settings"]["refine_rounds"] == 0 and run["settings"]["S"] == 4
        (k,) = read_csv(folder / "results.csv").column("channels").astype(int).tolist()
        ks.append(k)
    tables = [read_csv(tmp_path / "fine" / "results.csv"),
              *(read_csv(f / "results.csv") for f in rounds)]
    rows = [r for t in tables for r in t.rows]
    every = Table(tables[0].columns, rows)
    lo, hi = crossing_ci(every.column("channels"), every.column("error_rate_signed"),
                         every.column("trials_run"))
    h = res.summary["workable_channels_order11"]
    assert h["paper_point_ci95"] == [lo, hi] and 40 <= lo < hi <= 400 and hi - lo < 360
    assert lo <= h["paper_point"] <= hi
    # refined until a point lies inside, or the rounds ran out
    assert any(lo < k < hi for k in ks) or len(rounds) == 3
    assert refine_points(every) == {} or len(rounds) == 3
