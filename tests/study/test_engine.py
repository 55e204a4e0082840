"""The study engine: same tables on every executor, seeds, resume, failures, composites."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from cdma_lidar.errors import ConfigError
from cdma_lidar.study import engine
from cdma_lidar.study.detection import STUDY as DETECTION
from cdma_lidar.study.engine import (
    RunContext,
    Setting,
    Study,
    Table,
    TrialChunk,
    Trials,
    grid_product,
    headline,
    read_csv,
    run_study,
    task_seed,
)
from cdma_lidar.study.executors import Executor
from cdma_lidar.study.fig11 import STUDY as FIG11

#: The detection study shrunk to 4 points x 2 replicates of 20 trials (well under a second).
TINY = {"degrees": "5", "S": "1,2", "snr_db": "-12,-6", "trials": "20", "replicates": "2"}


def model_columns(out: Path, study: Study) -> list[dict]:
    """results.csv without the columns that measure the machine (time, memory)."""
    table = read_csv(out / "results.csv")
    drop = {c for m in study.machine_columns for c in (m, f"{m}_ci95", f"{m}_best")}
    return [{k: v for k, v in row.items() if k not in drop} for row in table.rows]


def test_in_process_and_local_cluster_give_identical_tables(tmp_path):
    local = run_study(DETECTION, tmp_path / "local", overrides=TINY, workers=0, progress=False)
    dask2 = run_study(DETECTION, tmp_path / "dask", overrides=TINY, workers=2, progress=False)
    assert local.computed == dask2.computed == 8 and not local.failures
    assert model_columns(tmp_path / "local", DETECTION) == model_columns(tmp_path / "dask",
                                                                         DETECTION)
    assert json.loads((tmp_path / "local" / "summary.json").read_text()) == \
        json.loads((tmp_path / "dask" / "summary.json").read_text())
    rates = read_csv(tmp_path / "dask" / "results.csv").column("detection_rate")
    assert rates.shape == (4,) and np.all((rates >= 0) & (rates <= 1))
    assert (tmp_path / "dask" / "detection.png").stat().st_size > 1000


def test_worker_count_does_not_change_the_table(tmp_path):
    one = run_study(DETECTION, tmp_path / "w1", overrides=TINY, workers=1, processes=False,
                    progress=False)
    three = run_study(DETECTION, tmp_path / "w3", overrides=TINY, workers=3, processes=False,
                      progress=False)
    assert one.computed == three.computed == 8
    assert model_columns(tmp_path / "w1", DETECTION) == model_columns(tmp_path / "w3", DETECTION)


def test_seeds_differ_per_point_and_replicate_and_follow_the_root():
    a = task_seed(1, {"x": 1}, 0).generate_state(4)
    assert np.array_equal(a, task_seed(1, {"x": 1}, 0).generate_state(4))
    for other in (task_seed(1, {"x": 2}, 0), task_seed(1, {"x": 1}, 1), task_seed(2, {"x": 1}, 0)):
        assert not np.array_equal(a, other.generate_state(4))


def test_another_seed_changes_the_measurement(tmp_path):
    a = run_study(DETECTION, tmp_path / "a", overrides=TINY, workers=0, progress=False)
    b = run_study(DETECTION, tmp_path / "b", overrides={**TINY, "seed": "7"}, workers=0,
                  progress=False)
    assert a.replicates.column("snr_xc_median_db").tolist() != \
        b.replicates.column("snr_xc_median_db").tolist()


def test_resume_recomputes_nothing_when_complete_and_only_what_is_missing(tmp_path):
    out = tmp_path / "run"
    first = run_study(DETECTION, out, overrides=TINY, workers=0, progress=False)
    assert (first.computed, first.cached) == (8, 0)
    table = (out / "results.csv").read_text()
    again = run_study(DETECTION, out, overrides=TINY, workers=0, resume=True, progress=False)
    assert (again.computed, again.cached) == (0, 8)
    assert (out / "results.csv").read_text() == table  # cached timings too: byte for byte
    stored = sorted((out / "tasks").glob("*.json"))
    for path in stored[:3]:
        path.unlink()
    model = model_columns(out, DETECTION)
    partial = run_study(DETECTION, out, overrides=TINY, workers=0, resume=True, progress=False)
    assert (partial.computed, partial.cached) == (3, 5)
    assert model_columns(out, DETECTION) == model
    fresh = run_study(DETECTION, out, overrides=TINY, workers=0, progress=False)
    assert (fresh.computed, fresh.cached) == (8, 0)  # without --resume: start again


def test_resume_ignores_a_corrupt_or_foreign_task_file(tmp_path):
    out = tmp_path / "run"
    run_study(DETECTION, out, overrides=TINY, workers=0, progress=False)
    stored = sorted((out / "tasks").glob("*.json"))
    stored[0].write_text("{not json")
    doc = json.loads(stored[1].read_text())
    doc["params"]["S"] = 99
    stored[1].write_text(json.dumps(doc))
    again = run_study(DETECTION, out, overrides=TINY, workers=0, resume=True, progress=False)
    assert (again.computed, again.cached) == (2, 6)


def _flaky_task(params, seed):
    if params["x"] == 2:
        raise RuntimeError("x = 2 is refused\nsecond line")
    return {"y": params["x"] * 10 + int(seed.generate_state(1)[0] % 3)}


FLAKY = Study("flaky", "a task that raises at one point",
              grid=lambda o: grid_product(x=[1, 2, 3]), task=_flaky_task)


@pytest.mark.parametrize("workers", [0, 2])
def test_a_failing_task_is_reported_with_its_parameters_and_the_others_finish(tmp_path, workers):
    res = run_study(FLAKY, tmp_path, workers=workers, processes=False, progress=False)
    assert [(f.params, f.replicate) for f in res.failures] == [({"x": 2}, 0)]
    assert res.failures[0].error == "RuntimeError: x = 2 is refused"
    assert res.computed == 2
    failures = json.loads((tmp_path / "failures.json").read_text())
    assert failures == [{"params": {"x": 2}, "replicate": 0,
                         "error": "RuntimeError: x = 2 is refused"}]
    rows = read_csv(tmp_path / "results.csv").rows
    assert [r["x"] for r in rows] == [1, 2, 3]
    assert rows[1]["replicates"] == 0 and rows[1]["y"] is None
    assert rows[0]["y"] // 10 == 1 and rows[2]["y"] // 10 == 3


def _always_fails(params: dict, seed: np.random.SeedSequence) -> dict:
    raise RuntimeError(f"x = {params['x']} is refused")


def _reduce_needs_y(table: Table, ctx: RunContext) -> dict:
    return {"y": headline(float(table.column("y")[0]), None, "1")}


def test_when_every_task_fails_the_reducer_is_not_run_and_failures_are_reported(tmp_path):
    study = Study("all-fail", "every task raises", grid=lambda o: grid_product(x=[1, 2]),
                  task=_always_fails, reduce=_reduce_needs_y)
    res = run_study(study, tmp_path, workers=0, progress=False)
    assert len(res.failures) == 2 and res.computed == 0 and res.summary == {}
    assert json.loads((tmp_path / "summary.json").read_text()) == {}


def _sub_reduce(table: Table, ctx: RunContext) -> dict:
    return {"total": headline(float(np.nansum(table.column("y"))), None, "1")}


SUB = Study("sub", "y = 10 x", grid=lambda o: grid_product(x=list(o["xs"])),
            task=lambda p, s: {"y": 10 * p["x"]}, reduce=_sub_reduce,
            settings=(Setting("xs", (1, 2), "x values"),))


def _composite_reduce(table: Table, ctx: RunContext) -> dict:
    a = ctx.run_sub(SUB)
    b = ctx.run_sub(Study("sub2", "y = 10 x", grid=SUB.grid, task=SUB.task, reduce=_sub_reduce,
                          settings=SUB.settings), {"xs": (5,)})
    (ctx.out / "report.md").write_text(f"a={a.summary['total']['ours']}\n")
    return {"a": a.summary["total"], "b": b.summary["total"]}


def test_a_composite_study_runs_its_parts_into_subfolders(tmp_path):
    composite = Study("all", "both", grid=lambda o: [], task=None, reduce=_composite_reduce)
    res = run_study(composite, tmp_path, workers=0, progress=False)
    assert res.summary == {"a": {"ours": 30.0, "paper": None, "unit": "1"},
                           "b": {"ours": 50.0, "paper": None, "unit": "1"}}
    assert (tmp_path / "sub" / "results.csv").exists() and (tmp_path / "report.md").exists()
    assert sorted(res.subs) == ["sub", "sub2"]
    assert json.loads((tmp_path / "run.json").read_text())["sub_studies"] == ["sub", "sub2"]


def test_bad_grids_and_settings_are_config_errors(tmp_path):
    dup = Study("dup", "", grid=lambda o: [{"x": 1}, {"x": 1}], task=_flaky_task)
    with pytest.raises(ConfigError, match="twice"):
        run_study(dup, tmp_path, workers=0)
    with pytest.raises(ConfigError, match="empty"):
        run_study(Study("e", "", grid=lambda o: [], task=_flaky_task), tmp_path, workers=0)
    with pytest.raises(ConfigError, match="no such setting"):
        run_study(DETECTION, tmp_path, overrides={"bogus": "1"}, workers=0)
    with pytest.raises(ConfigError, match="S must be"):
        run_study(DETECTION, tmp_path, overrides={"S": "0"}, workers=0)
    with pytest.raises(ConfigError, match="scheduler"):
        run_study(DETECTION, tmp_path, scheduler="http://x:1")
    with pytest.raises(ConfigError, match="not both"):
        run_study(DETECTION, tmp_path, scheduler="tcp://x:1", workers=2)


def test_an_interrupted_run_keeps_the_finished_tasks_and_resume_does_the_rest(tmp_path):
    state = {"interrupt_at": 3, "calls": 0}

    def task(params, seed):
        state["calls"] += 1
        if params["x"] == state["interrupt_at"]:
            raise KeyboardInterrupt  # Ctrl-C while this task runs
        return {"y": 2 * params["x"]}

    study = Study("ctrlc", "", grid=lambda o: grid_product(x=[1, 2, 3, 4, 5]), task=task)
    with pytest.raises(KeyboardInterrupt):
        run_study(study, tmp_path, workers=0, progress=False)
    assert len(list((tmp_path / "tasks").glob("*.json"))) == 2  # x = 1, 2 finished
    state["interrupt_at"] = None
    state["calls"] = 0
    res = run_study(study, tmp_path, workers=0, resume=True, progress=False)
    assert (res.computed, res.cached, state["calls"]) == (3, 2, 3)
    assert res.table.column("y").tolist() == [2, 4, 6, 8, 10]


# -- trials in chunks ----------------------------------------------------------------------


def _coin_trials(params, chunk: TrialChunk) -> dict:
    out: dict[str, list] = {"v": [], "hit": []}
    for rng, count in chunk.blocks():
        v = rng.normal(params["x"], 1.0, count)
        out["v"] += v.tolist()
        out["hit"] += (v > params["x"] + 0.5).tolist()
    return out


def _coin_row(params, t) -> dict:
    v = np.asarray(t["v"], dtype=float)
    return {"trials_run": len(v), "hit_rate": float(np.mean(t["hit"])) if len(v) else None,
            "median": float(np.median(v)) if len(v) else None,
            "first": float(v[0]) if len(v) else None, "sum": float(np.sum(v))}


#: Points of 0, 1, 5, 17 and 40 trials in blocks of 4: empty points, partial blocks.
COIN = Study("coin", "chunked toy", grid=lambda o: grid_product(x=[1, 2], n=[0, 1, 5, 17, 40]),
             task=None, trials=Trials(count=lambda p: p["n"], run=_coin_trials,
                                      summarise=_coin_row, block=4))


class _Shuffled(Executor):
    """``slots`` workers finishing their jobs in an order drawn by ``rnd``."""

    description = "shuffled"

    def __init__(self, slots: int, rnd) -> None:
        self.slots, self.rnd, self.pending = slots, rnd, []

    def submit(self, key, fn, args):
        self.pending.append((key, fn, args))

    def completed(self):
        while self.pending:
            key, fn, args = self.pending.pop(self.rnd.randrange(len(self.pending)))
            yield key, fn(*args), None


def _coin_reference() -> list[dict]:
    """Each point's row from one pass over all its trials, without the engine."""
    rows = []
    for p in COIN.grid(COIN.options()):
        seed = task_seed(COIN.options().seed, p, 0)
        cols = _coin_trials(p, TrialChunk(seed, 0, p["n"], 4))
        rows.append({**p, "replicates": 1, **_coin_row(p, cols)})
    return rows


