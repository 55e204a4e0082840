"""The resume store: one JSON file per finished task or chunk of trials in ``DIR/tasks``.

A plain task's file holds its params, replicate, root seed and result, named by
:func:`~cdma_lidar.study.model.task_key`; a chunk of trials holds the engine and study
versions, the root seed, params, replicate, its trials ``[start, stop)`` and one list
per column, named by :func:`chunk_key`. Files are written atomically as soon as a job
returns; unreadable or foreign files are skipped when loading.
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path
from typing import Any

from cdma_lidar.errors import ConfigError
from cdma_lidar.fileio import atomic_write_text
from cdma_lidar.study.model import ENGINE_VERSION, Params, Study, canonical, task_key

__all__ = ["chunk_key", "load_chunks", "load_task", "prepare_out", "save_chunk", "save_task"]


def prepare_out(out: Path, resume: bool) -> Path:
    """Create ``out`` and its ``tasks`` folder (emptied unless ``resume``); return the latter."""
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


def load_task(tasks_dir: Path, study: Study, params: Params, replicate: int, root: int
              ) -> dict[str, Any] | None:
    """The stored result of a plain task, or None when there is none (or it is not this one)."""
    path = tasks_dir / f"{task_key(study, params, replicate, root)}.json"
    try:
        stored = json.loads(path.read_text())
    except (OSError, ValueError):
        return None
    if stored.get("params") != json.loads(canonical(params)) or \
            stored.get("replicate") != replicate:
        return None
    return stored.get("result")


def load_chunks(tasks_dir: Path, study: Study, root: int
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
            found.setdefault((canonical(doc["params"]), int(doc["replicate"])), []).append(
                (a, b, cols))
        except (OSError, ValueError, KeyError, TypeError):
            continue
    return found


def chunk_key(study: Study, params: Params, replicate: int, root: int, start: int,
              stop: int) -> str:
    """The file name (without .json) of trials ``start..stop-1`` of (point, replicate)."""
    return task_key(study, {**params, "__trials__": f"{start}:{stop}"}, replicate, root)


def save_task(tasks_dir: Path, study: Study, params: Params, replicate: int, root: int,
              result: dict[str, Any]) -> None:
    """Store a finished plain task's result (atomically)."""
    doc = {"study": study.name, "params": params, "replicate": replicate, "seed": root,
           "result": result}
    # not sorted: the result's order is the columns'
    atomic_write_text(tasks_dir / f"{task_key(study, params, replicate, root)}.json",
                      json.dumps(doc))


def save_chunk(tasks_dir: Path, study: Study, params: Params, replicate: int, root: int,
               start: int, stop: int, columns: dict[str, list[Any]]) -> None:
    """Store a finished chunk of trials, one list per column (atomically)."""
    doc = {"engine": ENGINE_VERSION, "study": study.name, "version": study.version,
           "seed": root, "params": params, "replicate": replicate, "trials": [start, stop],
           "columns": columns}
    name = chunk_key(study, params, replicate, root, start, stop)
    atomic_write_text(tasks_dir / f"{name}.json", json.dumps(doc))
