"""The interval statistics of a study's table: one row per point from its replicates."""

from __future__ import annotations

import json
import math
from collections.abc import Sequence
from typing import Any

import numpy as np

from cdma_lidar.study.model import Params, canonical
from cdma_lidar.study.table import Table, plain

__all__ = ["aggregate", "ci95"]

def aggregate(points: list[Params], reps: Table, n_reps: int,
               machine: Sequence[str] = ()) -> Table:
    """One row per point: numeric columns averaged over replicates, with 95 % CIs.

    A machine column (time, memory) also gets ``<col>_best``, its minimum over the
    replicates: the figure least disturbed by other load on the machine.
    """
    names = list(points[0]) if points else []
    measured = [c for c in reps.columns if c not in names and c != "replicate"]
    groups: dict[str, list[dict[str, Any]]] = {canonical(p): [] for p in points}
    for row in reps.rows:
        groups[canonical({k: row[k] for k in names})].append(row)
    table = Table([*names, "replicates"])
    for p in points:
        rows = groups[canonical(p)]
        out: dict[str, Any] = {**p, "replicates": len(rows)}
        for c in measured:
            vals = [r.get(c) for r in rows]
            num = [v for v in vals if isinstance(v, int | float) and not isinstance(v, bool)]
            if vals and len(num) == len(vals):
                arr = np.asarray(num, dtype=np.float64)
                out[c] = float(np.mean(arr)) if len(arr) > 1 else plain(num[0])
                if n_reps > 1:
                    out[f"{c}_ci95"] = ci95(arr)
                    if c in machine:
                        out[f"{c}_best"] = float(np.min(arr))
            else:
                distinct = {json.dumps(v) for v in vals}
                out[c] = vals[0] if len(distinct) == 1 else ";".join(sorted(distinct))
        table.append(out)
    return table


def ci95(values: np.ndarray) -> float | None:
    """Half-width of the 95 % confidence interval of the mean (Student t); None if < 2."""
    finite = values[np.isfinite(values)]
    if len(finite) < 2:
        return None
    sem = float(np.std(finite, ddof=1) / math.sqrt(len(finite)))
    from scipy.special import stdtrit  # deferred: scipy costs 0.3 s at start-up

    return float(stdtrit(len(finite) - 1, 0.975) * sem)
