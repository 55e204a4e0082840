"""The study engine: a parameter grid, a seeded task per point and replicate, a reducer.

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
* ``reduce(table, ctx) -> summary``: turns the per-point table into figures (PNG, in
  ``ctx.out``) and the headline numbers (:func:`headline`); it may add columns to the
  table and write extra files; a composite study runs other studies from here with
  :meth:`RunContext.run_sub`.

Seeding (results never depend on where or in which order tasks ran): task (point p,
replicate r) gets ``SeedSequence(root_seed, spawn_key=(h0, h1, h2, h3, r))`` where
``h`` are the first 128 bits of the SHA-256 of the point's canonical JSON: a spawned
child of the study's root sequence named by the point itself, so adding points to a
grid does not change the seeds (or the cached results) of the others.

Storage (``--out DIR``)::

    DIR/tasks/<key>.json  one finished task: params, replicate, result (written atomically
                          as soon as the task returns; key = SHA-256 of study, version,
                          params, replicate and root seed)
    DIR/replicates.csv    one row per task (the tidy raw table)
    DIR/results.csv       one row per point: parameters, then measured columns (the mean
                          over replicates, with ``<col>_ci95`` half-widths when there
                          are at least two replicates, and ``<col>_best``, the minimum,
                          for machine columns); units in the column names
    DIR/summary.json      headline numbers, each {"ours": x, "paper": y or null, "unit": u}
    DIR/run.json          what ran: study, settings, engine, counts, failures, the columns
                          that measure the machine (time, memory) rather than the model
    DIR/failures.json     tasks that raised, with their parameters and the error
    DIR/*.png             the study's figures

``resume=True`` keeps ``DIR/tasks`` and computes only the missing tasks; without it the
folder's earlier task results are discarded first. A task that raises is recorded in
``failures.json`` (parameters, replicate, error) and the others go on; failed tasks are
not cached, so ``--resume`` retries them.

Executors: ``workers=0`` runs the tasks one after the other in this process (no Dask);
otherwise Dask: a ``LocalCluster`` of ``workers`` single-threaded worker processes
(default: one per CPU), or the cluster whose scheduler listens at ``scheduler``
(``tcp://`` or ``tls://HOST:PORT``; TLS settings come from Dask's configuration,
``distributed.comm.tls.*``, or ``security=``).
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import logging
import math
import os
import re
import shutil
import socket
import time
from collections.abc import Callable, Iterable, Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from cdma_lidar.errors import ConfigError, LinkError
from cdma_lidar.fileio import atomic_write_text
from cdma_lidar.study.table import Scalar, Table, plain, read_csv

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

#: Part of every task key: bump when the storage format changes.
ENGINE_VERSION = 1

Params = dict[str, Scalar]
Headline = dict[str, Any]

_SCHEDULER_RE = re.compile(r"^(tcp|tls|inproc|ucx)://[^\s/]+$")


def headline(ours: float | int | None, paper: float | int | None = None,
             unit: str = "") -> Headline:
    """One summary.json entry: our number, the paper's (or None) and the unit."""
    def clean(x: float | int | None) -> float | int | None:
        if x is None:
            return None
        x = float(x) if not isinstance(x, int | np.integer) else int(x)
        return None if isinstance(x, float) and not math.isfinite(x) else x
    return {"ours": clean(ours), "paper": clean(paper), "unit": unit}


# ------------------------------------------------------------------ settings


@dataclass(frozen=True)
class Setting:
    """A study knob settable with ``--set NAME=VALUE``.

    The type comes from ``default``: int, float, str, bool, or a tuple of one of those
    (given on the command line comma-separated: ``--set S=1,2,4``). ``quick`` is the
    value under ``--quick`` (None: same as ``default``).
    """

    name: str
    default: Any
    help: str
    quick: Any = None

    def value(self, quick: bool) -> Any:
        return self.default if (not quick or self.quick is None) else self.quick

    def parse(self, text: str) -> Any:
        """The value of ``--set NAME=text``, converted to this setting's type."""
        proto = self.default
        if isinstance(proto, tuple):
            kind = type(proto[0]) if proto else str
            return tuple(_convert(self.name, part.strip(), kind)
                         for part in text.split(",") if part.strip())
        return _convert(self.name, text, type(proto))


