"""Every bad input of issue 26 ends in one line on stderr and exit status 2, before work.

Each case builds its bad file or path in ``tmp_path`` and names the words the line must
hold (the field and what is allowed), so a traceback or a silent wrong value fails.
"""

from __future__ import annotations

import os
import socket
from pathlib import Path

import numpy as np
import pytest
from cli_helpers import one_line_error

import cdma_lidar.virtual  # noqa: F401 - registers virtual:// with pyserial
from cdma_lidar.errors import ScanAborted
from cdma_lidar.host.connection import connect
from cdma_lidar.host.scan import ScanOptions, run_scan, state_path


def _not_utf8(tmp: Path) -> str:
    p = tmp / "latin1.toml"
    p.write_bytes('name = "caf\xe9"\n'.encode("latin-1"))
    return str(p)


def _loop(tmp: Path) -> str:
    (tmp / "a.toml").symlink_to(tmp / "b.toml")
    (tmp / "b.toml").symlink_to(tmp / "a.toml")
    return str(tmp / "a.toml")


def _closed_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


SCAN = ("scan", "--port", "virtual://flat-wall?seed=1", "--no-progress")

CASES = {
    "calibration is a folder": (lambda t: (*SCAN, "--out", str(t / "a.ply"),
                                           "--calibration", str(t)),
                                ["calibration", "cannot be read"]),
    "calibration is a symlink loop": (lambda t: (*SCAN, "--out", str(t / "a.ply"),
                                                 "--calibration", _loop(t)),
                                      ["calibration", "cannot be read"]),
    "ghost map is a folder": (lambda t: (*SCAN, "--out", str(t / "a.ply"), "--ghost-map",
                                         str(t)), ["ghost map", "cannot be read"]),
    "profile is a folder": (lambda t: (*SCAN, "--out", str(t / "a.ply"), "--config", str(t)),
                            ["--config", "not a readable TOML"]),
    "scene truth not UTF-8": (lambda t: ("scene", "truth", _not_utf8(t), "--out",
                                         str(t / "t.npz")), ["not UTF-8"]),
    "scene show not UTF-8": (lambda t: ("scene", "show", _not_utf8(t)), ["not UTF-8"]),
    "device scene not UTF-8": (lambda t: ("device", "--scene", _not_utf8(t), "--tcp",
                                          "127.0.0.1:1", "--insecure"), ["not UTF-8"]),
    "hdl vectors into a file's child": (lambda t: ("hdl", "vectors", "--out",
                                                   str(_file(t) / "vec")),
                                        ["--out", "cannot create"]),
    "socket without a port": (lambda t: ("info", "--port", "socket://localhost"),
                              ["socket://HOST:PORT"]),
    "socket port 99999": (lambda t: ("info", "--port", "socket://localhost:99999"),
                          ["1 to 65535", "99999"]),
    "unreachable scheduler": (lambda t: ("study", "run", "detection", "--out", str(t / "s"),
                                         "--quick", "--scheduler",
                                         f"tcp://127.0.0.1:{_closed_port()}"),
                              ["cannot reach the Dask scheduler"]),
    "calibration target 1e12 m": (lambda t: ("calibrate", "--port", "virtual://flat-wall",
                                             "--target-distance", "1e12", "--out",
                                             str(t / "c.toml")),
                                  ["--target-distance", "1000 m"]),
    "power cap 1e9": (lambda t: (*SCAN, "--out", str(t / "a.ply"), "--frames", "2",
                                 "--near-far", "--power-cap", "1e9"),
                      ["power_cap", "at most 40"]),
    "timeout of a day": (lambda t: ("info", "--port", "virtual://flat-wall", "--timeout",
                                    "86400"), ["--timeout", "3600 s"]),
    "partial scan in the way": (lambda t: (*SCAN, "--out", _partial(t)),
                                ["interrupted scan", "--resume", "--force"]),
}


def _file(tmp: Path) -> Path:
    p = tmp / "plain-file"
    p.write_text("x")
    return p


def _partial(tmp: Path) -> str:
    out = tmp / "a.ply"
    state_path(out).write_bytes(b"a partial scan")
    return str(out)


@pytest.mark.parametrize("case", CASES, ids=list(CASES))
def test_bad_input_is_one_line_exit_2(capsys, tmp_path, case):
    build, words = CASES[case]
    line = one_line_error(capsys, *build(tmp_path))
    assert "Traceback" not in line
    for word in words:
        assert word in line, line
    if case == "partial scan in the way":  # the partial scan is still there, untouched
        assert state_path(tmp_path / "a.ply").read_bytes() == b"a partial scan"


def test_force_overwrites_a_partial_scan(capsys, tmp_path):
    from cli_helpers import run_cli

    out = _partial(tmp_path)
    code, _, err = run_cli(capsys, *SCAN, "--out", out, "--force")
    assert code == 0, err
    assert Path(out).is_file() and not state_path(out).exists()


def test_early_scan_end_saves_a_partial_that_resume_finishes(tmp_path):
    """The device ends the frame early (SCAN_ABORT mid-frame): the columns delivered so far
    are kept in the partial file and --resume scans only the rest."""
    out = tmp_path / "early.npz"
    with connect("virtual://paper-scene1?seed=2") as dev:
        def stop(_frame: int, column: int) -> None:
            if column == 5:
                dev.link.abort()

        with pytest.raises(ScanAborted, match="--resume"):
            run_scan(dev, out, progress=False, on_column=stop, frame_id=3)
        assert state_path(out).is_file() and not out.exists()
        with np.load(state_path(out)) as z:
            done = int(z["frame_done"].sum())
        assert 6 <= done < dev.columns
        res = run_scan(dev, out, resume=True, progress=False)
        assert res.columns_scanned == dev.columns - done
        clean = run_scan(dev, tmp_path / "clean.npz", progress=False, frame_id=3)
    assert out.is_file() and not state_path(out).exists()
    np.testing.assert_array_equal(res.image.flags, clean.image.flags)


def test_options_refuse_a_power_cap_above_every_pixel_at_maximum(tmp_path):
    with connect("virtual://flat-wall?seed=1") as dev, pytest.raises(ValueError, match="40"):
        run_scan(dev, tmp_path / "a.ply", ScanOptions(frames=2, near_far=True, power_cap=41.0),
                 progress=False)
    assert not os.listdir(tmp_path)
