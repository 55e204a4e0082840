"""``cdma-lidar study ...``: list the studies and run one, locally or on a Dask cluster.

Commands (a contract: users and tests rely on these forms)::

    cdma-lidar study list
    cdma-lidar study run NAME --out DIR [--quick]
                         [--workers N | --scheduler ADDRESS | --gpus N]
                         [--resume] [--set KEY=VALUE ...] [--no-progress]
    cdma-lidar study ask tradeoff DIR --max-p95 METRES [--scene NAME] [--min-valid F]
                         [--max-adc-rate HZ]
    cdma-lidar study frame SCENE --seed N --frame-id F --out FILE [--engine rtl] [--force]

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

This module holds only the options (no numpy, no study catalogue), so ``study --help``
starts as fast as Python; the work is in :mod:`cdma_lidar.study.commands`, imported when
a command runs.
"""

from __future__ import annotations

import argparse

from cdma_lidar.lazy import later

__all__ = ["register"]

#: The module that does the commands' work.
COMMANDS_MODULE = "cdma_lidar.study.commands"


def register(sub: argparse._SubParsersAction) -> None:
    """Add ``study list``, ``run``, ``ask`` and ``frame``."""
    p = sub.add_parser("study", help="sweeps of the speed/accuracy trade (docs/studies.md)")
    ssub = p.add_subparsers(dest="study_command", metavar="STUDY_COMMAND",
                            parser_class=type(p))
    ssub.required = True
    pl = ssub.add_parser("list", help="the studies, one line each")
    pl.set_defaults(func=later("cmd_list", COMMANDS_MODULE))
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
    pr.set_defaults(func=later("cmd_run", COMMANDS_MODULE))
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
    pa.set_defaults(func=later("cmd_ask", COMMANDS_MODULE))
    pf = ssub.add_parser("frame", help="one study frame, written as `cdma-lidar scan` writes "
                         "a scan of the virtual device")
    pf.add_argument("scene", help="a scene preset or .toml file")
    pf.add_argument("--seed", type=int, default=0, help="noise seed (default 0)")
    pf.add_argument("--frame-id", type=int, default=0, metavar="F",
                    help="frame id, which seeds the frame's noise (default 0)")
    pf.add_argument("--out", required=True, help="output cloud (.npz, .ply, ... as `scan`)")
    pf.add_argument("--force", action="store_true", help="overwrite a partial scan of --out")
    pf.add_argument("--engine", choices=("model", "rtl"), default="model",
                    help="the receive chain: the model (default) or the reference RTL under "
                    "Verilator, as virtual://SCENE?engine=rtl")
    pf.set_defaults(func=later("cmd_frame", COMMANDS_MODULE))