def _convert(name: str, text: str, kind: type) -> Any:
    try:
        if kind is bool:
            if text.lower() in ("1", "true", "yes", "on"):
                return True
            if text.lower() in ("0", "false", "no", "off"):
                return False
            raise ValueError(text)
        return kind(text)
    except ValueError:
        raise ConfigError(f"--set {name}={text!r}: expected {kind.__name__}", name) from None


#: Settings every study has.
COMMON_SETTINGS = (
    Setting("seed", 20260, "root of the SeedSequence every task's seed is spawned from"),
    Setting("replicates", 1, "independent repetitions of every point (confidence intervals "
            "need at least 2)"),
)


def parse_set(items: Iterable[str]) -> dict[str, str]:
    """``["KEY=VALUE", ...]`` -> dict; a malformed item raises ConfigError."""
    out: dict[str, str] = {}
    for item in items:
        key, sep, value = item.partition("=")
        if not sep or not key.strip():
            raise ConfigError(f"--set {item!r}: expected KEY=VALUE", "set")
        out[key.strip()] = value.strip()
    return out


# ------------------------------------------------------------------ the study


@dataclass(frozen=True)
class RunOptions:
    """What the user chose: ``--quick`` and the ``--set`` values (already typed)."""

    quick: bool = False
    values: Mapping[str, Any] = field(default_factory=dict)

    def __getitem__(self, name: str) -> Any:
        return self.values[name]

    @property
    def seed(self) -> int:
        return int(self.values["seed"])

    @property
    def replicates(self) -> int:
        return int(self.values["replicates"])


@dataclass(frozen=True)
class Study:
    """A declared study (see the module docstring for the contract of each callable).

    ``machine_columns`` names the measured columns that describe the machine (wall time,
    memory): they differ between runs; every other column is a function of the
    parameters and seeds alone. ``version`` is part of every task key: bump it when the
    task's meaning changes so old cached results are not reused.
    """

    name: str
    description: str
    grid: Callable[[RunOptions], list[Params]]
    task: Callable[[Params, np.random.SeedSequence], Mapping[str, Any]] | None
    reduce: Callable[[Table, RunContext], Mapping[str, Headline]] | None = None
    settings: tuple[Setting, ...] = ()
    machine_columns: tuple[str, ...] = ()
    version: str = "1"

    def all_settings(self) -> dict[str, Setting]:
        out = {s.name: s for s in COMMON_SETTINGS}
        out.update({s.name: s for s in self.settings})
        return out

    def options(self, quick: bool = False, overrides: Mapping[str, Any] | None = None
                ) -> RunOptions:
        """Typed options: each setting's (quick) default, then ``overrides``.

        Values in ``overrides`` may be strings (from ``--set``; converted) or typed
        values. An unknown name raises ConfigError listing the known ones.
        """
        known = self.all_settings()
        values = {n: s.value(quick) for n, s in known.items()}
        for key, val in (overrides or {}).items():
            if key not in known:
                raise ConfigError(f"--set {key}: study {self.name!r} has no such setting; "
                                  f"known: {', '.join(sorted(known))}", key)
            values[key] = known[key].parse(val) if isinstance(val, str) else val
        reps = values["replicates"]
        if not isinstance(reps, int) or not 1 <= reps <= 100000:
            raise ConfigError(f"--set replicates={reps!r}: expected 1..100000", "replicates")
        return RunOptions(quick=quick, values=values)


def grid_product(**axes: Sequence[Scalar]) -> list[Params]:
    """Every combination of the axes' values, the first axis varying slowest."""
    points: list[Params] = [{}]
    for name, values in axes.items():
        if len(values) == 0:
            raise ConfigError(f"grid axis {name!r} has no values", name)
        points = [{**p, name: plain(v)} for p in points for v in values]
    return points


