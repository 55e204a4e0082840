"""The numbers of docs/paper.md and docs/studies.md, generated from a ``paper`` run.

Every number those pages quote about the paper's results sits in a generated block::

    <!-- generated:NAME by `python -m cdma_lidar.study.paperdocs DIR` -->
    ...
    <!-- end:NAME -->

``python -m cdma_lidar.study.paperdocs DIR`` rewrites the blocks from ``DIR/summary.json``
and ``DIR/run.json`` (the folder of ``cdma-lidar study run paper --out DIR``);
``--check`` changes nothing and exits 1, naming each stale block, when a page differs
from what DIR gives (exit 2 for a missing folder or a page without its blocks). Blocks:

* ``paper-results`` -- per result: where, key, the paper's number as printed, ours at the
  paper's point and at the default with their 95 % intervals, the kind, the verdict;
* ``paper-counts`` -- the predictions by verdict and the other rows by kind;
* ``paper-calibration`` -- the joint calibration (:mod:`cdma_lidar.study.papercal`):
  fitted values, each measurement's residual, the held-out prediction;
* ``paper-assumptions`` -- the operating point, generated from the presets and the
  studies' paper-point settings (:func:`cdma_lidar.study.paperlab.assumptions_markdown`).
"""

from __future__ import annotations

import argparse
import json
import logging
import re
import sys
from pathlib import Path
from typing import Any

from cdma_lidar.fileio import atomic_write_text
from cdma_lidar.study.paper import (
    NOT_COVERED,
    calibration_markdown,
    fmt_interval,
    fmt_value,
    headline,
    operating_point,
    row_groups,
    verdict_cell,
)
from cdma_lidar.study.paperlab import PAPER_CITATION, assumptions_markdown

__all__ = ["BLOCKS", "DOCS", "apply", "blocks", "main"]

log = logging.getLogger(__name__)

#: The pages with generated blocks (relative to the repository root) and their blocks.
DOCS = {"docs/paper.md": ("paper-counts", "paper-results", "paper-calibration",
                         "paper-assumptions"),
        "docs/studies.md": ("paper-counts",)}
BLOCKS = ("paper-counts", "paper-results", "paper-calibration", "paper-assumptions")

_BLOCK = re.compile(r"(<!-- generated:(?P<name>[a-z-]+) [^>]*-->\n)(?P<body>.*?)"
                    r"(<!-- end:(?P=name) -->)", re.S)


def blocks(summary: dict[str, Any], run: dict[str, Any]) -> dict[str, str]:
    """The generated blocks' text from a paper run's summary.json and run.json."""
    settings = run.get("settings", {})
    how = (f"`cdma-lidar study run paper --out DIR{' --quick' if run.get('quick') else ''}` "
           f"(seed {settings.get('seed')}, point={settings.get('point', 'both')})")

    n = {k.replace("_", " "): v for k, v in (summary.get("counts") or {}).items()}
    counts = (f"From {how}: **{headline(n)}**\n" if n else
              f"From {how}: no counts in this run.\n")
    rows = [f"From {how}. Paper: {PAPER_CITATION}.", "",
            "| where | result | paper | ours at the paper's point [95 %] | ours at the default "
            "[95 %] | kind | verdict |", "|---|---|---|---|---|---|---|"]
    for name, (where, _, keys) in row_groups().items():
        for key in keys:
            h = summary.get(f"{name}.{key}")
            if h is None:
                rows.append(f"| {where} | `{name}.{key}` | -- | not in this run | -- | -- | -- |")
                continue
            unit = (f" {h['unit']}" if h.get("unit") not in (None, "", "1")
                    and isinstance(h.get("paper"), int | float) else "")
            at = fmt_interval(h.get("paper_point"), h.get("paper_point_ci95", h.get("ci95")))
            rows.append(f"| {where} | `{name}.{key}` | {fmt_value(h.get('paper'))}{unit} | {at} | "
                        f"{fmt_interval(h.get('ours'), h.get('ci95'))} | {h.get('kind', '--')} | "
                        f"{verdict_cell(h) if 'kind' in h else '--'} |")
    for where, _, _ in NOT_COVERED:
        rows.append(f"| {where} | -- | -- | -- | -- | -- | not covered |")
    cal = summary.get("calibration")
    calib = ("\n".join(calibration_markdown(cal)[2:]) if cal else "No calibration in this run.\n")
    return {"paper-counts": counts, "paper-results": "\n".join(rows) + "\n",
            "paper-calibration": calib,
            "paper-assumptions": "\n".join(assumptions_markdown(operating_point())) + "\n"}


def apply(text: str, generated: dict[str, str]) -> tuple[str, list[str]]:
    """``text`` with every generated block replaced; the names of the blocks that changed."""
    changed: list[str] = []

    def sub(m: re.Match[str]) -> str:
        name = m.group("name")
        if name not in generated:
            return m.group(0)
        if m.group("body") != generated[name]:
            changed.append(name)
        return m.group(1) + generated[name] + m.group(4)

    return _BLOCK.sub(sub, text), changed


def main(argv: list[str] | None = None) -> int:
    """``python -m cdma_lidar.study.paperdocs DIR [--check] [--root ROOT]``."""
    ap = argparse.ArgumentParser(prog="python -m cdma_lidar.study.paperdocs",
                                 description="regenerate (or --check) the paper numbers in docs")
    ap.add_argument("run", help="folder of `cdma-lidar study run paper --out DIR`")
    ap.add_argument("--check", action="store_true", help="change nothing; exit 1 if stale")
    ap.add_argument("--root", default=".", help="repository root (default: .)")
    args = ap.parse_args(argv)
    folder = Path(args.run)
    try:
        summary = json.loads((folder / "summary.json").read_text())
        run = json.loads((folder / "run.json").read_text())
    except (OSError, ValueError) as exc:
        sys.stderr.write(f"paperdocs: {folder}: not a paper run ({exc})\n")
        return 2
    generated = blocks(summary, run)
    stale = []
    for rel, names in DOCS.items():
        path = Path(args.root) / rel
        try:
            text = path.read_text()
        except OSError as exc:
            sys.stderr.write(f"paperdocs: {path}: {exc.strerror}\n")
            return 2
        found = {m.group("name") for m in _BLOCK.finditer(text)}
        missing = [n for n in names if n not in found]
        if missing:
            sys.stderr.write(f"paperdocs: {path}: no generated block {', '.join(missing)}\n")
            return 2
        new, changed = apply(text, generated)
        stale += [f"{rel}: {n}" for n in changed]
        if changed and not args.check:
            atomic_write_text(path, new)
    if stale and args.check:
        sys.stderr.write("paperdocs: stale against " + str(folder) + ": " + "; ".join(stale)
                         + "\n")
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