def _shuffled_run(study, out, slots: int, rnd, chunk):
    """``run_study`` on ``slots`` workers whose tasks finish in ``rnd``'s shuffled order."""
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(engine, "make_executor", lambda *a, **k: _Shuffled(slots, rnd))
        return run_study(study, out, workers=slots, progress=False, chunk_trials=chunk)


@settings(max_examples=25)
@given(chunk=st.one_of(st.none(), st.integers(1, 45)), slots=st.integers(1, 4),
       rnd=st.randoms(use_true_random=False))
def test_chunked_tables_do_not_depend_on_chunk_size_worker_count_or_order(
        tmp_path_factory, chunk, slots, rnd):
    out = tmp_path_factory.mktemp("coin")
    res = _shuffled_run(COIN, out, slots, rnd, chunk)
    assert res.table.rows == _coin_reference()
    assert res.computed == len(list((out / "tasks").glob("*.json")))
    if chunk is not None:  # every point's trials in ceil(n / whole blocks) chunks
        size = -(-chunk // 4) * 4
        assert res.computed == 2 * sum(max(1, -(-n // size)) for n in (0, 1, 5, 17, 40))


def _coin_stop(params, t) -> bool:
    """Stop a point once its first trials hold two hits (data-dependent on purpose)."""
    return int(np.sum(t["hit"])) >= 2


#: COIN with a sequential stop asked after 8, 16 and 32 trials.
STOPPING = dataclasses.replace(COIN, name="coin-stop", trials=dataclasses.replace(
    COIN.trials, stop=_coin_stop, first_look=6))  # 6 -> 8: looks fall on whole blocks


def _stopping_reference() -> list[dict]:
    """Each point's row from its trials up to the first look where the rule stops it."""
    rows = []
    for p in STOPPING.grid(STOPPING.options()):
        seed = task_seed(STOPPING.options().seed, p, 0)
        cols = {k: np.asarray(v) for k, v in _coin_trials(p, TrialChunk(seed, 0, p["n"], 4)
                                                          ).items()}
        looks = STOPPING.trials.looks(p["n"])
        end = next(n for n in looks if n == looks[-1] or _coin_stop(p, {k: v[:n] for k, v
                                                                      in cols.items()}))
        rows.append({**p, "replicates": 1, **_coin_row(p, {k: v[:end] for k, v in cols.items()})})
    return rows


def test_looks_double_from_the_first_on_whole_blocks():
    assert STOPPING.trials.looks(40) == [8, 16, 32, 40]
    assert STOPPING.trials.looks(8) == [8] and STOPPING.trials.looks(0) == [0]
    assert COIN.trials.looks(40) == [40]  # no rule, no looks


@settings(max_examples=20)
@given(chunk=st.one_of(st.none(), st.integers(1, 45)), slots=st.integers(1, 4),
       rnd=st.randoms(use_true_random=False))
def test_a_stopped_point_does_not_depend_on_chunk_size_worker_count_or_order(
        tmp_path_factory, chunk, slots, rnd):
    out = tmp_path_factory.mktemp("stop")
    res = _shuffled_run(STOPPING, out, slots, rnd, chunk)
    reference = _stopping_reference()
    assert res.table.rows == reference
    runs = [r["trials_run"] for r in reference]
    assert any(r < p["n"] for r, p in zip(runs, STOPPING.grid(STOPPING.options()),
                                          strict=True))  # the rule did stop some points
    # no trial past a point's stopping look was run
    for path in (out / "tasks").glob("*.json"):
        doc = json.loads(path.read_text())
        row = next(r for r in reference if r["x"] == doc["params"]["x"]
                   and r["n"] == doc["params"]["n"])
        assert doc["trials"][1] <= max(row["trials_run"], 1) or row["n"] == 0


def test_a_resumed_run_stops_where_a_fresh_run_stops(tmp_path):
    whole = run_study(COIN, tmp_path, workers=0, progress=False, chunk_trials=4)
    assert whole.table.rows == _coin_reference()
    res = run_study(STOPPING, tmp_path / "s", workers=0, progress=False)
    # the same chunks kept by a run without the rule: resume reads the looks from them
    for path in (tmp_path / "tasks").glob("*.json"):
        doc = json.loads(path.read_text())
        doc["study"] = "coin-stop"
        (tmp_path / "s" / "tasks" / path.name).write_text(json.dumps(doc))
    again = run_study(STOPPING, tmp_path / "s", workers=0, progress=False, resume=True)
    assert again.table.rows == res.table.rows == _stopping_reference()
    assert again.computed == 0


def test_chunks_follow_the_machine_and_stay_whole_blocks(tmp_path):
    res = run_study(COIN, tmp_path, workers=0, progress=False)
    assert res.table.rows == _coin_reference()
    for path in (tmp_path / "tasks").glob("*.json"):
        a, b = json.loads(path.read_text())["trials"]
        assert a % 4 == 0 and (b % 4 == 0 or b in (1, 5, 17))


def test_an_interrupted_chunked_run_resumes_from_its_chunks_with_any_chunk_size(tmp_path):
    calls = {"n": 0, "stop_at": 6}

    def run(params, chunk):
        calls["n"] += 1
        if calls["n"] == calls["stop_at"]:
            raise KeyboardInterrupt  # Ctrl-C in the sixth chunk
        return _coin_trials(params, chunk)

    study = dataclasses.replace(COIN, trials=dataclasses.replace(COIN.trials, run=run))
    with pytest.raises(KeyboardInterrupt):
        run_study(study, tmp_path, workers=0, progress=False, chunk_trials=8)
    kept = len(list((tmp_path / "tasks").glob("*.json")))
    assert kept == 5
    calls.update(n=0, stop_at=None)
    res = run_study(study, tmp_path, workers=0, progress=False, resume=True, chunk_trials=12)
    assert res.cached == kept and res.computed == calls["n"] > 0
    assert res.table.rows == _coin_reference()
    again = run_study(study, tmp_path, workers=0, progress=False, resume=True)
    assert (again.computed, again.cached) == (0, res.computed + res.cached)


def test_a_failing_chunk_fails_its_point_only_and_resume_keeps_its_finished_chunks(tmp_path):
    def run(params, chunk):
        if params["n"] == 40 and chunk.start >= 16:
            raise RuntimeError("late chunk refused")
        return _coin_trials(params, chunk)

    study = dataclasses.replace(COIN, trials=dataclasses.replace(COIN.trials, run=run))
    res = run_study(study, tmp_path, workers=0, progress=False, chunk_trials=8)
    assert sorted(f.params["x"] for f in res.failures) == [1, 2]
    assert {f.params["n"] for f in res.failures} == {40}
    assert [r["replicates"] for r in res.table.rows].count(0) == 2
    good = run_study(COIN, tmp_path, workers=0, progress=False, resume=True, chunk_trials=8)
    assert good.cached == res.computed and not good.failures
    assert good.table.rows == _coin_reference()


def test_resume_with_nothing_missing_starts_no_cluster(tmp_path, monkeypatch):
    first = run_study(COIN, tmp_path, workers=0, progress=False)
    assert first.computed > 0
    plain = tmp_path / "plain"
    run_study(DETECTION, plain, overrides=TINY, workers=0, progress=False)

    def no_cluster(*args, **kwargs):
        raise AssertionError("an executor was started with nothing to run")

    monkeypatch.setattr(engine, "make_executor", no_cluster)
    again = run_study(COIN, tmp_path, workers=2, resume=True, progress=False)
    assert (again.computed, again.cached) == (0, first.computed)
    assert json.loads((tmp_path / "run.json").read_text())["engine"].startswith("none")
    done = run_study(DETECTION, plain, overrides=TINY, workers=2, resume=True, progress=False)
    assert (done.computed, done.cached) == (0, 8)
    with pytest.raises(AssertionError, match="nothing to run"):  # the factory is live
        run_study(COIN, tmp_path / "new", workers=2, progress=False)


def test_a_trial_study_checks_its_columns(tmp_path):
    def run(params, chunk):
        return {"v": [0.0] * (len(chunk) + 1)}

    study = dataclasses.replace(COIN, trials=dataclasses.replace(COIN.trials, run=run))
    res = run_study(study, tmp_path, workers=0, progress=False)
    assert res.failures and "one value per trial" in res.failures[0].error
    with pytest.raises(ConfigError, match="not both"):
        Study("both", "", grid=COIN.grid, task=_flaky_task, trials=COIN.trials)
    with pytest.raises(ConfigError, match="chunk_trials"):
        run_study(COIN, tmp_path, workers=0, chunk_trials=0)


def test_fig11_is_the_same_in_one_chunk_or_many(tmp_path):
    small = {"channels_order11": (60,), "channels_order13": (), "channels_order15": (),
             "trials": "10", "S": "4"}
    one = run_study(FIG11, tmp_path / "one", overrides=small, workers=0, progress=False,
                    chunk_trials=1000)
    many = run_study(FIG11, tmp_path / "many", overrides=small, workers=0, progress=False,
                     chunk_trials=1)
    assert (one.computed, many.computed) == (1, 2)  # blocks of 8: 8 + 2 trials
    assert model_columns(tmp_path / "one", FIG11) == model_columns(tmp_path / "many", FIG11)


def test_chunked_study_on_a_dask_cluster_gives_the_reference_table(tmp_path):
    res = run_study(COIN, tmp_path, workers=2, processes=False, progress=False, chunk_trials=4)
    assert res.table.rows == _coin_reference() and res.computed == 38