def _canonical(params: Mapping[str, Any]) -> str:
    return json.dumps({k: plain(v) for k, v in params.items()}, sort_keys=True,
                      separators=(",", ":"))


def task_seed(root: int, params: Mapping[str, Any], replicate: int) -> np.random.SeedSequence:
    """The SeedSequence of (point, replicate): a child of ``root`` named by the point."""
    h = hashlib.sha256(_canonical(params).encode()).digest()
    words = tuple(int.from_bytes(h[4 * i:4 * i + 4], "little") for i in range(4))
    return np.random.SeedSequence(root, spawn_key=(*words, replicate))


def task_key(study: Study, params: Mapping[str, Any], replicate: int, root: int) -> str:
    """The cache key of one task: SHA-256 of everything its result depends on."""
    ident = json.dumps({"engine": ENGINE_VERSION, "study": study.name, "version": study.version,
                        "params": json.loads(_canonical(params)), "replicate": replicate,
                        "seed": root}, sort_keys=True)
    return hashlib.sha256(ident.encode()).hexdigest()[:32]


# ------------------------------------------------------------------ running


@dataclass(frozen=True)
class TaskFailure:
    """A task that raised: its point, replicate and the error (type: message)."""

    params: Params
    replicate: int
    error: str


@dataclass
class RunResult:
    """What :func:`run_study` produced (the files are in ``out``)."""

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
    executor: _Executor
    resume: bool
    progress: bool
    subs: dict[str, RunResult] = field(default_factory=dict)

    def run_sub(self, study: Study, overrides: Mapping[str, Any] | None = None) -> RunResult:
        """Run ``study`` into ``out/<study.name>`` on the same executor, quick and resume.

        ``seed`` and ``replicates`` are inherited unless ``overrides`` sets them.
        """
        inherited = {"seed": self.options.seed}
        inherited.update(overrides or {})
        result = _run(study, self.out / study.name, study.options(self.options.quick, inherited),
                      self.executor, resume=self.resume, progress=self.progress)
        self.subs[study.name] = result
        return result


def _execute_task(task: Callable[[Params, np.random.SeedSequence], Mapping[str, Any]],
                  params: Params, root: int, replicate: int) -> dict[str, Any]:
    """What runs on a worker: one seeded task, its result made JSON-plain."""
    seed = task_seed(root, params, replicate)
    result = task(dict(params), seed)
    return {k: plain(v) for k, v in result.items()}


class _Executor:
    """Runs (key, function, args) jobs and yields (key, result | exception) as they finish."""

    description = ""

    def map_unordered(self, jobs: list[tuple[str, Callable[..., Any], tuple]]
                      ) -> Iterator[tuple[str, Any, BaseException | None]]:
        raise NotImplementedError

    def close(self) -> None:
        pass


class _InProcess(_Executor):
    description = "in-process (no Dask)"

    def map_unordered(self, jobs):  # type: ignore[no-untyped-def]
        for key, fn, args in jobs:
            try:
                yield key, fn(*args), None
            except Exception as exc:
                yield key, None, exc


def _probe_scheduler(address: str, timeout_s: float) -> None:
    """Fail in at most ``timeout_s`` with one line when a tcp/tls scheduler cannot be reached.

    Dask retries a refused or silent address for its whole connect timeout and then logs
    many lines; one TCP connection attempt answers the common case (a wrong host or port).
    """
    scheme, _, where = address.partition("://")
    if scheme not in ("tcp", "tls"):
        return
    host, _, port = where.rpartition(":")
    if not host or not port.isdigit() or not 1 <= int(port) <= 65535:
        raise ConfigError(f"--scheduler {address!r}: expected {scheme}://HOST:PORT with a "
                          "port from 1 to 65535", "scheduler")
    try:
        with socket.create_connection((host.strip("[]"), int(port)), timeout=timeout_s) as sock:
            if scheme == "tcp":  # a Dask server speaks first: an 8-byte little-endian length
                head = sock.recv(8, socket.MSG_WAITALL)
                if len(head) < 8 or int.from_bytes(head, "little") > 1 << 30:
                    raise LinkError(f"--scheduler {address!r}: the server there is not a Dask "
                                    "scheduler; check the address")
    except OSError as exc:
        if isinstance(exc, LinkError):
            raise
        raise LinkError(f"--scheduler {address!r}: cannot reach the Dask scheduler "
                        f"({exc.strerror or 'no answer in ' + format(timeout_s, 'g') + ' s'}); "
                        "check the address and that the scheduler runs") from None


