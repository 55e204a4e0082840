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

import collections
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
    trials: Trials | None = None

    def __post_init__(self) -> None:
        if self.task is not None and self.trials is not None:
            raise ConfigError(f"study {self.name!r}: give task or trials, not both", "task")

    @property
    def runs_tasks(self) -> bool:
        """Whether the study measures its grid (False: a composite running sub-studies)."""
        return self.task is not None or self.trials is not None

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


# ------------------------------------------------------------------ trials in chunks


@dataclass(frozen=True)
class TrialChunk:
    """Trials ``start .. stop - 1`` of one (point, replicate), in blocks with their own seeds.

    Block b holds trials ``b*block .. (b+1)*block - 1`` and draws from
    :func:`block_seed` ``(seed, b)``; chunks start on a block boundary, so any chunking
    of a point's trials draws the same random numbers for every trial.
    """

    seed: np.random.SeedSequence
    start: int
    stop: int
    block: int

    def __len__(self) -> int:
        return self.stop - self.start

    def blocks(self) -> Iterator[tuple[np.random.Generator, int]]:
        """(generator, trials in the block) for each block of the chunk, in trial order."""
        for b in range(self.start // self.block, -(-self.stop // self.block)):
            count = min(self.block, self.stop - b * self.block)
            yield np.random.default_rng(block_seed(self.seed, b)), count


def block_seed(seed: np.random.SeedSequence, block: int) -> np.random.SeedSequence:
    """The SeedSequence of trial block ``block`` of the (point, replicate) ``seed``."""
    return np.random.SeedSequence(seed.entropy, spawn_key=(*seed.spawn_key, block))


@dataclass(frozen=True)
class Trials:
    """A task made of independent random trials, which the engine runs in chunks.

    * ``count(params) -> int``: trials of one (point, replicate) (0: ``summarise`` alone);
    * ``run(params, chunk: TrialChunk) -> {column: sequence}``: one value per trial of
      the chunk in each column (JSON scalars), every random number drawn from
      ``chunk.blocks()``;
    * ``summarise(params, columns) -> row``: the point's measured columns from ALL its
      trials (``columns``: numpy arrays in trial order, chunks concatenated), so counts,
      means and percentiles are exact whatever the chunking.

    ``block``: trials per seed (the unit of chunking; changing it changes the draws).

    ``stop`` (optional): a sequential stopping rule. ``stop(params, columns) -> bool`` is
    asked at fixed looks, after the first ``first_look`` trials and each doubling of that
    (``first_look``, 2 ``first_look``, 4 ``first_look``, ... below ``count``), with the
    columns of exactly those first trials; True ends the point there (``summarise`` then
    gets those trials only). The looks depend on nothing but ``count``, so a stopped
    point's trials, and the table, still do not depend on chunking, workers or order.
    """

    count: Callable[[Params], int]
    run: Callable[[Params, TrialChunk], Mapping[str, Sequence[Any]]]
    summarise: Callable[[Params, Mapping[str, np.ndarray]], Mapping[str, Any]]
    block: int = 8
    stop: Callable[[Params, Mapping[str, np.ndarray]], bool] | None = None
    first_look: int = 64

    def looks(self, count: int) -> list[int]:
        """Trial counts at which ``stop`` is asked, then ``count`` itself (the last)."""
        out = []
        look = -(-max(self.first_look, 1) // self.block) * self.block  # whole blocks
        while self.stop is not None and look < count:
            out.append(look)
            look *= 2
        return [*out, count]


#: Chunk durations the engine aims at (s): at most MAX_CHUNK_S (a Ctrl-C loses little,
#: a worker's last chunk ends soon after the others'), at least MIN_CHUNK_S (a chunk's
#: set-up, e.g. preparing a receiver, stays small against its trials).
MAX_CHUNK_S = 2.0
MIN_CHUNK_S = 0.25


@dataclass
class _Unit:
    """One (point, replicate): its finished chunks, the trial ranges still to run, its
    measured seconds per trial. ``total`` is None for a plain (unchunked) task; else the
    trials the point will have (its count, or the look where ``Trials.stop`` ended it),
    ``looks`` the trial counts at which it may stop (the last is the count), ``looks[0]``
    the end of the stretch of trials now open."""

    params: Params
    replicate: int
    total: int | None
    block: int = 1
    done: dict[int, tuple[int, dict[str, Any]]] = field(default_factory=dict)
    todo: list[tuple[int, int]] = field(default_factory=list)
    rate: float | None = None
    inflight: int = 0
    failed: bool = False
    looks: list[int] = field(default_factory=list)

    def missing(self) -> int:
        """Trials of the open stretch not yet handed out."""
        return sum(b - a for a, b in self.todo)

    def left(self) -> int:
        """Trials still to run up to the point's count (if it never stops)."""
        end = self.looks[-1] if self.looks else 0
        return end - sum(min(b, end) - a for a, (b, _) in self.done.items() if a < end)

    def columns(self, stop: int) -> dict[str, np.ndarray]:
        """Trials 0..stop-1 of the finished chunks, one array per column (trial order)."""
        parts = [(a, *self.done[a]) for a in sorted(self.done) if a < stop or a == 0]
        names = list(parts[0][2]) if parts else []
        if any(list(c) != names for _, _, c in parts):
            raise ValueError("the chunks of this point returned different trial columns")
        return {k: np.asarray([v for a, b, c in parts for v in c[k][:max(0, stop - a)]])
                for k in names}

    def advance(self, trials: Trials) -> int:
        """Past a finished look: stop there (``trials.stop``) or open the next stretch.

        Returns the trials the point will not run because it stopped (0 otherwise).
        """
        skipped = 0
        while self.looks and not self.todo and not self.inflight and not self.failed \
                and len(self.looks) > 1:
            look = self.looks[0]
            assert trials.stop is not None  # more than one look: there is a rule
            if trials.stop(dict(self.params), self.columns(look)):
                skipped = self.looks[-1] - look
                self.total, self.looks = look, [look]
                break
            self.looks.pop(0)
            self.todo = _uncovered(self.looks[0], [(a, b) for a, (b, _) in self.done.items()],
                                   self.block)
        return skipped

    def take(self, blocks: int) -> tuple[int, int]:
        """The next ``blocks`` blocks (at most the first missing range) as (start, stop)."""
        a, b = self.todo[0]
        stop = min(b, a + blocks * self.block)
        if stop < b:
            self.todo[0] = (stop, b)
        else:
            self.todo.pop(0)
        self.inflight += 1
        return a, stop


def _uncovered(total: int, chunks: Iterable[tuple[int, int]], block: int) -> list[tuple[int, int]]:
    """Block-aligned ranges of 0..total not covered by the given (start, stop) chunks."""
    covered = sorted(chunks)
    gaps, pos = [], 0
    for a, b in covered:
        if a > pos:
            gaps.append((pos, a))
        pos = max(pos, b)
    if pos < total:
        gaps.append((pos, total))
    return gaps if total else ([] if covered else [(0, 0)])


def _next_job(units: list[_Unit], slots: int, chunk_trials: int | None = None
              ) -> tuple[_Unit, int | None, int | None] | None:
    """The next chunk to run, or None when nothing should start now.

    Plain tasks and one-block probes of unmeasured points first (grid order), then the
    point with the most estimated time left, in a chunk of about a 1/(2 slots) share of
    all the time left, between MIN_CHUNK_S and MAX_CHUNK_S (guided self-scheduling).
    ``chunk_trials``: chunks of that many trials (whole blocks) instead, in grid order.
    """
    live = [u for u in units if u.todo and not u.failed]
    for u in live:
        if u.total is None:
            u.todo.clear()
            u.inflight += 1
            return u, None, None
        if chunk_trials is not None:
            return (u, *u.take(-(-chunk_trials // u.block)))
        if u.rate is None and u.inflight == 0:
            return (u, *u.take(1))
    known = [u.rate for u in units if u.rate is not None]
    if not live or not known:
        return None  # wait for a probe
    slow = max(known)

    def left(u: _Unit) -> float:
        return u.missing() * (slow if u.rate is None else u.rate)

    target = min(MAX_CHUNK_S, max(MIN_CHUNK_S, sum(map(left, live)) / (2 * slots)))
    u = max(live, key=left)
    rate = slow if u.rate is None else u.rate
    blocks = max(1, int(target / (rate * u.block))) if rate > 0 else u.missing()
    return (u, *u.take(blocks))


# ------------------------------------------------------------------ running


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
    executor: _Executor
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


def _execute_task(task: Callable[[Params, np.random.SeedSequence], Mapping[str, Any]],
                  params: Params, root: int, replicate: int
                  ) -> tuple[dict[str, Any], float, float]:
    """What runs on a worker: one seeded task, its result made JSON-plain, and its
    seconds (:func:`_clocks`)."""
    c0 = _clocks()
    result = task(dict(params), task_seed(root, params, replicate))
    return ({k: plain(v) for k, v in result.items()},
            *(b - a for a, b in zip(c0, _clocks(), strict=True)))


def _execute_chunk(trials: Trials, params: Params, root: int, replicate: int, start: int,
                   stop: int) -> tuple[dict[str, list[Any]], float, float]:
    """What runs on a worker: trials start..stop-1 of (point, replicate), one list per
    column, and the seconds they took (:func:`_clocks`)."""
    c0 = _clocks()
    chunk = TrialChunk(task_seed(root, params, replicate), start, stop, trials.block)
    columns = {k: [plain(v) for v in np.asarray(vals).tolist()]
               for k, vals in trials.run(dict(params), chunk).items()}
    bad = [k for k, v in columns.items() if len(v) != stop - start]
    if bad:
        raise ValueError(f"trial columns {bad} do not have one value per trial "
                         f"({stop - start})")
    return columns, *(b - a for a, b in zip(c0, _clocks(), strict=True))


def _clocks() -> tuple[float, float, float]:
    """(wall, CPU of this process, runqueue wait of this thread) in seconds.

    The wait is the time this thread was ready to run but another process held the
    core (Linux ``/proc/thread-self/schedstat``; 0 elsewhere): on a shared machine it
    tells the other load's share of a task's wall time from the task's own.
    """
    try:
        with open("/proc/thread-self/schedstat") as f:
            wait = int(f.read().split()[1]) * 1e-9
    except (OSError, ValueError, IndexError):
        wait = 0.0
    return time.perf_counter(), time.process_time(), wait


class _Executor:
    """Runs submitted (key, function, args) jobs; :meth:`completed` yields (key, result |
    None, exception | None) as they finish, including jobs submitted while it iterates."""

    description = ""
    #: jobs that run at once
    slots = 1

    def submit(self, key: str, fn: Callable[..., Any], args: tuple) -> None:
        raise NotImplementedError

    def completed(self) -> Iterator[tuple[str, Any, BaseException | None]]:
        raise NotImplementedError

    def close(self) -> None:
        pass


class _InProcess(_Executor):
    description = "in-process (no Dask)"

    def __init__(self) -> None:
        self._queue: collections.deque[tuple[str, Callable[..., Any], tuple]] = \
            collections.deque()

    def submit(self, key, fn, args):  # type: ignore[no-untyped-def]
        self._queue.append((key, fn, args))

    def completed(self):  # type: ignore[no-untyped-def]
        while self._queue:
            key, fn, args = self._queue.popleft()
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


#: Environment of local worker processes: one single-threaded worker per core, so the
#: receive chain runs one thread in each (Dask already sets the BLAS libraries to one).
WORKER_ENV = {"CDMA_LIDAR_THREADS": "1"}


class _Dask(_Executor):
    """A dask.distributed Client on a LocalCluster or an existing scheduler.

    ``gpus`` > 0: a local cluster of that many single-threaded workers, worker i seeing
    only GPU i (``CUDA_VISIBLE_DEVICES``), so the receive chain's ``method="auto"`` finds
    one device per worker (one worker per GPU).
    """

    def __init__(self, workers: int | None, scheduler: str | None,
                 security: Any = None, processes: bool = True,
                 connect_timeout_s: float = 10.0, gpus: int = 0) -> None:
        try:
            # optional dependency (extra "study"): only sweeps on Dask need it
            from distributed import Client, LocalCluster, as_completed
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
            self.slots = max(1, sum(self.client.nthreads().values()))
        else:
            n = gpus or (workers if workers is not None else (os.cpu_count() or 1))
            # no dashboard; the scheduler's small HTTP server (health, metrics) on a free
            # loopback port rather than 8787, which another cluster may hold
            if gpus:  # one worker process per device, each seeing only its own
                self._cluster = _gpu_cluster(gpus)
            else:
                self._cluster = LocalCluster(n_workers=n, threads_per_worker=1,
                                             processes=processes,
                                             host="127.0.0.1" if processes else None,
                                             dashboard_address="127.0.0.1:0",
                                             scheduler_kwargs={"dashboard": False},
                                             silence_logs=logging.ERROR,
                                             **({"env": WORKER_ENV} if processes else {}))
            self.client = Client(self._cluster, set_as_default=False)
            if gpus:
                self.client.wait_for_workers(gpus, timeout=60)
            self.slots = n
            self.description = (f"dask LocalCluster, {n} worker "
                                f"{'processes' if processes else 'threads'}"
                                + (", one per GPU" if gpus else ""))
        self._done = as_completed(loop=self.client.loop)
        self._keys: dict[Any, str] = {}

    def submit(self, key, fn, args):  # type: ignore[no-untyped-def]
        fut = self.client.submit(fn, *args, key=f"study-{key}", pure=False)
        self._keys[fut] = key
        self._done.add(fut)

    def completed(self):  # type: ignore[no-untyped-def]
        try:
            for fut in self._done:
                key = self._keys.pop(fut)
                try:
                    yield key, fut.result(), None
                except Exception as exc:
                    yield key, None, exc
                finally:
                    fut.release()
        finally:
            for fut in list(self._keys):
                if not fut.done():
                    fut.cancel()
            self._keys.clear()
            self._done.clear()

    def close(self) -> None:
        self.client.close()
        if self._cluster is not None:
            self._cluster.close()


def _gpu_cluster(gpus: int) -> Any:
    """A local Dask cluster of ``gpus`` single-threaded worker processes, worker i with
    ``CUDA_VISIBLE_DEVICES=i``."""
    from distributed import Nanny, Scheduler, SpecCluster  # optional dependency, as above
    workers = {f"gpu-{i}": {"cls": Nanny, "options": {
        "nthreads": 1, "host": "127.0.0.1", "silence_logs": logging.ERROR,
        "env": {**WORKER_ENV, "CUDA_VISIBLE_DEVICES": str(i)}}} for i in range(gpus)}
    scheduler = {"cls": Scheduler, "options": {"host": "127.0.0.1", "dashboard": False,
                                               "dashboard_address": "127.0.0.1:0"}}
    return SpecCluster(workers=workers, scheduler=scheduler, silence_logs=logging.ERROR)


class _Lazy(_Executor):
    """Starts its executor (a Dask cluster, say) only when the first job is submitted:
    a resumed run with nothing missing starts nothing."""

    def __init__(self, factory: Callable[[], _Executor]) -> None:
        self._factory = factory
        self._real: _Executor | None = None
        #: seconds it took to start (0 until started)
        self.start_s = 0.0

    def _get(self) -> _Executor:
        if self._real is None:
            t0 = time.monotonic()
            self._real = self._factory()
            self.start_s = time.monotonic() - t0
        return self._real

    @property
    def description(self) -> str:  # type: ignore[override]
        return self._real.description if self._real is not None else "none (nothing to run)"

    @property
    def slots(self) -> int:  # type: ignore[override]
        return self._get().slots

    def submit(self, key, fn, args):  # type: ignore[no-untyped-def]
        self._get().submit(key, fn, args)

    def completed(self):  # type: ignore[no-untyped-def]
        return iter(()) if self._real is None else self._real.completed()

    def close(self) -> None:
        if self._real is not None:
            self._real.close()


def _check_executor(workers: int | None, scheduler: str | None, gpus: int = 0) -> None:
    if workers is not None and scheduler is not None:
        raise ConfigError("give --workers or --scheduler, not both", "workers")
    if workers is not None and not (isinstance(workers, int) and 0 <= workers <= 4096):
        raise ConfigError(f"--workers {workers!r}: expected 0..4096 (0: in this process)",
                          "workers")
    if not (isinstance(gpus, int) and 0 <= gpus <= 1024):
        raise ConfigError(f"--gpus {gpus!r}: expected 0..1024", "gpus")
    if gpus and (scheduler is not None or workers is not None):
        raise ConfigError("--gpus starts one local worker per GPU: give it without "
                          "--workers and --scheduler", "gpus")
    if scheduler is not None and not _SCHEDULER_RE.match(scheduler):
        raise ConfigError(f"--scheduler {scheduler!r}: expected tcp://HOST:PORT or "
                          "tls://HOST:PORT", "scheduler")


def make_executor(workers: int | None = None, scheduler: str | None = None, *,
                  security: Any = None, processes: bool = True,
                  connect_timeout_s: float = 10.0, gpus: int = 0) -> _Executor:
    """``workers=0``: in this process; otherwise Dask (local cluster or ``scheduler``);
    ``gpus`` > 0: a local cluster of one worker per GPU."""
    _check_executor(workers, scheduler, gpus)
    if workers == 0:
        return _InProcess()
    return _Dask(workers, scheduler, security=security, processes=processes,
                 connect_timeout_s=connect_timeout_s, gpus=gpus)


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
    _check_executor(workers, scheduler, gpus)
    if chunk_trials is not None and not (isinstance(chunk_trials, int) and chunk_trials >= 1):
        raise ConfigError(f"chunk_trials {chunk_trials!r}: expected an integer >= 1 (None: "
                          "follow the machine)", "chunk_trials")
    out_dir = Path(out)
    executor = _Lazy(lambda: make_executor(workers, scheduler, security=security,
                                           processes=processes,
                                           connect_timeout_s=connect_timeout_s, gpus=gpus))
    try:
        return _run(study, out_dir, options, executor, resume=resume, progress=progress,
                    chunk_trials=chunk_trials)
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


def _load_chunks(tasks_dir: Path, study: Study, root: int
                 ) -> dict[tuple[str, int], list[tuple[int, int, dict[str, list[Any]]]]]:
    """Finished chunks of trials in ``tasks_dir`` of this study, version and root seed,
    by (canonical point, replicate); unreadable or foreign files are skipped."""
    found: dict[tuple[str, int], list[tuple[int, int, dict[str, list[Any]]]]] = {}
    for path in sorted(tasks_dir.glob("*.json")):
        try:
            doc = json.loads(path.read_text())
            if (doc.get("engine"), doc.get("study"), doc.get("version"), doc.get("seed")) \
                    != (ENGINE_VERSION, study.name, study.version, root):
                continue
            a, b = (int(v) for v in doc["trials"])
            cols = doc["columns"]
            if not (0 <= a <= b and isinstance(cols, dict)
                    and all(isinstance(v, list) and len(v) == b - a for v in cols.values())):
                continue
            found.setdefault((_canonical(doc["params"]), int(doc["replicate"])), []).append(
                (a, b, cols))
        except (OSError, ValueError, KeyError, TypeError):
            continue
    return found


def _chunk_key(study: Study, params: Params, replicate: int, root: int, start: int,
               stop: int) -> str:
    return task_key(study, {**params, "__trials__": f"{start}:{stop}"}, replicate, root)


def _units(study: Study, points: list[Params], reps: int, root: int, tasks_dir: Path,
           resume: bool) -> tuple[list[_Unit], int]:
    """Every (point, replicate) with what is cached and what is left; and the cached count."""
    units: list[_Unit] = []
    cached = 0
    chunks = _load_chunks(tasks_dir, study, root) if resume and study.trials else {}
    for p in points:
        for r in range(reps):
            if study.trials is None:
                u = _Unit(p, r, None)
                hit = _load_cached(tasks_dir / f"{task_key(study, p, r, root)}.json", p, r) \
                    if resume else None
                if hit is None:
                    u.todo.append((0, 1))
                else:
                    u.done[0] = (1, hit)
                    cached += 1
            else:
                total = int(study.trials.count(p))
                if total < 0:
                    raise ConfigError(f"study {study.name!r}: {total} trials at "
                                      f"{_canonical(p)}", "trials")
                u = _Unit(p, r, total, block=study.trials.block)
                pos = 0
                block = study.trials.block
                for a, b, cols in sorted(chunks.get((_canonical(p), r), []),
                                         key=lambda c: (c[0], -c[1])):
                    aligned = a % block == 0 and (b % block == 0 or b == total)
                    if a >= pos and b <= total and aligned and (b > a or total == 0):
                        u.done[a] = (b, cols)
                        pos = b
                        cached += 1
                u.looks = study.trials.looks(total)
                u.todo = _uncovered(u.looks[0], [(a, b) for a, (b, _) in u.done.items()],
                                    block)
                u.advance(study.trials)
            units.append(u)
    return units, cached


def _finish(study: Study, u: _Unit) -> dict[str, Any]:
    """The row of a unit whose chunks are all done (raises what the study raises)."""
    if study.trials is None:
        return u.done[0][1]
    columns = u.columns(u.total or 0)
    return {k: plain(v) for k, v in study.trials.summarise(dict(u.params), columns).items()}


def _run(study: Study, out: Path, options: RunOptions, executor: _Executor, *,
         resume: bool, progress: bool, chunk_trials: int | None = None) -> RunResult:
    t0 = time.monotonic()
    points = study.grid(options)
    _check_grid(study, points)
    tasks_dir = _prepare_out(out, resume)
    root, reps = options.seed, options.replicates
    units, cached = _units(study, points, reps, root, tasks_dir, resume) \
        if study.runs_tasks else ([], 0)
    log.info("study %s: %d points x %d replicates, %d tasks cached", study.name,
             len(points), reps, cached)

    failures: list[TaskFailure] = []
    rows: dict[int, dict[str, Any]] = {}

    def fail(u: _Unit, exc: BaseException) -> None:
        u.failed = True
        msg = f"{type(exc).__name__}: {exc}".splitlines()[0]
        failures.append(TaskFailure(u.params, u.replicate, msg))
        log.warning("study %s: task %s replicate %d failed: %s", study.name,
                    _canonical(u.params), u.replicate, msg)

    def complete(i: int, u: _Unit) -> None:
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
    jobs: dict[str, tuple[_Unit, int, int]] = {}
    try:
        if any(u.todo for u in units):
            slots = executor.slots
            inflight = 2 * slots if slots > 1 else 1

            def fill() -> None:
                while len(jobs) < inflight:
                    job = _next_job(units, slots, chunk_trials)
                    if job is None:
                        return
                    u, a, b = job
                    if a is None or b is None:  # a plain task
                        key = task_key(study, u.params, u.replicate, root)
                        jobs[key] = (u, 0, 1)
                        executor.submit(key, _execute_task, (study.task, u.params, root,
                                                             u.replicate))
                    else:
                        key = _chunk_key(study, u.params, u.replicate, root, a, b)
                        jobs[key] = (u, a, b)
                        executor.submit(key, _execute_chunk, (study.trials, u.params, root,
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
                        doc = {"study": study.name, "params": u.params,
                               "replicate": u.replicate, "seed": root, "result": value}
                        name = task_key(study, u.params, u.replicate, root)
                    else:
                        u.rate = seconds / max(1, b - a)
                        doc = {"engine": ENGINE_VERSION, "study": study.name,
                               "version": study.version, "seed": root, "params": u.params,
                               "replicate": u.replicate, "trials": [a, b], "columns": value}
                        name = key
                    # not sorted: the result's order is the columns'
                    atomic_write_text(tasks_dir / f"{name}.json", json.dumps(doc))
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
    table = _aggregate(points, rep_table, reps, study.machine_columns)
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


def _progress(total: int, name: str, enabled: bool,  # type: ignore[no-untyped-def]
              unit: str = "task"):
    if not enabled or total == 0:
        return None
    from tqdm import tqdm  # deferred: 60 ms at start-up for a bar only a run shows

    return tqdm(total=total, desc=f"study {name}", unit=unit, dynamic_ncols=True)
