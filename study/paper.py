"""The ``paper`` study: every quantitative result of the paper by one command, with a report.

``cdma-lidar study run paper --out DIR [--quick]`` runs the paper's studies (the
``studies`` setting; by default all of :data:`PAPER_STUDIES`) one after the other with
:meth:`cdma_lidar.study.engine.RunContext.run_sub` -- each on the same executor, with the
same ``--quick``, ``--resume`` and ``seed``, into ``DIR/<name>/`` -- and writes
``DIR/report.md``: per headline the paper's number, ours, the ratio, the figure (a
relative link to the study's PNG; for decibels the difference, since a ratio of
logarithms means nothing), each study's explanatory paragraph (its module's
``REPORT_NOTE``), and how long each study took on which executor.

A study that is not registered in this build (the catalogue has no such name) is
listed as "not available in this build" with its expected headlines, so the report
always has a row for every result of the paper. A study that fails is reported with
its error and the others go on.

``sub_set`` passes settings to the parts: ``--set sub_set=eq42.trials=1000,fig4d.frames=2``
(``NAME.KEY=VALUE`` items, comma-separated; each must name a setting of that study; a
list value continues over the commas: ``sub_set=eq42.degrees=9,11,eq42.pairs=50``).
"""

from __future__ import annotations

import importlib
import json
import logging
import math
from pathlib import Path
from typing import Any

from cdma_lidar.errors import ConfigError
from cdma_lidar.fileio import atomic_write_text
from cdma_lidar.study import catalogue
from cdma_lidar.study.engine import Headline, RunContext, RunResult, Setting, Study, Table, headline

__all__ = ["PAPER_STUDIES", "STUDY", "parse_sub_set", "write_report"]

log = logging.getLogger(__name__)

#: The paper's results: study name -> (where in the paper, what it is, the headline keys).
PAPER_STUDIES: dict[str, tuple[str, str, tuple[str, ...]]] = {
    "fig2c": ("Fig. 2c, eq. 27", "histogram of 1000 repeated single-point ranges; "
              "resolution = 2 sigma", ("resolution_2sigma_m", "precision_eq27_m")),
    "fig2d": ("Fig. 2d, eq. 28", "resolution vs chip rate and sample rate",
              ("resolution_m_at_62_5mhz", "resolution_m_at_200mhz")),
    "fig2e": ("Fig. 2e", "SNR_XC and error rate vs SNR (EDFA gain sweep); threshold at 10 % "
              "error", ("snr_xc_threshold_db", "min_workable_snr_db")),
    "fig2f": ("Fig. 2f", "maximum range vs code length at constant power (95 % band)",
              ("max_range_m_order11", "max_range_m_order13")),
    "fig11": ("Fig. 11, Note 8", "channel capacity at 10 % error, orders 11/13/15, 50 samples "
              "per chip, 1000 random delays",
              ("workable_channels_order11", "workable_channels_order13",
               "workable_channels_order15")),
    "fig17": ("Fig. 17, eqs. 52-53", "UID vs direct-spread candidate counts from a degree-9 "
              "code", tuple(f"candidates_{k}_l{i}" for k in ("uid", "direct")
                            for i in range(1, 5))),
    "eq42": ("Note 9, eq. 42", "asynchronous cross-correlation power N E[r^2] = 2/3",
             ("async_xcorr_power_times_n",)),
    "eq29": ("Note 8, eq. 29", "frame rate at 1 GHz, degree 13, 1000 pixels",
             ("frame_rate_hz",)),
    "fig4b": ("Fig. 4b, Note 11", "four users on one code with 3-bit UIDs",
              ("users_identified", "foreign_ranges_accepted")),
    "fig4d": ("Fig. 4d, Note 12", "near-far heatmaps before and after power control",
              ("object_valid_fraction_before", "object_valid_fraction_after")),
    "table1": ("Table 1, Note 8", "the preferred-pair table, with the errata",
               ("pairs_checked", "pairs_not_preferred")),
}

NOT_AVAILABLE = "not available in this build"