class _Dask(_Executor):
    """A dask.distributed Client on a LocalCluster or an existing scheduler."""

    def __init__(self, workers: int | None, scheduler: str | None,
                 security: Any = None, processes: bool = True,
                 connect_timeout_s: float = 10.0) -> None:
        try:
            # optional dependency (extra "study"): only sweeps on Dask need it
            from distributed import Client, LocalCluster
        except ImportError:
            raise ConfigError("running a study on Dask needs dask.distributed: install "
                              "'cdma-lidar[study]' (or use --workers 0 to run in this process)",
                              "workers") from None
        if not log.isEnabledFor(logging.DEBUG):  # Dask logs every scheduler event at INFO
            logging.getLogger("distributed").setLevel(logging.WARNING)
        self._cluster = None
        if scheduler is not None:
            if not _SCHEDULER_RE.match(scheduler):
                raise ConfigError(f"--scheduler {scheduler!r}: expected tcp://HOST:PORT or "
                                  "tls://HOST:PORT", "scheduler")
            _probe_scheduler(scheduler, min(connect_timeout_s, 3.0))
            try:
                self.client = Client(scheduler, timeout=f"{connect_timeout_s}s", security=security,
                                     set_as_default=False)
            except (OSError, TimeoutError, ValueError) as exc:
                raise LinkError(f"--scheduler {scheduler!r}: cannot reach the Dask scheduler "
                                f"({type(exc).__name__}: {str(exc).splitlines()[0][:120]})"
                                ) from None
            self.description = f"dask scheduler {scheduler}"
        else:
            n = workers if workers is not None else (os.cpu_count() or 1)
            # no dashboard; the scheduler's small HTTP server (health, metrics) on a free
            # loopback port rather than 8787, which another cluster may hold
            self._cluster = LocalCluster(n_workers=n, threads_per_worker=1, processes=processes,
                                         host="127.0.0.1" if processes else None,
                                         dashboard_address="127.0.0.1:0",
                                         scheduler_kwargs={"dashboard": False},
                                         silence_logs=logging.ERROR)
            self.client = Client(self._cluster, set_as_default=False)
            self.description = (f"dask LocalCluster, {n} worker "
                                f"{'processes' if processes else 'threads'}")

    def map_unordered(self, jobs):  # type: ignore[no-untyped-def]
        # optional dependency (extra "study"), present once __init__ succeeded
        from distributed import as_completed
        if not jobs:
            return
        futures = {}
        for key, fn, args in jobs:
            fut = self.client.submit(fn, *args, key=f"study-{key}", pure=False)
            futures[fut] = key
        try:
            for fut in as_completed(list(futures), loop=self.client.loop):
                key = futures[fut]
                try:
                    yield key, fut.result(), None
                except Exception as exc:
                    yield key, None, exc
                finally:
                    fut.release()
        finally:
            for fut in futures:
                if not fut.done():
                    fut.cancel()

    def close(self) -> None:
        self.client.close()
        if self._cluster is not None:
            self._cluster.close()


