"""``cdma-lidar study``: list, run, one-line errors, and a separately started Dask cluster."""

from __future__ import annotations

import json
import os
import socket
import subprocess
import sys
import time
from pathlib import Path

import pytest
from cli_helpers import one_line_error as _one_line_error
from cli_helpers import run_cli as _run

from cdma_lidar.errors import LinkError
from cdma_lidar.study.catalogue import get_study, register_study, studies
from cdma_lidar.study.engine import read_csv, run_study

TINY_SET = ["--set", "degrees=5", "--set", "S=1,2", "--set", "snr_db=-12,-6",
            "--set", "trials=20"]


def test_list_names_every_study_on_one_line_each(capsys):
    code, out, _ = _run(capsys, "study", "list")
    assert code == 0
    lines = out.splitlines()
    assert [ln.split()[0] for ln in lines] == [s.name for s in studies()]
    assert "detection" in out


def test_run_writes_table_summary_run_info_and_figure(capsys, tmp_path):
    code, out, _ = _run(capsys, "study", "run", "detection", "--out", str(tmp_path), "--quick",
                        "--workers", "0", *TINY_SET, "--no-progress")
    assert code == 0
    assert "4 points, 4 tasks computed" in out
    table = read_csv(tmp_path / "results.csv")
    assert table.columns[:5] == ["degree", "S", "snr_db", "trials", "replicates"]
    summary = json.loads((tmp_path / "summary.json").read_text())
    assert summary and all(set(h) == {"ours", "paper", "unit"} for h in summary.values())
    info = json.loads((tmp_path / "run.json").read_text())
    assert info["quick"] is True and info["machine_columns"] == ["time_per_trial_s"]
    assert (tmp_path / "detection.png").exists()
    code, out, _ = _run(capsys, "study", "run", "detection", "--out", str(tmp_path), "--quick",
                        "--workers", "0", *TINY_SET, "--resume", "--no-progress")
    assert code == 0 and "0 tasks computed, 4 reused" in out


@pytest.mark.parametrize("argv, needle", [
    (["study", "run", "nope", "--out", "X"], "unknown study 'nope'; known: tradeoff, extremes"),
    (["study", "run", "detection", "--out", "X", "--set", "bogus=1"], "no such setting"),
    (["study", "run", "detection", "--out", "X", "--set", "S=0"], "S must be"),
    (["study", "run", "detection", "--out", "X", "--set", "S=x"], "expected int"),
    (["study", "run", "detection", "--out", "X", "--set", "noequals"], "KEY=VALUE"),
    (["study", "run", "detection", "--out", "X", "--scheduler", "localhost:8786"],
     "tcp://HOST:PORT"),
    (["study", "run", "detection", "--out", "X", "--workers", "2", "--scheduler", "tcp://a:1"],
     "not allowed with"),
    (["study", "run", "detection", "--out", "X", "--workers", "-1"], "--workers"),
    (["study", "run", "detection", "--out", "X", "--gpus", "-1"], "--gpus"),
    (["study", "run", "detection", "--out", "X", "--gpus", "1", "--workers", "2"],
     "not allowed with"),
    (["study", "run", "detection"], "--out"),
    (["study"], "STUDY_COMMAND"),
])
def test_bad_names_settings_grids_and_addresses_exit_2_with_one_line(capsys, tmp_path, argv,
                                                                      needle):
    argv = [str(tmp_path / "o") if a == "X" else a for a in argv]
    assert needle in _one_line_error(capsys, *argv)


def test_a_file_as_out_is_one_line(capsys, tmp_path):
    f = tmp_path / "file"
    f.write_text("")
    assert "is a file" in _one_line_error(capsys, "study", "run", "detection", "--out", str(f),
                                          "--workers", "0", *TINY_SET)


