"""Run benchmark modules: ``python -m bench [area ...]``.

``python -m bench AREA --write-doc DOC`` runs one benchmark and writes what it prints
into DOC's block between ``<!-- bench AREA:begin -->`` and ``<!-- bench AREA:end -->``
(see ``bench/docblock.py``); ``--check-doc DOC`` runs it and reports the rows of that
block that a fresh run no longer prints (numbers aside; exit status 1 if any).
"""

from __future__ import annotations

import argparse
import importlib
import os
import pkgutil
import sys
import time

import bench
from bench import docblock
from cdma_lidar.errors import ConfigError
from cdma_lidar.fileio import atomic_write_text


def bench_names() -> list[str]:
    """Every benchmark area (``bench/bench_<area>.py``)."""
    mods = pkgutil.iter_modules(bench.__path__)
    return sorted(m.name.removeprefix("bench_") for m in mods if m.name.startswith("bench_"))


def run(areas: list[str]) -> None:
    """Run the benchmarks of ``areas`` (all when empty), each under a ``== bench_NAME`` line."""
    for area in bench_names():
        if not areas or area in areas:
            print(f"== bench_{area}", flush=True)
            importlib.import_module(f"bench.bench_{area}").main()


def main(argv: list[str]) -> int:
    parser = argparse.ArgumentParser(prog="python -m bench", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("areas", nargs="*", metavar="AREA",
                        help=f"benchmarks to run (default: all): {', '.join(bench_names())}")
    doc = parser.add_mutually_exclusive_group()
    doc.add_argument("--write-doc", metavar="DOC",
                     help="write the output into DOC's block of this (one) AREA")
    doc.add_argument("--check-doc", metavar="DOC",
                     help="compare DOC's block of this (one) AREA with a fresh run")
    # options of a bench itself (bench_studies reads --full from sys.argv)
    args, rest = parser.parse_known_args(argv)
    unknown = sorted(set(args.areas) - set(bench_names()))
    if unknown:
        print(f"python -m bench: unknown area {unknown[0]!r}; known: "
              f"{', '.join(bench_names())}", file=sys.stderr)
        return 2
    path = args.write_doc or args.check_doc
    if path is None:
        run(args.areas)
        return 0
    if len(args.areas) != 1:
        print("python -m bench: --write-doc / --check-doc take exactly one AREA",
              file=sys.stderr)
        return 2
    name = args.areas[0]
    started, commit = time.time(), docblock.git_commit()  # the code that will run
    try:
        docblock.read_doc(path, name)
        output = docblock.capture(lambda: run([name]), sys.stdout)
        text = docblock.read_doc(path, name)  # again: others may have edited it meanwhile
    except ConfigError as exc:
        print(f"python -m bench: {exc}", file=sys.stderr)
        return 2
    if args.check_doc:
        diff = docblock.check(text, name, output, path)
        print("\n".join(diff) if diff else f"{path}: bench {name} block matches this run")
        return 1 if diff else 0
    head = docblock.header(name, path, started, commit, os.cpu_count() or 1,
                           tuple(rest))
    atomic_write_text(path, docblock.replace_block(text, name, docblock.make_block(head, output),
                                                    path))
    return 0


if __name__ == "__main__":
    raise SystemExit(main(sys.argv[1:]))
