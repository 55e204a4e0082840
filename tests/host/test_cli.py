"""The host commands end to end, and their one-line errors (exit status 2)."""

from __future__ import annotations

import math
import os
import re
import tomllib

import numpy as np
import pytest
from cli_helpers import one_line_error as _one_line_error
from cli_helpers import run_cli as _run


def test_info_on_virtual_device(capsys):
    code, out, _ = _run(capsys, "info", "--port", "virtual://flat-wall?seed=1")
    assert code == 0
    assert "VIRT-flat-wall-1" in out and "channels    40" in out
    assert "samples_per_chip" in out


def test_demo_summary_and_files(capsys, tmp_path):
    code, out, _ = _run(capsys, "demo", "--out", str(tmp_path), "--no-progress")
    assert code == 0
    valid = float(re.search(r"([\d.]+) % of object pixels", out).group(1))
    assert valid >= 95.0
    assert ", 0 valid without an object" in out
    m = re.search(r"range error   median ([\d.]+) cm.*eq. 27 precision ([\d.]+) cm", out)
    assert float(m.group(1)) <= float(m.group(2))
    names = sorted(p.name for p in tmp_path.iterdir())
    assert names == ["calibration.toml", "paper-scene1.ply", "paper-scene1_3d.png",
                     "paper-scene1_column.png", "paper-scene1_depth.png",
                     "paper-scene1_hist.png", "paper-scene1_snr.png"]


def test_calibrate_then_scan_with_calibration(capsys, tmp_path):
    cal = tmp_path / "cal.toml"
    code, out, _ = _run(capsys, "calibrate", "--port", "virtual://multi-user?seed=1",
                        "--target-distance", "0.5", "--shots", "8", "--out", str(cal))
    assert code == 0 and "offset" in out
    doc = tomllib.loads(cal.read_text())
    assert doc["device"]["serial"] == "VIRT-multi-user-1" and doc["shots"] == 8
    code, out, _ = _run(capsys, "scan", "--port", "virtual://multi-user?seed=1", "--out",
                        str(tmp_path / "mu.pcd"), "--calibration", str(cal), "--no-progress",
                        "--set", "peaks=4")
    assert code == 0 and "pixels valid" in out and (tmp_path / "mu.pcd").is_file()
    # The same file on another device is refused with a clear message.
    line = _one_line_error(capsys, "scan", "--port", "virtual://multi-user?seed=2", "--out",
                           str(tmp_path / "x.ply"), "--calibration", str(cal), "--no-progress")
    assert "another device" in line and "calibrate" in line


def test_unknown_port(capsys, tmp_path):
    line = _one_line_error(capsys, "scan", "--port", "/dev/no-such-port", "--out",
                           str(tmp_path / "a.ply"))
    assert "cannot open port" in line
    line = _one_line_error(capsys, "info", "--port", "nope://thing")
    assert "nope" in line


def test_silent_device(capsys):
    master, slave = os.openpty()
    try:
        line = _one_line_error(capsys, "info", "--port", os.ttyname(slave), "--timeout", "0.1")
    finally:
        os.close(master)
        os.close(slave)
    assert "no answer" in line and "check" in line


def test_impossible_configuration(capsys, tmp_path):
    line = _one_line_error(capsys, "scan", "--port", "virtual://flat-wall", "--out",
                           str(tmp_path / "a.ply"), "--set", "samples_per_chip=99")
    assert "samples_per_chip" in line
    line = _one_line_error(capsys, "scan", "--port", "virtual://flat-wall", "--out",
                           str(tmp_path / "a.ply"), "--frames", "0")
    assert "frames" in line


@pytest.mark.parametrize(("out", "words"), [
    ("/no/such/folder/a.ply", "does not exist"),
    ("{tmp}/a.xyz", "must end in one of"),
])
def test_bad_output_path(capsys, tmp_path, out, words):
    line = _one_line_error(capsys, "scan", "--port", "virtual://flat-wall", "--out",
                           out.format(tmp=tmp_path))
    assert words in line


def test_unwritable_output_folder(capsys, tmp_path):
    ro = tmp_path / "ro"
    ro.mkdir()
    ro.chmod(0o500)
    try:
        if os.access(ro, os.W_OK):
            pytest.skip("running as a user who can write anywhere")
        line = _one_line_error(capsys, "scan", "--port", "virtual://flat-wall", "--out",
                               str(ro / "a.ply"))
        assert "not writable" in line
    finally:
        ro.chmod(0o700)


