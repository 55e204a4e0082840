"""The study engine: a parameter grid, a seeded task per point and replicate, a reducer.

This module runs a study (:func:`run_study`) and re-exports the study model, so a study
imports everything from here. The rooms behind it, one job each:
:mod:`~cdma_lidar.study.model` (the study model and seeding),
:mod:`~cdma_lidar.study.scheduler` (chunks of trials and what runs on a worker),
:mod:`~cdma_lidar.study.executors` (in this process or on Dask),
:mod:`~cdma_lidar.study.store` (the resume store) and :mod:`~cdma_lidar.study.stats`
(the replicates' means and 95 % intervals).

A :class:`Study` declares

* ``settings``: named knobs a user may change with ``--set KEY=VALUE`` (each with a
  default and, optionally, a smaller ``--quick`` default), e.g. the axes' values;
* ``grid(options) -> list[dict]``: the canonical list of points (parameter dicts, JSON
  scalars only) built from those settings; bad values raise ConfigError;
* ``task(params, seed) -> dict``: measures ONE point for ONE replicate and returns flat
  JSON scalars (the measured columns, units in their names: ``_s``, ``_m``, ``_mib``).
  ``seed`` is a :class:`numpy.random.SeedSequence`; the task draws every random number
  from it (``np.random.default_rng(seed)``, or ``int(seed.generate_state(1)[0])`` for an
  API that takes an integer seed) and from nothing else;
* or, for a study of many independent random trials per point, ``trials``: a
  :class:`Trials` (``count``, ``run`` over one :class:`TrialChunk`, ``summarise`` of all
  the point's per-trial values) that the engine runs in chunks spread over the workers;
* ``reduce(table, ctx) -> summary``: turns the per-point table into figures (PNG, in
  ``ctx.out``) and the headline numbers (:func:`headline`); it may add columns to the
  table and write extra files; a composite study runs other studies from here with
  :meth:`RunContext.run_sub`.

Seeding (results never depend on where or in which order tasks ran): task (point p,
replicate r) gets ``SeedSequence(root_seed, spawn_key=(h0, h1, h2, h3, r))`` where
``h`` are the first 128 bits of the SHA-256 of the point's canonical JSON: a spawned
child of the study's root sequence named by the point itself, so adding points to a
grid does not change the seeds (or the cached results) of the others. A :class:`Trials`
study's block b of trials (``Trials.block`` trials each) draws from
``SeedSequence(root_seed, spawn_key=(h0, h1, h2, h3, r, b))`` (:func:`block_seed`):
chunks are whole blocks, so no chunking changes what any trial draws.

Chunks: each (point, replicate) first runs one block (its seconds per trial measured);
then the point with the most time left gets a chunk of about 1/(2 x workers) of all the
time left, clamped to MIN_CHUNK_S..MAX_CHUNK_S (guided self-scheduling), or
``chunk_trials`` trials when given.

Storage (``--out DIR``)::

    DIR/tasks/<key>.json  one finished task: params, replicate, result (written atomically
                          as soon as the task returns; key = SHA-256 of study, version,
                          params, replicate and root seed); for a Trials study one
                          finished chunk: params, replicate, trials [start, stop), one
                          list per column
    DIR/replicates.csv    one row per task (the tidy raw table)
    DIR/results.csv       one row per point: parameters, then measured columns (the mean
                          over replicates, with ``<col>_ci95`` half-widths when there
                          are at least two replicates, and ``<col>_best``, the minimum,
                          for machine columns); units in the column names
    DIR/summary.json      headline numbers, each {"ours": x, "paper": y or null, "unit": u}
    DIR/run.json          what ran: study, settings, engine, counts, failures, wall time,
                          the computed tasks' own wall, CPU and runqueue-wait seconds
                          in the workers (``task_cpu_s`` / ``wall_time_s``: the cores
                          kept busy; ``task_wait_s``: time other load took from them),
                          the columns that measure the machine (time, memory) rather
                          than the model
    DIR/failures.json     tasks that raised, with their parameters and the error
    DIR/*.png             the study's figures

``resume=True`` keeps ``DIR/tasks`` and computes only the missing tasks (the trials no
kept chunk holds, whatever chunk size ran before); with nothing missing no executor is
started (no Dask cluster). Without it the folder's earlier task results are discarded
first. A task that raises is recorded in
``failures.json`` (parameters, replicate, error) and the others go on; failed tasks are
not cached, so ``--resume`` retries them.

Executors: ``workers=0`` runs the tasks one after the other in this process (no Dask);
otherwise Dask: a ``LocalCluster`` of ``workers`` single-threaded worker processes
(default: one per CPU), or the cluster whose scheduler listens at ``scheduler``
(``tcp://`` or ``tls://HOST:PORT``; TLS settings come from Dask's configuration,
``distributed.comm.tls.*``, or ``security=``); ``gpus=N``: a local cluster of one worker
per GPU (worker i sees only GPU i). Local worker processes get :data:`WORKER_ENV`.
"""

