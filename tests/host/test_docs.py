"""The README's command lines run, and the docs' multi-user figures come from the preset.

README: every ``cdma-lidar`` line of its ``sh`` blocks runs from a fresh folder in order,
with these quick variants, each named here so that a reader can redo them by hand:

* scans get ``--no-progress`` and, on a device, ``--set columns_per_frame=16`` (16 of
  160 columns);
* studies run in this process on a tiny grid (``--workers 0`` and :data:`TINY_STUDY`);
* ``device`` lines serve: the test waits for the first line they print (the pty path or
  the ``socket://`` URL) and stops them; port 7700 becomes a free one and ``~`` a fresh
  home folder;
* lines holding ``...`` or ``HOST`` are templates, not commands: the test counts them.
"""

from __future__ import annotations

import os
import re
import subprocess
import sys
import tomllib
from pathlib import Path

import pytest
from cli_helpers import run_cli

from cdma_lidar.firmware_model.uid import uid_to_str

ROOT = Path(__file__).resolve().parents[2]

#: Settings that make the README's tradeoff study a few seconds long (same grid for both
#: lines, so --resume has nothing left to do).
TINY_STUDY = ["--set", "scenes=flat-wall", "--set", "S=1", "--set", "R=1", "--set", "degree=9",
              "--set", "adc_bits=8", "--set", "gate=64", "--set", "method=none",
              "--set", "fidelity=accumulated"]


def readme_lines() -> list[str]:
    """The ``cdma-lidar`` lines of the README's ``sh`` blocks, comments stripped."""
    text = (ROOT / "README.md").read_text(encoding="utf-8")
    blocks = re.findall(r"```sh\n(.*?)```", text, flags=re.S)
    lines = [ln.split("  #")[0].strip() for b in blocks for ln in b.splitlines()]
    return [ln for ln in lines if ln.startswith("cdma-lidar ")]


def _profile() -> str:
    text = (ROOT / "README.md").read_text(encoding="utf-8")
    return re.search(r"```toml\n(.*?)```", text, flags=re.S).group(1)


