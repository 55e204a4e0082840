"""The work of ``cdma-lidar study ...``: its options and exit statuses are in
:mod:`cdma_lidar.study.cli`, which imports this module when a command runs.

The catalogue imports every study, and with them numpy, scipy and the whole stack.
"""

from __future__ import annotations

import argparse
import json
import logging
import sys

from cdma_lidar.errors import ConfigError
from cdma_lidar.study.catalogue import get_study, studies
from cdma_lidar.study.engine import parse_set, run_study
from cdma_lidar.study.simulate import write_study_frame
from cdma_lidar.study.tradeoff import ask

__all__ = ["cmd_ask", "cmd_frame", "cmd_list", "cmd_run"]

log = logging.getLogger(__name__)


def _safe(text: str) -> str:
    """Text from a study or a task error, with control characters escaped for a terminal."""
    return "".join(c if c.isprintable() else repr(c)[1:-1] for c in text)


def cmd_list(args: argparse.Namespace) -> int:
    """``study list``: name and one line per study."""
    width = max(len(s.name) for s in studies())
    for s in studies():
        sys.stdout.write(f"{s.name:<{width}}  {_safe(s.description)}\n")
    return 0


def cmd_run(args: argparse.Namespace) -> int:
    """``study run NAME``: run a study and write its table, summary and figures."""
    study = get_study(args.name)
    overrides = parse_set(args.set or [])
    # run_study checks the --set values, the grid and --workers before any cluster starts
    result = run_study(study, args.out, quick=args.quick, overrides=overrides,
                       workers=args.workers, scheduler=args.scheduler, resume=args.resume,
                       gpus=args.gpus or 0,
                       progress=not args.no_progress and sys.stderr.isatty())
    sys.stdout.write(f"{study.name}: {len(result.table)} points, {result.computed} tasks "
                     f"computed, {result.cached} reused -> {result.out}\n")
    for name, h in result.summary.items():
        sys.stdout.write(f"  {name}: {_safe(_summary_value(h))}\n")
    for f in result.failures:
        sys.stderr.write(f"cdma-lidar study: task failed: {_safe(json.dumps(f.params))} "
                         f"replicate {f.replicate}: {_safe(f.error)}\n")
    return 1 if result.failures else 0


def _summary_value(h: dict) -> str:
    """One summary entry on one line: a headline's value, unit and the paper's; another
    dict (the paper study's ``counts``, ``calibration``) its numbers, one level deep, as
    ``key=value`` and how many other fields summary.json holds."""
    if "ours" in h:
        paper = "" if h.get("paper") is None else f" (paper: {h['paper']})"
        return f"{h.get('ours')} {h.get('unit', '')}{paper}"
    shown, rest = [], 0
    for key, v in h.items():
        items = v.items() if isinstance(v, dict) else [(None, v)]
        for sub, x in items:
            if isinstance(x, int | float) and not isinstance(x, bool):
                shown.append(f"{key}.{sub}={x:g}" if sub else f"{key}={x:g}")
            else:
                rest += 1
    more = f" (+{rest} more fields in summary.json)" if rest else ""
    return ", ".join(shown) + more


def cmd_ask(args: argparse.Namespace) -> int:
    """``study ask tradeoff DIR``: the fastest configuration meeting the constraints."""
    if args.name != "tradeoff":
        raise ConfigError(f"study ask {args.name!r}: only 'tradeoff' answers questions", "name")
    answer = ask(args.dir, args.max_p95, scene=args.scene, min_valid=args.min_valid,
                 max_adc_rate_hz=args.max_adc_rate)
    for line in answer.describe().splitlines():
        sys.stdout.write(_safe(line) + "\n")
    return 0 if answer.best is not None else 1


def cmd_frame(args: argparse.Namespace) -> int:
    """``study frame SCENE``: one study frame written as ``cdma-lidar scan`` writes a scan."""
    if args.seed < 0:
        raise ConfigError(f"--seed must be a non-negative integer, not {args.seed}", "seed")
    if not 0 <= args.frame_id <= 2**31 - 2:
        raise ConfigError(f"--frame-id must be from 0 to {2**31 - 2}, not {args.frame_id}",
                          "frame_id")
    result = write_study_frame(args.scene, args.seed, args.frame_id, args.out, force=args.force,
                               engine=args.engine)
    sys.stdout.write(f"study frame {args.scene} seed {args.seed} frame id {args.frame_id}: "
                     f"{int(result.cloud.has_range.sum())} points -> {args.out}\n")
    return 0