from __future__ import annotations

import dataclasses
import json
import logging
import os
import time
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from cdma_lidar.errors import ConfigError
from cdma_lidar.fileio import atomic_write_text
from cdma_lidar.study.executors import Executor, Lazy, check_executor, make_executor
from cdma_lidar.study.model import (
    COMMON_SETTINGS,
    ENGINE_VERSION,
    Headline,
    Params,
    RunOptions,
    Setting,
    Study,
    TrialChunk,
    Trials,
    block_seed,
    canonical,
    grid_product,
    headline,
    parse_set,
    task_key,
    task_seed,
)
from cdma_lidar.study.scheduler import Unit, execute_chunk, execute_task, next_job, units_of
from cdma_lidar.study.stats import aggregate
from cdma_lidar.study.store import chunk_key, prepare_out, save_chunk, save_task
from cdma_lidar.study.table import Table, plain, read_csv

__all__ = [
    "COMMON_SETTINGS",
    "ENGINE_VERSION",
    "Headline",
    "RunContext",
    "RunOptions",
    "RunResult",
    "Setting",
    "Study",
    "Table",
    "TaskFailure",
    "TrialChunk",
    "Trials",
    "block_seed",
    "grid_product",
    "headline",
    "make_executor",
    "parse_set",
    "read_csv",
    "run_study",
    "task_key",
    "task_seed",
]

log = logging.getLogger(__name__)

@dataclass(frozen=True)
class TaskFailure:
    """A task that raised: its point, replicate and the error (type: message)."""

    params: Params
    replicate: int
    error: str


@dataclass
class RunResult:
    """What :func:`run_study` produced (the files are in ``out``).

    ``computed`` and ``cached`` count tasks: chunks of trials for a study with
    :class:`Trials`, one per (point, replicate) otherwise.
    """

    study: str
    out: Path
    table: Table
    replicates: Table
    summary: dict[str, Headline]
    failures: list[TaskFailure]
    computed: int
    cached: int
    subs: dict[str, RunResult] = field(default_factory=dict)


@dataclass
class RunContext:
    """Handed to a reducer: where to write, the options, and a way to run sub-studies."""

    study: Study
    out: Path
    options: RunOptions
    executor: Executor
    resume: bool
    progress: bool
    subs: dict[str, RunResult] = field(default_factory=dict)
    chunk_trials: int | None = None

    def run_sub(self, study: Study, overrides: Mapping[str, Any] | None = None) -> RunResult:
        """Run ``study`` into ``out/<study.name>`` on the same executor, quick and resume.

        ``seed`` and ``replicates`` are inherited unless ``overrides`` sets them.
        """
        inherited = {"seed": self.options.seed}
        inherited.update(overrides or {})
        result = _run(study, self.out / study.name, study.options(self.options.quick, inherited),
                      self.executor, resume=self.resume, progress=self.progress,
                      chunk_trials=self.chunk_trials)
        self.subs[study.name] = result
        return result


