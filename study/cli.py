"""``cdma-lidar study ...``: list the studies and run one, locally or on a Dask cluster.

Commands (a contract: users and tests rely on these forms)::

    cdma-lidar study list
    cdma-lidar study run NAME --out DIR [--quick]
                         [--workers N | --scheduler ADDRESS | --gpus N]
                         [--resume] [--set KEY=VALUE ...] [--no-progress]
    cdma-lidar study ask tradeoff DIR --max-p95 METRES [--scene NAME] [--min-valid F]
                         [--max-adc-rate HZ]
    cdma-lidar study frame SCENE --seed N --frame-id F --out FILE [--force]

``list`` prints one line per study: its name, then a one-line description.
``run`` writes DIR/results.csv, DIR/summary.json, DIR/run.json, DIR/replicates.csv,
DIR/failures.json and the study's PNG figures (docs/studies.md). ``--workers 0`` runs
in this process without Dask; ``--workers N`` a local Dask cluster of N worker
processes (default: one per CPU); ``--scheduler tcp://HOST:PORT`` (or ``tls://``) an
existing cluster; ``--gpus N`` a local cluster of one worker per GPU (worker i sees GPU i
only, and the receive chain's ``auto`` kernel choice finds it). Trial-heavy studies run
in chunks of trials; "M tasks computed" counts those chunks. A ``--resume`` with nothing
missing starts no cluster. Exit status: 0 all tasks done, 1 some tasks failed (listed on stderr
with their parameters, all others done and written), 2 bad name, setting, grid or
address (one line), 130 interrupted (finished tasks are kept: rerun with --resume).
``ask tradeoff`` answers from a finished run's folder with the fastest configuration
meeting the constraints, its 95 % intervals and the runner-up
(:func:`cdma_lidar.study.tradeoff.ask`): exit status 0 with an answer, 1 when no
configuration meets them, 2 for a bad folder or option (one line).
``frame`` writes one study frame of SCENE (a preset or a TOML file) in the format of
``cdma-lidar scan`` (by FILE's extension): the same arrays, with equal values, as
``cdma-lidar scan --port 'virtual://SCENE?seed=N' --frame-id F --out FILE``, the
wall-clock stamp aside (:func:`cdma_lidar.study.simulate.write_study_frame`: the device's
acquisition, receiver configuration and the scan's default power, without the protocol).
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

__all__ = ["register"]

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
    result = write_study_frame(args.scene, args.seed, args.frame_id, args.out, force=args.force)
    sys.stdout.write(f"study frame {args.scene} seed {args.seed} frame id {args.frame_id}: "
                     f"{int(result.cloud.has_range.sum())} points -> {args.out}\n")
    return 0


def register(sub: argparse._SubParsersAction) -> None:
    """Add ``study list``, ``run``, ``ask`` and ``frame``."""
    p = sub.add_parser("study", help="sweeps of the speed/accuracy trade (docs/studies.md)")
    ssub = p.add_subparsers(dest="study_command", metavar="STUDY_COMMAND",
                            parser_class=type(p))
    ssub.required = True
    pl = ssub.add_parser("list", help="the studies, one line each")
    pl.set_defaults(func=cmd_list)
    pr = ssub.add_parser("run", help="run a study into --out DIR")
    pr.add_argument("name", help="study name (see `study list`)")
    pr.add_argument("--out", required=True, help="output folder")
    pr.add_argument("--quick", action="store_true", help="the study's reduced grid")
    where = pr.add_mutually_exclusive_group()
    where.add_argument("--workers", type=int, default=None,
                       help="local Dask workers (default: one per CPU; 0: in this process)")
    where.add_argument("--scheduler", default=None,
                       help="address of a running Dask scheduler, tcp://HOST:PORT or tls://...")
    where.add_argument("--gpus", type=int, default=None,
                       help="a local Dask cluster of one worker per GPU (GPU i for worker i)")
    pr.add_argument("--resume", action="store_true",
                    help="reuse the finished tasks in --out, compute only the missing ones")
    pr.add_argument("--set", action="append", metavar="KEY=VALUE",
                    help="change a study setting (repeatable; lists comma-separated)")
    pr.add_argument("--no-progress", action="store_true", help="no progress bar")
    pr.set_defaults(func=cmd_run)
    pa = ssub.add_parser("ask", help="the fastest configuration of a finished run meeting "
                         "an accuracy target")
    pa.add_argument("name", help="the study asked (tradeoff)")
    pa.add_argument("dir", help="the --out folder of a finished run")
    pa.add_argument("--max-p95", type=float, required=True, metavar="METRES",
                    help="95th-percentile range error at most this (m)")
    pa.add_argument("--scene", default=None, help="the scene (needed when the run has several)")
    pa.add_argument("--min-valid", type=float, default=0.95,
                    help="valid fraction of object pixels at least this (default 0.95)")
    pa.add_argument("--max-adc-rate", type=float, default=None, metavar="HZ",
                    help="ADC sample rate (S x chip rate) at most this")
    pa.set_defaults(func=cmd_ask)
    pf = ssub.add_parser("frame", help="one study frame, written as `cdma-lidar scan` writes "
                         "a scan of the virtual device")
    pf.add_argument("scene", help="a scene preset or .toml file")
    pf.add_argument("--seed", type=int, default=0, help="noise seed (default 0)")
    pf.add_argument("--frame-id", type=int, default=0, metavar="F",
                    help="frame id, which seeds the frame's noise (default 0)")
    pf.add_argument("--out", required=True, help="output cloud (.npz, .ply, ... as `scan`)")
    pf.add_argument("--force", action="store_true", help="overwrite a partial scan of --out")
    pf.set_defaults(func=cmd_frame)