def make_executor(workers: int | None = None, scheduler: str | None = None, *,
                  security: Any = None, processes: bool = True,
                  connect_timeout_s: float = 10.0) -> _Executor:
    """``workers=0``: in this process; otherwise Dask (local cluster or ``scheduler``)."""
    if workers is not None and scheduler is not None:
        raise ConfigError("give --workers or --scheduler, not both", "workers")
    if workers is not None and not (isinstance(workers, int) and 0 <= workers <= 4096):
        raise ConfigError(f"--workers {workers!r}: expected 0..4096 (0: in this process)",
                          "workers")
    if workers == 0:
        return _InProcess()
    return _Dask(workers, scheduler, security=security, processes=processes,
                 connect_timeout_s=connect_timeout_s)


def run_study(study: Study, out: str | os.PathLike[str], *, quick: bool = False,
              overrides: Mapping[str, Any] | None = None, workers: int | None = None,
              scheduler: str | None = None, resume: bool = False, progress: bool = True,
              security: Any = None, processes: bool = True,
              connect_timeout_s: float = 10.0) -> RunResult:
    """Run ``study`` into folder ``out`` and write its table, summary and figures.

    ``workers``: 0 runs in this process without Dask, N > 0 a local Dask cluster of N
    single-threaded worker processes (threads if ``processes`` is False), None one per
    CPU; ``scheduler`` sends the tasks to an existing Dask cluster instead (``security``:
    a ``distributed.security.Security`` for ``tls://``; default from Dask's configuration),
    giving up after ``connect_timeout_s``.
    """
    options = study.options(quick, overrides)
    _check_grid(study, study.grid(options))  # a bad grid fails before any cluster starts
    out_dir = Path(out)
    executor = make_executor(workers, scheduler, security=security, processes=processes,
                             connect_timeout_s=connect_timeout_s)
    try:
        return _run(study, out_dir, options, executor, resume=resume, progress=progress)
    finally:
        executor.close()


def _prepare_out(out: Path, resume: bool) -> Path:
    if out.exists() and not out.is_dir():
        raise ConfigError(f"--out {str(out)!r} is a file; give a folder", "out")
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise ConfigError(f"--out {str(out)!r}: cannot create the folder ({exc.strerror})",
                          "out") from None
    tasks = out / "tasks"
    if tasks.exists() and not resume:
        shutil.rmtree(tasks)
    tasks.mkdir(exist_ok=True)
    return tasks


def _load_cached(path: Path, params: Params, replicate: int) -> dict[str, Any] | None:
    try:
        stored = json.loads(path.read_text())
    except (OSError, ValueError):
        return None
    if stored.get("params") != json.loads(_canonical(params)) or \
            stored.get("replicate") != replicate:
        return None
    return stored.get("result")


def _run(study: Study, out: Path, options: RunOptions, executor: _Executor, *,
         resume: bool, progress: bool) -> RunResult:
    t0 = time.monotonic()
    points = study.grid(options)
    _check_grid(study, points)
    tasks_dir = _prepare_out(out, resume)
    root, reps = options.seed, options.replicates

    jobs = []
    results: dict[str, dict[str, Any]] = {}
    order: list[tuple[str, Params, int]] = []
    cached = 0
    if study.task is not None:
        for p in points:
            for r in range(reps):
                key = task_key(study, p, r, root)
                order.append((key, p, r))
                hit = _load_cached(tasks_dir / f"{key}.json", p, r) if resume else None
                if hit is not None:
                    results[key] = hit
                    cached += 1
                else:
                    jobs.append((key, _execute_task, (study.task, p, root, r)))
    log.info("study %s: %d points x %d replicates, %d cached, %d to run on %s", study.name,
             len(points), reps, cached, len(jobs), executor.description)

    failures: list[TaskFailure] = []
    by_key = {k: (p, r) for k, p, r in order}
    bar = _progress(len(jobs), study.name, progress)
    try:
        for key, result, exc in executor.map_unordered(jobs):
            p, r = by_key[key]
            if exc is not None:
                msg = f"{type(exc).__name__}: {exc}".splitlines()[0]
                failures.append(TaskFailure(p, r, msg))
                log.warning("study %s: task %s replicate %d failed: %s", study.name,
                            _canonical(p), r, msg)
            else:
                results[key] = result
                atomic_write_text(tasks_dir / f"{key}.json", json.dumps(
                    {"study": study.name, "params": p, "replicate": r, "seed": root,
                     "result": result}))  # not sorted: the result's order is the columns'
            if bar is not None:
                bar.update(1)
                if failures:
                    bar.set_postfix(failed=len(failures))
    finally:
        if bar is not None:
            bar.close()

    rep_table = Table([*points[0], "replicate"] if points else [])
    for key, p, r in order:
        if key in results:
            rep_table.append({**p, "replicate": r, **results[key]})
    table = _aggregate(points, rep_table, reps, study.machine_columns)
    ctx = RunContext(study, out, options, executor, resume, progress)
    # A reducer needs measured columns: when every task failed there are none, and the
    # run reports its failures (exit 1) with an empty summary instead of a reducer's crash.
    if study.reduce is None or (points and not results):
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
        "tasks": len(order), "computed": len(jobs) - len(failures), "cached": cached,
        "failed": len(failures), "wall_time_s": round(time.monotonic() - t0, 3),
        "machine_columns": list(study.machine_columns),
        "sub_studies": sorted(ctx.subs),
    }
    atomic_write_text(out / "run.json", json.dumps(info, indent=2) + "\n")
    return RunResult(study.name, out, table, rep_table, summary, failures,
                     computed=len(jobs) - len(failures), cached=cached, subs=ctx.subs)


