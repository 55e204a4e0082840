"""Atomic writes and the writability probe shared by every command that writes a file."""

from __future__ import annotations

import os
import stat

import pytest

from cdma_lidar.errors import ConfigError
from cdma_lidar.fileio import atomic_open, atomic_write_bytes, atomic_write_text, check_writable


def test_atomic_write_replaces_whole_file(tmp_path):
    target = tmp_path / "cloud.ply"
    atomic_write_bytes(target, b"old contents")
    atomic_write_text(target, "new")
    assert target.read_text() == "new"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["cloud.ply"]


def test_failure_inside_leaves_old_file_and_no_temporary(tmp_path):
    target = tmp_path / "cal.toml"
    target.write_text("offset_m = 1.0\n")
    with pytest.raises(RuntimeError), atomic_open(target, "w") as fh:
        fh.write("half a fi")
        raise RuntimeError("interrupted")
    assert target.read_text() == "offset_m = 1.0\n"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["cal.toml"]


def test_files_get_the_permissions_open_would_give(tmp_path):
    mask = os.umask(0o022)
    os.umask(mask)
    target = tmp_path / "x.npz"
    atomic_write_bytes(target, b"x")
    assert stat.S_IMODE(target.stat().st_mode) == 0o666 & ~mask


def test_check_writable_names_the_option(tmp_path):
    assert check_writable(tmp_path / "ok.ply") == tmp_path / "ok.ply"
    with pytest.raises(ConfigError, match=r"--out: folder .* does not exist") as exc:
        check_writable(tmp_path / "missing" / "x.ply")
    assert exc.value.field == "out"
    with pytest.raises(ConfigError, match="is a folder"):
        check_writable(tmp_path, "--calibration")
    assert not list(tmp_path.glob("*.probe"))


@pytest.mark.skipif(not os.path.isdir("/proc/self"), reason="needs Linux /proc")
def test_check_writable_probes_instead_of_trusting_os_access():
    # os.access says yes to root for /proc; creating a file there fails for everyone
    with pytest.raises(ConfigError, match="cannot write in folder '/proc'"):
        check_writable("/proc/cloud.ply")
