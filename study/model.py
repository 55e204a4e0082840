"""The study model and its seeding: settings, studies, grids, trials and task seeds.

A :class:`Study` declares its settings, its grid, and either a ``task`` (one point,
one replicate) or :class:`Trials` (many independent random trials per point, run in
chunks); :mod:`cdma_lidar.study.engine` states the contract and runs it.

Seeding (results never depend on where or in which order tasks ran): task (point p,
replicate r) gets ``SeedSequence(root_seed, spawn_key=(h0, h1, h2, h3, r))`` where
``h`` are the first 128 bits of the SHA-256 of the point's canonical JSON
(:func:`task_seed`); block b of a :class:`Trials` point draws from
``SeedSequence(root_seed, spawn_key=(h0, h1, h2, h3, r, b))`` (:func:`block_seed`).
"""

from __future__ import annotations

import hashlib
import json
import math
from collections.abc import Callable, Iterable, Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import numpy as np

from cdma_lidar.errors import ConfigError
from cdma_lidar.study.table import Scalar, Table, plain

if TYPE_CHECKING:
    from cdma_lidar.study.engine import RunContext

__all__ = [
    "COMMON_SETTINGS",
    "ENGINE_VERSION",
    "Headline",
    "Params",
    "RunOptions",
    "Setting",
    "Study",
    "TrialChunk",
    "Trials",
    "block_seed",
    "canonical",
    "grid_product",
    "headline",
    "parse_set",
    "task_key",
    "task_seed",
]

#: Part of every task key: bump when the storage format changes.
ENGINE_VERSION = 1

Params = dict[str, Scalar]
Headline = dict[str, Any]


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
        else:
            return kind(text)
    except ValueError:
        pass
    raise ConfigError(f"--set {name}={text!r}: expected {kind.__name__}", name)


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


def canonical(params: Mapping[str, Any]) -> str:
    return json.dumps({k: plain(v) for k, v in params.items()}, sort_keys=True,
                      separators=(",", ":"))


def task_seed(root: int, params: Mapping[str, Any], replicate: int) -> np.random.SeedSequence:
    """The SeedSequence of (point, replicate): a child of ``root`` named by the point."""
    h = hashlib.sha256(canonical(params).encode()).digest()
    words = tuple(int.from_bytes(h[4 * i:4 * i + 4], "little") for i in range(4))
    return np.random.SeedSequence(root, spawn_key=(*words, replicate))


def task_key(study: Study, params: Mapping[str, Any], replicate: int, root: int) -> str:
    """The cache key of one task: SHA-256 of everything its result depends on."""
    ident = json.dumps({"engine": ENGINE_VERSION, "study": study.name, "version": study.version,
                        "params": json.loads(canonical(params)), "replicate": replicate,
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