@pytest.mark.skipif(not os.path.isdir("/proc/self"), reason="needs Linux /proc")
@pytest.mark.parametrize("argv", [
    ("scan", "--port", "virtual://flat-wall", "--out", "/proc/a.ply"),
    ("scan", "--port", "virtual://flat-wall", "--out", "{tmp}/a.ply",
     "--save-ghost-map", "/proc/g.toml"),
    ("calibrate", "--port", "virtual://calibration", "--target-distance", "0.75",
     "--out", "/proc/c.toml"),
    ("demo", "--out", "/proc/demo"),
    ("demo", "--out", "/proc"),
])
def test_output_folder_that_refuses_files(capsys, tmp_path, argv):
    """/proc refuses new files even to root, whom os.access always lets through."""
    argv = tuple(a.format(tmp=tmp_path) for a in argv)
    line = _one_line_error(capsys, *argv)
    assert "/proc" in line and ("cannot write" in line or "cannot create" in line)
    assert not list(tmp_path.iterdir())  # nothing scanned, nothing written


def test_resume_without_partial_scan(capsys, tmp_path):
    line = _one_line_error(capsys, "scan", "--port", "virtual://flat-wall", "--out",
                           str(tmp_path / "a.ply"), "--resume")
    assert "nothing to resume" in line


def test_calibrate_bad_arguments(capsys, tmp_path):
    code, _, err = _run(capsys, "calibrate", "--port", "virtual://calibration",
                        "--target-distance", "-1", "--out", str(tmp_path / "c.toml"))
    assert code == 2 and "target-distance" in err
    line = _one_line_error(capsys, "calibrate", "--port", "virtual://calibration",
                           "--target-distance", "0.75", "--out", str(tmp_path / "c.txt"))
    assert ".toml" in line


def test_scan_over_a_pty(capsys, tmp_path):
    import subprocess
    import sys

    proc = subprocess.Popen([sys.executable, "-m", "cdma_lidar.cli", "device", "--scene",
                             "multi-user", "--seed", "1", "--pty"],
                            stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True)
    try:
        path = proc.stdout.readline().strip()
        assert path.startswith("/dev/"), path
        code, out, _ = _run(capsys, "scan", "--port", path, "--out", str(tmp_path / "p.ply"),
                            "--no-progress", "--set", "peaks=4")
        assert code == 0
        assert "320 of 320 pixels valid" in out and "UID 0" in out
    finally:
        proc.terminate()
        proc.wait(timeout=10)


def test_calibration_on_a_noisy_device_is_refused(capsys, tmp_path):
    out = tmp_path / "c.toml"
    line = _one_line_error(capsys, "calibrate", "--port",
                           "virtual://calibration?seed=1&instrument.noise_rms_v=0.5",
                           "--target-distance", "0.75", "--out", str(out),
                           "--snr-threshold", "8")
    assert "too wide" in line and not out.exists()


def test_scan_interpolate_and_min_support(capsys, tmp_path):
    from cdma_lidar.host.cloud_formats.npz import read as read_npz

    out = tmp_path / "i.npz"
    code, text, _ = _run(capsys, "scan", "--port", "virtual://paper-scene1?seed=2", "--out",
                         str(out), "--no-progress", "--snr-threshold", "20", "--interpolate",
                         "--min-support", "2")
    assert code == 0, text
    cloud = read_npz(out)
    filled = cloud.flags == 1
    assert filled.sum() >= 20
    assert np.all(np.isfinite(cloud.x[filled]))
    assert np.all(np.isnan(cloud.x[(cloud.flags & 2) != 0]))
    line = _one_line_error(capsys, "scan", "--port", "virtual://flat-wall", "--out",
                           str(tmp_path / "a.ply"), "--min-support", "9")
    assert "min_support must be from 0 to 8" in line


def test_las_without_laspy_is_refused_before_scanning(capsys, tmp_path, monkeypatch):
    import importlib.util

    real = importlib.util.find_spec
    monkeypatch.setattr(importlib.util, "find_spec",
                        lambda name, *a: None if name == "laspy" else real(name, *a))
    line = _one_line_error(capsys, "scan", "--port", "/dev/no-such-port", "--out",
                           str(tmp_path / "a.las"))
    assert "pip install 'cdma-lidar[las]'" in line  # not "cannot open port": checked first


def test_same_seed_and_frame_id_same_cloud_bytes(capsys, tmp_path):
    def scan(name: str, frame_id: str) -> bytes:
        out = tmp_path / name
        code, text, _ = _run(capsys, "scan", "--port", "virtual://multi-user?seed=3", "--out",
                             str(out), "--no-progress", "--frame-id", frame_id)
        assert code == 0, text
        return out.read_bytes()

    first = scan("a.ply", "41")
    assert scan("b.ply", "41") == first
    assert scan("c.ply", "42") != first  # another frame id: other noise
    line = _one_line_error(capsys, "scan", "--port", "virtual://multi-user", "--out",
                           str(tmp_path / "d.ply"), "--frame-id", "-1")
    assert "--frame-id must be from 0" in line


