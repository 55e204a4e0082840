"""fig11's and fig2e's sequential stop: a point ends early only when it is decided."""

from __future__ import annotations

import numpy as np
from hypothesis import given
from hypothesis import strategies as st

from cdma_lidar.study.fig11 import TRIALS, decided
from cdma_lidar.study.paperlab import wilson

PARAMS = {"trials": 1000}


def _cols(n: int, errors: int, signed: int) -> dict[str, np.ndarray]:
    return {"error": np.arange(n) < errors, "error_signed": np.arange(n) < signed}


def test_the_looks_of_a_full_point():
    assert TRIALS.looks(1000) == [64, 128, 256, 512, 1000]
    assert TRIALS.looks(40) == [40]


def test_far_points_stop_at_the_first_look_and_near_ones_do_not():
    assert decided(PARAMS, _cols(64, 0, 0))        # no error in 64: far below 10 %
    assert decided(PARAMS, _cols(64, 64, 60))      # almost every trial wrong: far above
    assert not decided(PARAMS, _cols(64, 6, 6))    # 9 %: could be either side
    assert not decided(PARAMS, _cols(64, 0, 6))    # one detector undecided keeps it going
    assert not decided(PARAMS, _cols(64, 3, 0))    # 3 of 64: 95 % would decide, 2.5 sigma not


@given(look=st.sampled_from(TRIALS.looks(1000)[:-1]), data=st.data())
def test_a_stopped_point_is_on_one_side_at_95_percent(look, data):
    errors = data.draw(st.integers(0, look))
    signed = data.draw(st.integers(0, look))
    if decided(PARAMS, _cols(look, errors, signed)):
        for k in (errors, signed):
            lo, hi = wilson(k, look)  # the interval the capacity's bracket uses
            assert hi < 0.10 or lo > 0.10


def test_fig11_stops_far_points_at_the_first_look_whatever_the_chunks(tmp_path):
    from cdma_lidar.study.engine import read_csv, run_study
    from cdma_lidar.study.fig11 import STUDY

    small = {"channels_order11": (8, 1500), "channels_order13": (), "channels_order15": (),
             "trials": "128", "S": "4", "refine_rounds": 0}
    rows = []
    for chunk in (8, 1000):
        out = tmp_path / str(chunk)
        res = run_study(STUDY, out, overrides=small, workers=0, progress=False,
                        chunk_trials=chunk)
        assert not res.failures
        table = read_csv(out / "results.csv")
        assert table.column("trials_run").tolist() == [64, 64]  # decided: 0 % and ~100 %
        assert table.column("error_rate").tolist()[0] == 0.0
        assert table.column("error_rate").tolist()[1] > 0.5
        rows.append([{k: v for k, v in r.items() if not k.startswith("time_per_trial")}
                     for r in table.rows])
    assert rows[0] == rows[1]