def _serve(argv: list[str], home: Path) -> str:
    env = {**os.environ, "HOME": str(home), "XDG_CONFIG_HOME": str(home / ".config")}
    proc = subprocess.Popen([sys.executable, "-m", "cdma_lidar.cli", *argv], env=env,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        first = proc.stdout.readline().strip()
    finally:
        proc.terminate()
        proc.wait(timeout=30)
    return first


@pytest.mark.slow
def test_every_readme_command_runs(capsys, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    home = tmp_path / "home"
    home.mkdir()
    (tmp_path / "scan.toml").write_text(_profile())
    templates = 0
    lines = readme_lines()
    assert len(lines) > 20
    for line in lines:
        if "..." in line or "HOST" in line:
            templates += 1
            continue
        argv = line.replace("~/", f"{home}/").replace(":7700", ":0").split()[1:]
        if argv[0] == "device":
            first = _serve(argv, home)
            assert first.startswith(("/dev/", "socket://")), (line, first)
            if "--key-file" in argv:   # the bare option: the key outside the working tree
                key = home / ".config" / "cdma-lidar" / "device.key"
                assert key.stat().st_mode & 0o777 == 0o600
            continue
        if argv[0] == "scan":
            argv += ["--no-progress"]
            if "replay://" not in line:
                argv += ["--set", "columns_per_frame=16"]
        if argv[:2] == ["study", "run"]:
            argv += ["--workers", "0", "--no-progress", *TINY_STUDY]
        code, out, err = run_cli(capsys, *argv)
        assert code == 0, f"{line}\n{err}"
        if "--resume" in argv and argv[0] == "study":
            assert " 0 tasks computed" in out, out
    assert templates == 2   # `scan ... --resume` and the --scheduler line
    for name in ("scan.ply", "scan_column.png", "scan_hist.png", "nf_power.npz", "scan.mcap",
                 "mean.mcap", "profile.ply", "scan.las", "replay.ply", "corr.png"):
        assert (tmp_path / name).is_file(), name


def test_readme_study_resume_line_uses_the_grid_of_the_line_before():
    study = [ln for ln in readme_lines() if ln.startswith("cdma-lidar study run tradeoff")]
    first, resume = study[0].split(), study[1].split()
    assert "--resume" in resume and ("--quick" in first) == ("--quick" in resume)


def test_docs_multi_user_figures_are_the_presets():
    doc = tomllib.loads((ROOT / "scene" / "presets" / "multi-user.toml").read_text())
    inst = doc["instrument"]
    n = inst["uid_bits"]
    users = ", ".join(f"{u['uid']} = `{uid_to_str(u['uid'], n)}` at "
                      f"{u['distance_m']:g} m"
                      for u in inst["other_users"])
    want = (f"multi-user (our UID {inst['uid']} = `{uid_to_str(inst['uid'], n)}`, wall at "
            f"{doc['objects'][0]['position_m'][0]:g} m; users {users} one way")
    host = " ".join((ROOT / "docs" / "host.md").read_text(encoding="utf-8").split())
    assert want in host, want
    assert f"UID {inst['uid']} = {uid_to_str(inst['uid'], n)}" in doc["description"]


def test_docs_ring_0_is_the_top_beam_with_the_angles_of_paper_scene1():
    import cdma_lidar.virtual  # noqa: F401 - registers virtual://
    from cdma_lidar.host.connection import connect

    with connect("virtual://paper-scene1") as dev:
        el, az = dev.beam_angles_deg()
    mid = el.shape[1] // 2
    assert el[0, mid] > 0 > el[-1, mid] and az[20, 0] > 0 > az[20, -1]
    host = " ".join((ROOT / "docs" / "host.md").read_text(encoding="utf-8").split())
    assert (f"elevation {el[0, mid]:+.2f} deg on paper-scene1, the last ring "
            f"{el[-1, mid]:.2f} deg") in host
    assert f"azimuth {az[20, 0]:+.0f} deg on paper-scene1" in host


@pytest.mark.slow
def test_docs_host_python_api_snippet_runs(tmp_path, monkeypatch, capsys):
    text = (ROOT / "docs" / "host.md").read_text(encoding="utf-8")
    code = re.search(r"## Python API\n.*?```python\n(.*?)```", text, flags=re.S).group(1)
    monkeypatch.chdir(tmp_path)
    exec(compile(code, "docs/host.md", "exec"), {})
    assert (tmp_path / "scene.ply").is_file() and (tmp_path / "four.mcap").is_file()
    assert capsys.readouterr().out.count("valid pixels") == 4


def test_scene_docs_preset_table_is_generated_from_the_presets(capsys):
    """docs/scene.md's preset table is `scene list --markdown`, and a preset's description
    names its UIDs the way `codes uid` does (period 0 first)."""
    code, out, err = run_cli(capsys, "scene", "list", "--markdown")
    assert code == 0, err
    text = (ROOT / "docs" / "scene.md").read_text(encoding="utf-8")
    block = re.search(r"<!-- generated:presets[^\n]*-->\n(.*?)<!-- end:presets -->", text,
                      flags=re.S).group(1)
    assert block == out
    for path in sorted((ROOT / "scene" / "presets").glob("*.toml")):
        doc = tomllib.loads(path.read_text())
        inst = doc["instrument"]
        n = inst.get("uid_bits", 1)
        if n <= 1:
            continue
        assert f"UID {inst['uid']} = {uid_to_str(inst['uid'], n)}, period 0 first" in \
            doc["description"]
        others = ", ".join(uid_to_str(u["uid"], n) for u in inst.get("other_users", []))
        assert f"(UIDs {others})" in doc["description"]


def test_device_and_host_agree_on_the_default_key_file(monkeypatch, tmp_path):
    """One function gives the path (cdma_lidar.paths): the host's and the device's."""
    from cdma_lidar import paths
    from cdma_lidar.host import connection
    from cdma_lidar.virtual import cli

    assert connection.default_key_file is cli.default_key_file is paths.default_key_file
    monkeypatch.setenv("XDG_CONFIG_HOME", str(tmp_path))
    assert paths.default_key_file() == tmp_path / "cdma-lidar" / "device.key"
    monkeypatch.delenv("XDG_CONFIG_HOME")
    monkeypatch.setenv("HOME", str(tmp_path))
    assert paths.default_key_file() == tmp_path / ".config" / "cdma-lidar" / "device.key"