def test_scan_over_a_noisy_serial_line_gives_the_clean_cloud(capsys, tmp_path):
    """The CLI at a bit error rate of 1e-3 (a UART's pace, errors both ways): HELLO, the
    power matrix (cut into short POWER_SETs) and the scan all get through, and the
    cloud is byte for byte the clean line's."""
    def scan(name: str, line: str) -> bytes:
        out = tmp_path / name
        code, _, err = _run(capsys, "scan", "--port", f"virtual://flat-wall?seed=2{line}",
                               "--out", str(out), "--no-progress", "--frame-id", "8",
                               "--timeout", "2")
        assert code == 0, err
        return out.read_bytes()

    clean = scan("clean.ply", "")
    assert scan("noisy.ply", "&line_error_rate=1e-3&line_seed=4&line_baud=4000000") == clean


def test_ctrl_c_leaves_a_partial_scan_that_resume_finishes(capsys, tmp_path, monkeypatch):
    from cdma_lidar.host.frame import FrameData
    from cdma_lidar.host.scan import state_path

    port = "virtual://multi-user?seed=2"
    whole = tmp_path / "whole.ply"
    code, _, _ = _run(capsys, "scan", "--port", port, "--out", str(whole), "--no-progress",
                      "--frame-id", "5")
    assert code == 0
    out = tmp_path / "cut.ply"
    real = FrameData.set_column

    def interrupt_at_3(self, index, result, angle_deg=None):
        if index == 3:
            raise KeyboardInterrupt
        real(self, index, result, angle_deg)

    monkeypatch.setattr(FrameData, "set_column", interrupt_at_3)
    code, _, err = _run(capsys, "scan", "--port", port, "--out", str(out), "--no-progress",
                        "--frame-id", "5")
    assert code == 130 and "--resume" in err
    assert state_path(out).is_file() and not out.exists()
    monkeypatch.setattr(FrameData, "set_column", real)
    code, text, _ = _run(capsys, "scan", "--port", port, "--out", str(out), "--no-progress",
                         "--resume")
    assert code == 0 and "scanned 5 columns" in text  # 3..7, not 0..2 again
    assert not state_path(out).exists()
    import plyfile  # in the test extra

    # Same points; only the time of the columns measured after the resume differs (the
    # device clock of a new session), so t is compared on the columns of the first run.
    a, b = plyfile.PlyData.read(str(out))["vertex"], plyfile.PlyData.read(str(whole))["vertex"]
    for prop in a.properties:
        if prop.name != "t":
            np.testing.assert_array_equal(a[prop.name], b[prop.name], err_msg=prop.name)
    first = a["column"] < 3
    np.testing.assert_array_equal(a["t"][first], b["t"][first])


def test_scan_in_calibration_mode_says_what_to_do(capsys, tmp_path):
    line = _one_line_error(capsys, "scan", "--port", "virtual://multi-user", "--out",
                           str(tmp_path / "a.ply"), "--no-progress", "--set", "mode=calibration")
    assert "calibration mode" in line and "--set mode=ranging" in line
    assert not list(tmp_path.iterdir())


def test_a_capped_device_is_reported_and_calibrated_at_the_power_it_scanned(capsys, tmp_path):
    """flat-wall with a 20 mW column cap: 40 pixels at the default quarter of the 10 mW
    maximum would need 100 mW, so the scan runs at 0.05; the near-far cap line and the
    intensity gain use that level, not the requested 0.25."""
    from cdma_lidar.host.cloud_formats.npz import read as read_npz

    capped = "instrument.total_power_cap_w=0.02&power=0.0005&seed=1"
    level = math.floor(0.02e6 * 65535 / (40 * 10_000)) / 65535   # default_power_level
    code, text, _ = _run(capsys, "scan", "--port", f"virtual://flat-wall?{capped}", "--out",
                         str(tmp_path / "n.npz"), "--near-far", "--frames", "2",
                         "--no-progress")
    assert code == 0
    cap = float(re.search(r"\(cap (\S+) x the per-pixel maximum\)", text).group(1))
    assert cap == pytest.approx(40 * level, rel=1e-5)
    cal = tmp_path / "cal.toml"
    assert _run(capsys, "calibrate", "--port", f"virtual://flat-wall?{capped}",
                "--target-distance", "0.5", "--out", str(cal))[0] == 0
    assert _run(capsys, "scan", "--port", f"virtual://flat-wall?{capped}", "--out",
                str(tmp_path / "w.npz"), "--calibration", str(cal), "--calibrate-intensity",
                "0.5", "--no-progress")[0] == 0
    out = tmp_path / "x.npz"
    assert _run(capsys, "scan", "--port", f"virtual://flat-wall?reflectivity=0.2&{capped}",
                "--out", str(out), "--calibration", str(cal), "--no-progress")[0] == 0
    cloud = read_npz(out)
    # (about 1.1, 0.25 / 0.05 times too much, with the requested level in the gain)
    assert np.median(cloud.intensity[cloud.flags == 0]) == pytest.approx(0.2, rel=0.25)