def test_registry_refuses_a_taken_name():
    with pytest.raises(ValueError, match="already registered"):
        register_study(type(get_study("detection"))("detection", "x", grid=lambda o: [],
                                                     task=None))


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _wait_for_port(port: int, timeout_s: float = 60.0) -> None:
    """Until something listens on 127.0.0.1:port (a loaded CI machine starts Dask slowly)."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        try:
            socket.create_connection(("127.0.0.1", port), timeout=1.0).close()
            return
        except OSError:
            time.sleep(0.2)
    pytest.fail(f"the dask scheduler did not listen on port {port} within {timeout_s} s")


def test_separately_started_scheduler_and_worker_give_the_same_table(capsys, tmp_path):
    """`dask scheduler` + `dask worker` as their own processes, the CLI as the client."""
    pytest.importorskip("distributed")
    # this interpreter's Dask (and so this tree's cdma_lidar), not whatever `dask` is on PATH
    def dask_cli(command: str) -> list[str]:
        return [sys.executable, "-m", f"distributed.cli.dask_{command}"]
    port = _free_port()
    address = f"tcp://127.0.0.1:{port}"
    env = {**os.environ, "DASK_DISTRIBUTED__WORKER__DAEMON": "False"}
    procs = [subprocess.Popen([*dask_cli("scheduler"), "--host", "127.0.0.1", "--port",
                               str(port), "--no-dashboard"], stdout=subprocess.DEVNULL,
                              stderr=subprocess.DEVNULL, env=env)]
    try:
        _wait_for_port(port)
        procs.append(subprocess.Popen([*dask_cli("worker"), address, "--nthreads", "1",
                                       "--nworkers", "2", "--no-dashboard"],
                                      stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                                      env=env))
        code, _, err = _run(capsys, "study", "run", "detection", "--out",
                            str(tmp_path / "remote"), "--scheduler", address, *TINY_SET,
                            "--no-progress")
        assert code == 0, err
    finally:
        for p in reversed(procs):
            p.terminate()
        for p in reversed(procs):
            try:
                p.wait(timeout=20)
            except subprocess.TimeoutExpired:
                p.kill()
    code, _, err = _run(capsys, "study", "run", "detection", "--out", str(tmp_path / "local"),
                        "--workers", "0", *TINY_SET, "--no-progress")
    assert code == 0, err
    drop = {"time_per_trial_s"}
    tables = [[{k: v for k, v in r.items() if k not in drop}
               for r in read_csv(Path(tmp_path / d / "results.csv")).rows]
              for d in ("remote", "local")]
    assert tables[0] == tables[1]
    assert json.loads((tmp_path / "remote" / "run.json").read_text())["engine"] == \
        f"dask scheduler {address}"


def test_an_unreachable_scheduler_is_a_link_error_naming_the_address(tmp_path):
    address = f"tcp://127.0.0.1:{_free_port()}"
    with pytest.raises(LinkError, match="cannot reach the Dask scheduler"):
        run_study(get_study("detection"), tmp_path, scheduler=address, connect_timeout_s=1.0)


def test_run_prints_dict_summary_entries_by_their_numbers(capsys, tmp_path):
    """The paper study's ``counts`` and ``calibration`` are dicts, not headlines: their
    numbers are printed, not ``None`` (eq29 alone: a few seconds)."""
    code, out, _ = _run(capsys, "study", "run", "paper", "--out", str(tmp_path), "--workers",
                        "0", "--set", "studies=eq29", "--no-progress")
    assert code == 0 and "None" not in out
    summary = json.loads((tmp_path / "summary.json").read_text())
    lines = {ln.split(":")[0].strip(): ln for ln in out.splitlines()[1:]}
    n = summary["counts"]
    printed = lines["counts"].split(": ", 1)[1].split(", ")
    assert sorted(printed) == sorted(f"{k}={v}" for k, v in n.items())
    link = summary["calibration"]["parameters"]["link_db"]
    assert f"parameters.link_db={link:g}" in lines["calibration"]
    assert "more fields in summary.json" in lines["calibration"]
    assert lines["eq29.frame_rate_hz"].endswith("Hz (paper: 122.0)")