def parse_sub_set(items: tuple[str, ...], names: list[str]) -> dict[str, dict[str, str]]:
    """``("eq42.trials=1000", ...)`` -> ``{"eq42": {"trials": "1000"}}`` (ConfigError if bad)."""
    joined: list[str] = []
    for item in items:  # "eq42.degrees=9,11" arrives split at the comma: "11" continues it
        if "=" not in item and joined:
            joined[-1] += "," + item
        else:
            joined.append(item)
    out: dict[str, dict[str, str]] = {}
    for item in joined:
        key, sep, value = item.partition("=")
        name, dot, setting = key.strip().partition(".")
        if not sep or not dot or not setting:
            raise ConfigError(f"--set sub_set item {item!r}: expected STUDY.KEY=VALUE",
                              "sub_set")
        if name not in names:
            raise ConfigError(f"--set sub_set item {item!r}: {name!r} is not one of the "
                              f"studies run ({', '.join(names)})", "sub_set")
        out.setdefault(name, {})[setting] = value.strip()
    return out


def _grid(options: Any) -> list[dict]:
    names = list(options["studies"])
    for n in names:
        if n not in PAPER_STUDIES:
            raise ConfigError(f"--set studies: {n!r} is not a paper study; known: "
                              f"{', '.join(PAPER_STUDIES)}", "studies")
    parse_sub_set(tuple(options["sub_set"]), names)
    return []


def _note(study: Study) -> str | None:
    """The study module's ``REPORT_NOTE`` (the paragraph explaining differences)."""
    fn = study.grid if study.task is None else study.task
    module = importlib.import_module(fn.__module__)
    note = getattr(module, "REPORT_NOTE", None)
    return note if isinstance(note, str) else None


def _run_json(folder: Path) -> dict[str, Any]:
    try:
        return json.loads((folder / "run.json").read_text())
    except (OSError, ValueError):
        return {}


def _ratio(h: Headline) -> float | None:
    ours, paper = h.get("ours"), h.get("paper")
    if not isinstance(ours, int | float) or not isinstance(paper, int | float) or paper == 0:
        return None
    r = float(ours) / float(paper)
    return r if math.isfinite(r) else None


def _compare(h: Headline) -> str:
    """The comparison cell: ours / paper, or for decibels (a log scale) ours - paper."""
    ours, paper = h.get("ours"), h.get("paper")
    if h.get("unit") == "dB" and isinstance(ours, int | float) and isinstance(paper, int | float):
        return f"{float(ours) - float(paper):+.1f} dB (difference)"
    r = _ratio(h)
    return _fmt(r) if r is not None else "--"


def _fmt(x: Any) -> str:
    if x is None:
        return "--"
    if isinstance(x, bool | int):
        return str(x)
    if isinstance(x, float):
        return f"{x:.4g}"
    return str(x).replace("|", "\\|")


def _entry(name: str, result: RunResult | None, error: str | None, out: Path,
           study: Study | None) -> dict[str, Any]:
    where, what, keys = PAPER_STUDIES[name]
    folder = out / name
    run = _run_json(folder) if result is not None else {}
    pngs = sorted(p.name for p in folder.glob("*.png")) if result is not None else []
    summary = dict(result.summary) if result is not None else {}
    return {"name": name, "where": where, "what": what, "keys": keys,
            "status": "ok" if result is not None and not result.failures else
            ("failed tasks" if result is not None else (error or NOT_AVAILABLE)),
            "summary": summary, "figures": [f"{name}/{p}" for p in pngs],
            "note": _note(study) if study is not None else None,
            "wall_time_s": run.get("wall_time_s"), "engine": run.get("engine"),
            "tasks": run.get("tasks"), "failed": run.get("failed"),
            "settings": run.get("settings", {})}


