"""Start-up of the ``cdma-lidar`` command: ``--help``, every ``COMMAND --help`` and ``scene list``.

Each is run in a fresh interpreter, best of ``REPEATS`` wall times, against the bare
interpreter (``python -c pass``) and ``import numpy`` measured in the same run. Targets
(issue 43): every ``--help`` within :data:`HELP_OVER_BARE_S` of bare Python (help text
without numpy and the host stack), ``scene list`` under :data:`SCENE_LIST_S` in all. The
CPU time (user + system) of the best run is printed too: it moves less with the machine's
load, which is printed first and last. ``python -m bench startup``.
"""

from __future__ import annotations

import os
import resource
import subprocess
import sys
import time

from cdma_lidar.cli import COMMANDS

REPEATS = 5
#: Largest start-up of a ``--help`` over bare Python (s).
HELP_OVER_BARE_S = 0.2
#: Largest start-up of ``scene list`` (s).
SCENE_LIST_S = 0.5


def _best(argv: list[str]) -> tuple[float, float]:
    """(best wall s, CPU s of that run) of a command in a fresh process."""
    best = (float("inf"), 0.0)
    for _ in range(REPEATS):
        before = resource.getrusage(resource.RUSAGE_CHILDREN)
        t0 = time.perf_counter()
        # check: a command that fails (a missing dependency) would time as a fast start-up
        subprocess.run(argv, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, check=True)
        wall = time.perf_counter() - t0
        after = resource.getrusage(resource.RUSAGE_CHILDREN)
        cpu = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
        best = min(best, (wall, cpu))
    return best


def main() -> None:
    print(f"load average {os.getloadavg()[0]:.2f} on {os.cpu_count()} CPUs; best of {REPEATS}")
    py = [sys.executable]
    bare, _ = _best([*py, "-c", "pass"])
    numpy_s, _ = _best([*py, "-c", "import numpy"])
    print(f"{'python -c pass':30s} {bare:6.3f} s (baseline)")
    print(f"{'python -c import numpy':30s} {numpy_s:6.3f} s  {numpy_s / bare:5.1f}x  "
          f"{numpy_s - bare:+6.3f} s")
    cli = [*py, "-m", "cdma_lidar.cli"]
    runs = [([*words, "--help"], bare + HELP_OVER_BARE_S)
            for words in [[], *([c.name] for c in COMMANDS)]]
    runs.append((["scene", "list"], SCENE_LIST_S))
    for words, target in runs:
        wall, cpu = _best([*cli, *words])
        flag = "" if wall < target else f"  over its target, {target:.3f} s"
        print(f"{' '.join(['cdma-lidar', *words]):30s} {wall:6.3f} s  {wall / bare:5.1f}x  "
              f"{wall - bare:+6.3f} s  cpu {cpu:5.3f} s{flag}")
    print(f"load average {os.getloadavg()[0]:.2f} at the end")


if __name__ == "__main__":
    main()