def run_study(study: Study, out: str | os.PathLike[str], *, quick: bool = False,
              overrides: Mapping[str, Any] | None = None, workers: int | None = None,
              scheduler: str | None = None, resume: bool = False, progress: bool = True,
              security: Any = None, processes: bool = True,
              connect_timeout_s: float = 10.0, gpus: int = 0,
              chunk_trials: int | None = None) -> RunResult:
    """Run ``study`` into folder ``out`` and write its table, summary and figures.

    ``workers``: 0 runs in this process without Dask, N > 0 a local Dask cluster of N
    single-threaded worker processes (threads if ``processes`` is False), None one per
    CPU; ``scheduler`` sends the tasks to an existing Dask cluster instead (``security``:
    a ``distributed.security.Security`` for ``tls://``; default from Dask's configuration),
    giving up after ``connect_timeout_s``; ``gpus`` > 0 a local cluster of one worker per
    GPU (worker i sees GPU i only). The cluster starts only when a task must run: a
    resumed run with nothing missing starts none.

    A study with :class:`Trials` runs in chunks of trials sized to take MIN_CHUNK_S to
    MAX_CHUNK_S each on this machine, or of ``chunk_trials`` trials (rounded up to whole
    blocks); the tables are the same either way.
    """
    options = study.options(quick, overrides)
    _check_grid(study, study.grid(options))  # a bad grid fails before any cluster starts
    check_executor(workers, scheduler, gpus)
    if chunk_trials is not None and not (isinstance(chunk_trials, int) and chunk_trials >= 1):
        raise ConfigError(f"chunk_trials {chunk_trials!r}: expected an integer >= 1 (None: "
                          "follow the machine)", "chunk_trials")
    out_dir = Path(out)
    executor = Lazy(lambda: make_executor(workers, scheduler, security=security,
                                           processes=processes,
                                           connect_timeout_s=connect_timeout_s, gpus=gpus))
    try:
        return _run(study, out_dir, options, executor, resume=resume, progress=progress,
                    chunk_trials=chunk_trials)
    finally:
        executor.close()

def _finish(study: Study, u: Unit) -> dict[str, Any]:
    """The row of a unit whose chunks are all done (raises what the study raises)."""
    if study.trials is None:
        return u.done[0][1]
    columns = u.columns(u.total or 0)
    return {k: plain(v) for k, v in study.trials.summarise(dict(u.params), columns).items()}


