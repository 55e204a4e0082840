"""Start-up of the ``cdma-lidar`` command: ``--help`` and every ``COMMAND --help``.

Each is run in a fresh interpreter, best of ``REPEATS`` wall times, against the bare
interpreter (``python -c pass``) and ``import numpy`` measured in the same run; the
target (issue 26) is under 0.5 s each on the 2-core development machine. The CPU time
(user + system) of the best run is printed too: it moves less with the machine's load,
which is printed first. ``python -m bench startup``.
"""

from __future__ import annotations

import os
import resource
import subprocess
import sys
import time

from cdma_lidar.cli import COMMANDS

REPEATS = 5
TARGET_S = 0.5


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
    print(f"{'python -c pass':28s} {bare:6.3f} s (baseline)")
    print(f"{'python -c import numpy':28s} {numpy_s:6.3f} s  {numpy_s / bare:5.1f}x")
    cli = [*py, "-m", "cdma_lidar.cli"]
    for words in [[], *([c.name] for c in COMMANDS)]:
        wall, cpu = _best([*cli, *words, "--help"])
        flag = "" if wall < TARGET_S else f"  over {TARGET_S} s"
        print(f"{' '.join(['cdma-lidar', *words, '--help']):28s} {wall:6.3f} s  "
              f"{wall / bare:5.1f}x  cpu {cpu:5.3f} s{flag}")


if __name__ == "__main__":
    main()
