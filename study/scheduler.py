"""The chunk scheduler: which (point, replicate) runs next, in how many trials, and
what runs on a worker.

Each (point, replicate) is a :class:`Unit`: its finished chunks, the trial ranges still
to run and its measured seconds per trial. A :class:`~cdma_lidar.study.model.Trials`
point first runs one block (its rate measured); then the point with the most time left
gets a chunk of about 1/(2 x workers) of all the time left, clamped to
:data:`MIN_CHUNK_S`..:data:`MAX_CHUNK_S` (guided self-scheduling), or ``chunk_trials``
trials when given (:func:`next_job`). :func:`execute_task` and :func:`execute_chunk` are
what an executor (:mod:`cdma_lidar.study.executors`) runs.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from cdma_lidar.errors import ConfigError
from cdma_lidar.study.model import Params, Study, TrialChunk, Trials, canonical, task_seed
from cdma_lidar.study.store import load_chunks, load_task
from cdma_lidar.study.table import plain

__all__ = [
    "MAX_CHUNK_S",
    "MIN_CHUNK_S",
    "Unit",
    "execute_chunk",
    "execute_task",
    "next_job",
    "uncovered",
    "units_of",
]

#: Chunk durations the engine aims at (s): at most MAX_CHUNK_S (a Ctrl-C loses little,
#: a worker's last chunk ends soon after the others'), at least MIN_CHUNK_S (a chunk's
#: set-up, e.g. preparing a receiver, stays small against its trials).
MAX_CHUNK_S = 2.0
MIN_CHUNK_S = 0.25


@dataclass
class Unit:
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
            raise RuntimeError("the chunks of this point returned different trial columns")
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
            self.todo = uncovered(self.looks[0], [(a, b) for a, (b, _) in self.done.items()],
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


def uncovered(total: int, chunks: Iterable[tuple[int, int]], block: int) -> list[tuple[int, int]]:
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


def next_job(units: list[Unit], slots: int, chunk_trials: int | None = None
              ) -> tuple[Unit, int | None, int | None] | None:
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

    def left(u: Unit) -> float:
        return u.missing() * (slow if u.rate is None else u.rate)

    target = min(MAX_CHUNK_S, max(MIN_CHUNK_S, sum(map(left, live)) / (2 * slots)))
    u = max(live, key=left)
    rate = slow if u.rate is None else u.rate
    blocks = max(1, int(target / (rate * u.block))) if rate > 0 else u.missing()
    return (u, *u.take(blocks))


def execute_task(task: Callable[[Params, np.random.SeedSequence], Mapping[str, Any]],
                  params: Params, root: int, replicate: int
                  ) -> tuple[dict[str, Any], float, float]:
    """What runs on a worker: one seeded task, its result made JSON-plain, and its
    seconds (:func:`_clocks`)."""
    c0 = _clocks()
    result = task(dict(params), task_seed(root, params, replicate))
    return ({k: plain(v) for k, v in result.items()},
            *(b - a for a, b in zip(c0, _clocks(), strict=True)))


def execute_chunk(trials: Trials, params: Params, root: int, replicate: int, start: int,
                   stop: int) -> tuple[dict[str, list[Any]], float, float]:
    """What runs on a worker: trials start..stop-1 of (point, replicate), one list per
    column, and the seconds they took (:func:`_clocks`)."""
    c0 = _clocks()
    chunk = TrialChunk(task_seed(root, params, replicate), start, stop, trials.block)
    columns = {k: [plain(v) for v in np.asarray(vals).tolist()]
               for k, vals in trials.run(dict(params), chunk).items()}
    bad = [k for k, v in columns.items() if len(v) != stop - start]
    if bad:
        raise RuntimeError(f"trial columns {bad} do not have one value per trial "
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


def units_of(study: Study, points: list[Params], reps: int, root: int, tasks_dir: Path,
           resume: bool) -> tuple[list[Unit], int]:
    """Every (point, replicate) of ``points`` x ``reps`` as a :class:`Unit`, with what the
    store in ``tasks_dir`` holds (when ``resume``) and what is left; and the cached count."""
    units: list[Unit] = []
    cached = 0
    chunks = load_chunks(tasks_dir, study, root) if resume and study.trials else {}
    for p in points:
        for r in range(reps):
            if study.trials is None:
                u = Unit(p, r, None)
                hit = load_task(tasks_dir, study, p, r, root) if resume else None
                if hit is None:
                    u.todo.append((0, 1))
                else:
                    u.done[0] = (1, hit)
                    cached += 1
            else:
                total = int(study.trials.count(p))
                if total < 0:
                    raise ConfigError(f"study {study.name!r}: {total} trials at "
                                      f"{canonical(p)}", "trials")
                u = Unit(p, r, total, block=study.trials.block)
                pos = 0
                block = study.trials.block
                for a, b, cols in sorted(chunks.get((canonical(p), r), []),
                                         key=lambda c: (c[0], -c[1])):
                    aligned = a % block == 0 and (b % block == 0 or b == total)
                    if a >= pos and b <= total and aligned and (b > a or total == 0):
                        u.done[a] = (b, cols)
                        pos = b
                        cached += 1
                u.looks = study.trials.looks(total)
                u.todo = uncovered(u.looks[0], [(a, b) for a, (b, _) in u.done.items()],
                                    block)
                u.advance(study.trials)
            units.append(u)
    return units, cached