def _run(study: Study, out: Path, options: RunOptions, executor: Executor, *,
         resume: bool, progress: bool, chunk_trials: int | None = None) -> RunResult:
    t0 = time.monotonic()
    points = study.grid(options)
    _check_grid(study, points)
    tasks_dir = prepare_out(out, resume)
    root, reps = options.seed, options.replicates
    units, cached = units_of(study, points, reps, root, tasks_dir, resume) \
        if study.runs_tasks else ([], 0)
    log.info("study %s: %d points x %d replicates, %d tasks cached", study.name,
             len(points), reps, cached)

    failures: list[TaskFailure] = []
    rows: dict[int, dict[str, Any]] = {}

    def fail(u: Unit, exc: BaseException) -> None:
        u.failed = True
        msg = f"{type(exc).__name__}: {exc}".splitlines()[0]
        failures.append(TaskFailure(u.params, u.replicate, msg))
        log.warning("study %s: task %s replicate %d failed: %s", study.name,
                    canonical(u.params), u.replicate, msg)

    def complete(i: int, u: Unit) -> None:
        if study.trials is not None and not u.failed:
            try:
                skipped = u.advance(study.trials)
            except Exception as exc:  # the stopping rule raised: the point fails
                fail(u, exc)
                return
            if skipped and bar is not None:
                bar.total = max(bar.n, bar.total - skipped)
                bar.refresh()
        if not u.todo and not u.inflight and not u.failed:
            try:
                rows[i] = _finish(study, u)
            except Exception as exc:
                fail(u, exc)

    work = sum(1 if u.total is None else max(u.left(), 1) if u.todo else 0 for u in units)
    bar = _progress(work, study.name, progress, "task" if study.trials is None else "trial")
    for i, u in enumerate(units):
        complete(i, u)
    computed = 0
    busy = [0.0, 0.0, 0.0]  # wall, CPU and runqueue-wait seconds of the tasks computed
    index = {id(u): i for i, u in enumerate(units)}
    jobs: dict[str, tuple[Unit, int, int]] = {}
    try:
        if any(u.todo for u in units):
            slots = executor.slots
            inflight = 2 * slots if slots > 1 else 1

            def fill() -> None:
                while len(jobs) < inflight:
                    job = next_job(units, slots, chunk_trials)
                    if job is None:
                        return
                    u, a, b = job
                    if a is None or b is None:  # a plain task
                        key = task_key(study, u.params, u.replicate, root)
                        jobs[key] = (u, 0, 1)
                        executor.submit(key, execute_task, (study.task, u.params, root,
                                                             u.replicate))
                    else:
                        key = chunk_key(study, u.params, u.replicate, root, a, b)
                        jobs[key] = (u, a, b)
                        executor.submit(key, execute_chunk, (study.trials, u.params, root,
                                                              u.replicate, a, b))

            fill()
            for key, result, exc in executor.completed():
                u, a, b = jobs.pop(key)
                u.inflight -= 1
                if exc is not None:
                    if not u.failed:
                        fail(u, exc)
                else:
                    value, seconds, cpu, wait = result
                    busy[0] += seconds
                    busy[1] += cpu
                    busy[2] += wait
                    u.done[a] = (b, value)
                    computed += 1
                    if u.total is None:
                        save_task(tasks_dir, study, u.params, u.replicate, root, value)
                    else:
                        u.rate = seconds / max(1, b - a)
                        save_chunk(tasks_dir, study, u.params, u.replicate, root, a, b, value)
                    complete(index[id(u)], u)
                if bar is not None:
                    bar.update(1 if u.total is None else max(b - a, 1 if u.total == 0 else 0))
                    if failures:
                        bar.set_postfix(failed=len(failures))
                fill()
    finally:
        if bar is not None:
            bar.close()

    rep_table = Table([*points[0], "replicate"] if points else [])
    for i, u in enumerate(units):
        if i in rows:
            rep_table.append({**u.params, "replicate": u.replicate, **rows[i]})
    table = aggregate(points, rep_table, reps, study.machine_columns)
    ctx = RunContext(study, out, options, executor, resume, progress,
                     chunk_trials=chunk_trials)
    # A reducer needs measured columns: when every task failed there are none, and the
    # run reports its failures (exit 1) with an empty summary instead of a reducer's crash.
    if study.reduce is None or (points and not rows):
        summary: dict[str, Any] = {}
    else:
        summary = dict(study.reduce(table, ctx))

    atomic_write_text(out / "replicates.csv", rep_table.to_csv())
    atomic_write_text(out / "results.csv", table.to_csv())
    atomic_write_text(out / "summary.json", json.dumps(summary, indent=2, sort_keys=True) + "\n")
    failure_rows = [dataclasses.asdict(f) for f in failures]
    atomic_write_text(out / "failures.json", json.dumps(failure_rows, indent=2) + "\n")
    info = {
        "study": study.name, "version": study.version, "quick": options.quick,
        "settings": {k: list(v) if isinstance(v, tuple) else v
                     for k, v in options.values.items()},
        "engine": executor.description, "points": len(points), "replicates": reps,
        "tasks": computed + cached, "computed": computed, "cached": cached,
        "failed": len(failures), "wall_time_s": round(time.monotonic() - t0, 3),
        "executor_start_s": round(getattr(executor, "start_s", 0.0), 3),
        "task_wall_s": round(busy[0], 3), "task_cpu_s": round(busy[1], 3),
        "task_wait_s": round(busy[2], 3),
        "machine_columns": list(study.machine_columns),
        "sub_studies": sorted(ctx.subs),
    }
    atomic_write_text(out / "run.json", json.dumps(info, indent=2) + "\n")
    return RunResult(study.name, out, table, rep_table, summary, failures,
                     computed=computed, cached=cached, subs=ctx.subs)


def _check_grid(study: Study, points: list[Params]) -> None:
    if study.runs_tasks and not points:
        raise ConfigError(f"study {study.name!r}: the grid is empty; check the --set values",
                          "grid")
    seen: set[str] = set()
    names = list(points[0]) if points else []
    for p in points:
        if list(p) != names:
            raise ConfigError(f"study {study.name!r}: every point must have the parameters "
                              f"{names}, not {list(p)}", "grid")
        for k, v in p.items():
            if not isinstance(v, int | float | str | bool) and v is not None:
                raise ConfigError(f"study {study.name!r}: parameter {k!r} must be a JSON "
                                  f"scalar, not {type(v).__name__}", k)
        c = canonical(p)
        if c in seen:
            raise ConfigError(f"study {study.name!r}: the grid has the point {c} twice", "grid")
        seen.add(c)

def _progress(total: int, name: str, enabled: bool,  # type: ignore[no-untyped-def]
              unit: str = "task"):
    if not enabled or total == 0:
        return None
    from tqdm import tqdm  # deferred: 60 ms at start-up for a bar only a run shows

    return tqdm(total=total, desc=f"study {name}", unit=unit, dynamic_ncols=True)