def _check_grid(study: Study, points: list[Params]) -> None:
    if study.task is not None and not points:
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
        c = _canonical(p)
        if c in seen:
            raise ConfigError(f"study {study.name!r}: the grid has the point {c} twice", "grid")
        seen.add(c)


def _aggregate(points: list[Params], reps: Table, n_reps: int,
               machine: Sequence[str] = ()) -> Table:
    """One row per point: numeric columns averaged over replicates, with 95 % CIs.

    A machine column (time, memory) also gets ``<col>_best``, its minimum over the
    replicates: the figure least disturbed by other load on the machine.
    """
    names = list(points[0]) if points else []
    measured = [c for c in reps.columns if c not in names and c != "replicate"]
    groups: dict[str, list[dict[str, Any]]] = {_canonical(p): [] for p in points}
    for row in reps.rows:
        groups[_canonical({k: row[k] for k in names})].append(row)
    table = Table([*names, "replicates"])
    for p in points:
        rows = groups[_canonical(p)]
        out: dict[str, Any] = {**p, "replicates": len(rows)}
        for c in measured:
            vals = [r.get(c) for r in rows]
            num = [v for v in vals if isinstance(v, int | float) and not isinstance(v, bool)]
            if vals and len(num) == len(vals):
                arr = np.asarray(num, dtype=np.float64)
                out[c] = float(np.mean(arr)) if len(arr) > 1 else plain(num[0])
                if n_reps > 1:
                    out[f"{c}_ci95"] = _ci95(arr)
                    if c in machine:
                        out[f"{c}_best"] = float(np.min(arr))
            else:
                distinct = {json.dumps(v) for v in vals}
                out[c] = vals[0] if len(distinct) == 1 else ";".join(sorted(distinct))
        table.append(out)
    return table


def _ci95(values: np.ndarray) -> float | None:
    """Half-width of the 95 % confidence interval of the mean (Student t); None if < 2."""
    finite = values[np.isfinite(values)]
    if len(finite) < 2:
        return None
    sem = float(np.std(finite, ddof=1) / math.sqrt(len(finite)))
    from scipy.special import stdtrit  # deferred: scipy costs 0.3 s at start-up

    return float(stdtrit(len(finite) - 1, 0.975) * sem)


def _progress(total: int, name: str, enabled: bool):  # type: ignore[no-untyped-def]
    if not enabled or total == 0:
        return None
    from tqdm import tqdm  # deferred: 60 ms at start-up for a bar only a run shows

    return tqdm(total=total, desc=f"study {name}", unit="task", dynamic_ncols=True)