def write_report(entries: list[dict[str, Any]], path: Path, *, quick: bool, seed: int,
                 engine: str) -> None:
    """Write ``report.md`` (see the module docstring) from the per-study entries."""
    total = sum(e["wall_time_s"] or 0.0 for e in entries)
    lines = [
        "# The paper, reproduced",
        "",
        "Generated by `cdma-lidar study run paper --out DIR"
        + (" --quick" if quick else "") + f"` (seed {seed}, {engine}); every number below "
        "comes from that run (the studies' own `summary.json`, `results.csv` and figures are "
        "in the sub-folders). Paper: *Identity-enabled CDMA LiDAR* "
        "(`shared/seed/identity-enabled-cdma-lidar.md`). "
        + ("`--quick`: reduced trial counts and grids, so some numbers are noisier than the "
           "full run's. " if quick else "Full trial counts. ")
        + "The SNR_XC scale and the depth-resolution definitions are explained in "
        "`docs/studies.md` (\"Paper reproduction: ranging\") and `docs/paper.md`.",
        "",
        "## Results",
        "",
        "| result | quantity | paper | ours | ours / paper | unit | figure |",
        "|---|---|---|---|---|---|---|",
    ]
    for e in entries:
        fig = f"[{Path(e['figures'][0]).name}]({e['figures'][0]})" if e["figures"] else "--"
        keys = list(e["keys"]) + [k for k in e["summary"] if k not in e["keys"]]
        for key in keys:
            h = e["summary"].get(key)
            if h is None:
                status = e["status"] if e["status"] != "ok" else "missing from summary.json"
                lines.append(f"| {e['name']} ({e['where']}) | `{key}` | -- | {status} | -- "
                             f"| -- | -- |")
                continue
            lines.append(f"| {e['name']} ({e['where']}) | `{key}` | {_fmt(h.get('paper'))} | "
                         f"{_fmt(h.get('ours'))} | {_compare(h)} | {h.get('unit', '')} | "
                         f"{fig} |")
    lines += ["", "## Time", "", "| study | wall time (s) | tasks | failed | executor |",
              "|---|---|---|---|---|"]
    for e in entries:
        t = e["wall_time_s"]
        lines.append(f"| {e['name']} | {_fmt(t) if t is not None else '--'} | "
                     f"{_fmt(e['tasks'])} | {_fmt(e['failed'])} | "
                     f"{e['engine'] or e['status']} |")
    lines += [f"| **total** | {total:.1f} | | | |", ""]
    for e in entries:
        lines += [f"## {e['name']}: {e['what']} ({e['where']})", ""]
        if e["status"] != "ok":
            lines += [f"Status: **{e['status']}**.", ""]
        if e["summary"]:
            lines += ["| quantity | paper | ours | ours / paper | unit |", "|---|---|---|---|---|"]
            for key, h in e["summary"].items():
                lines.append(f"| `{key}` | {_fmt(h.get('paper'))} | {_fmt(h.get('ours'))} | "
                             f"{_compare(h)} | {h.get('unit', '')} |")
            lines.append("")
        for f in e["figures"]:
            lines += [f"![{e['name']}]({f})", ""]
        if e["note"]:
            lines += [e["note"], ""]
        if e["wall_time_s"] is not None:
            settings = ", ".join(f"{k}={v}" for k, v in e["settings"].items()
                                 if k not in ("seed",))
            lines += [f"Took {e['wall_time_s']:.1f} s on {e['engine']}; settings: {settings}. "
                      f"Files: `{e['name']}/results.csv`, `{e['name']}/summary.json`.", ""]
    atomic_write_text(path, "\n".join(lines))


def _reduce(table: Table, ctx: RunContext) -> dict[str, Any]:
    del table
    names = list(ctx.options["studies"])
    sub_set = parse_sub_set(tuple(ctx.options["sub_set"]), names)
    entries = []
    out: dict[str, Headline] = {}
    for name in names:
        try:
            study = catalogue.get_study(name)
        except ConfigError:
            log.warning("paper: study %s is %s", name, NOT_AVAILABLE)
            entries.append(_entry(name, None, None, ctx.out, None))
            continue
        result, error = None, None
        try:
            result = ctx.run_sub(study, sub_set.get(name))
        except ConfigError:
            raise  # a bad sub_set value: the user's mistake, exit 2
        except Exception as exc:  # one broken part must not cost the others' results
            error = f"failed: {type(exc).__name__}: {str(exc).splitlines()[0] if str(exc) else ''}"
            log.warning("paper: study %s %s", name, error)
        entries.append(_entry(name, result, error, ctx.out, study))
        for key, h in (result.summary.items() if result is not None else ()):
            out[f"{name}.{key}"] = h
    write_report(entries, ctx.out / "report.md", quick=ctx.options.quick,
                 seed=ctx.options.seed, engine=ctx.executor.description)
    missing = [e["name"] for e in entries if e["status"] != "ok"]
    out["studies_reproduced"] = headline(len(names) - len(missing), len(PAPER_STUDIES),
                                         "studies")
    return out


STUDY = Study(
    name="paper",
    description="every quantitative result of the paper (all paper studies) and "
                "DIR/report.md with the paper's values beside ours",
    grid=_grid, task=None, reduce=_reduce,
    settings=(
        Setting("studies", tuple(PAPER_STUDIES), "which paper studies to run"),
        Setting("sub_set", (), "settings for the parts, STUDY.KEY=VALUE items"),
    ),
    version="1",
)
