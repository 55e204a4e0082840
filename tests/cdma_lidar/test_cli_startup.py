"""Start-up of the ``cdma-lidar`` command: only the chosen command's module is loaded.

``--help``, every ``COMMAND --help`` and ``scene list`` run in a fresh interpreter, which
then reports which third-party packages ended up in ``sys.modules``: neither numpy nor a
heavy one may, since each costs 0.1-0.5 s that every command would pay (no timing is
asserted). The table
of commands in :mod:`cdma_lidar.cli` must say what each module registers.
"""

from __future__ import annotations

import argparse
import importlib
import json
import subprocess
import sys

import pytest

from cdma_lidar.cli import COMMANDS, build_parser

#: Packages no command may import just to start (they load when the work needs them).
HEAVY = ("matplotlib", "scipy", "dask", "distributed", "tqdm", "rerun", "open3d", "pyarrow",
         "laspy", "mcap")

_PROBE = """
import json, sys
{before}
from cdma_lidar.cli import main
try:
    main(sys.argv[1:])
except SystemExit:
    pass
print(json.dumps(sorted({{m.split('.')[0] for m in sys.modules}})))
"""


def _loaded_after(*argv: str, before: str = "") -> set[str]:
    """Top-level packages in ``sys.modules`` after ``cdma-lidar ARGV`` (``before`` runs first)."""
    proc = subprocess.run([sys.executable, "-c", _PROBE.format(before=before), *argv],
                          capture_output=True,
                          text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr
    return set(json.loads(proc.stdout.splitlines()[-1]))


def test_top_level_help_loads_no_command_module_and_not_numpy() -> None:
    loaded = _loaded_after("--help")
    assert "numpy" not in loaded
    assert not loaded & set(HEAVY)


@pytest.mark.parametrize("command", [c.name for c in COMMANDS])
def test_a_commands_help_loads_no_heavy_package(command: str) -> None:
    loaded = _loaded_after(command, "--help")
    assert not loaded & set(HEAVY), f"`cdma-lidar {command} --help` imports {loaded & set(HEAVY)}"


@pytest.mark.parametrize("command", [c.name for c in COMMANDS])
def test_a_commands_help_loads_no_numpy(command: str) -> None:
    """Help text without numpy (issue 43.4: within 0.2 s of bare Python): each layer's
    ``cli`` holds only the options and defers the work (:func:`cdma_lidar.lazy.later`)."""
    assert "numpy" not in _loaded_after(command, "--help")


def test_scene_list_loads_no_numpy() -> None:
    """``scene list`` reads the preset files; it loads no scene model (issue 43.4)."""
    assert "numpy" not in _loaded_after("scene", "list")


def test_the_probe_can_see_numpy() -> None:
    """The check above can fail: numpy imported on the way shows up."""
    assert "numpy" in _loaded_after("scan", "--help", before="import numpy")


def test_the_probe_can_see_a_heavy_import() -> None:
    """The check above can fail: a heavy package imported on the way shows up."""
    assert "scipy" in _loaded_after("codes", "--help", before="import scipy.special")


def _registered(module: str) -> dict[str, str]:
    """{command: help} that ``module.register`` adds to a fresh parser."""
    parser = argparse.ArgumentParser()
    sub = parser.add_subparsers()
    importlib.import_module(module).register(sub)
    return {a.dest: a.help for a in sub._choices_actions}


@pytest.mark.parametrize("module", sorted({c.module for c in COMMANDS}))
def test_the_command_table_says_what_each_module_registers(module: str) -> None:
    table = {c.name: c.help for c in COMMANDS if c.module == module}
    assert _registered(module) == table


def test_the_full_parser_knows_every_command(capsys: pytest.CaptureFixture[str]) -> None:
    parser = build_parser()
    sub = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    assert list(sub.choices) == sorted(sub.choices, key=[c.name for c in COMMANDS].index)
    with pytest.raises(SystemExit) as exc:
        parser.parse_args(["scan", "--help"])
    assert exc.value.code == 0 and "--out" in capsys.readouterr().out
