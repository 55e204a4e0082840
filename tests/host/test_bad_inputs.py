"""Every bad input of issues 26 and 43 ends in one line on stderr and exit status 2.

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
from cdma_lidar.host.cloud_formats import write, write_frames
from cdma_lidar.host.connection import connect
from cdma_lidar.host.pointcloud import POINT_FIELDS, PointCloud, assemble
from cdma_lidar.host.ranging import RangeImage
from cdma_lidar.host.scan import ScanOptions, run_scan, state_path
from cdma_lidar.host.uid_filter import ForeignReturns
from cdma_lidar.optics.grating import GratingGeometry


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
    # issue 43: files cut short at a record boundary, read by convert and by a replay
    **{f"{ext} cut short, {how}": (
        (lambda t, ext=ext, how=how: (
            ("convert", _cut(t, ext), str(t / "out.npz")) if how == "converted" else
            (*_replay(_cut(t, ext)), "--out", str(t / "out.npz")))),
        ["cut short", "header says"])
       for ext in (".ply", ".pcd", ".las") for how in ("converted", "replayed")},
    ".ply with bytes after its vertices": (lambda t: ("convert", _cut(t, ".ply", extra=b"x"),
                                                      str(t / "o.npz")), ["padded"]),
    # windows checked against the device's gate (flat-wall: lags 0 to 127)
    "ghost window beyond the gate": (lambda t: (*SCAN, "--out", str(t / "a.ply"),
                                                "--ghost-window", "500:10"),
                                     ["ghost window 500:10", "outside", "lags 0 to 127"]),
    "ghost window covering everything": (lambda t: (*SCAN, "--out", str(t / "a.ply"),
                                                    "--ghost-window", "0:100000"),
                                         ["cover the whole gate", "every pixel"]),
    "ghost windows covering the gate together": (
        lambda t: (*SCAN, "--out", str(t / "a.ply"), "--ghost-window", "0:64",
                   "--ghost-window", "64:64"), ["cover the whole gate"]),
    "ghost map covering everything": (lambda t: (*SCAN, "--out", str(t / "a.ply"),
                                                 "--ghost-map", _toml(t, "windows = [[0, 9000]]")),
                                      ["cover the whole gate"]),
    # calibrations that cannot be right
    "calibration target beyond the measured target": (
        lambda t: ("calibrate", "--port", "virtual://flat-wall", "--target-distance", "7",
                   "--out", str(t / "c.toml")),
        ["--target-distance 7 m", "measured at 6.", "negative"]),
    "calibration with a negative spread": (
        lambda t: (*SCAN, "--out", str(t / "a.ply"), "--calibration",
                   _toml(t, CAL.format(offset=5.6, spread=-0.01))),
        ["spread_m must be >= 0 m", "-0.01"]),
    "calibration with a NaN offset": (
        lambda t: (*SCAN, "--out", str(t / "a.ply"), "--calibration",
                   _toml(t, CAL.format(offset="nan", spread=0.01))),
        ["offset_m must be a finite number"]),
    # replays that cannot give what is asked
    "--frames 10 of a 2-frame replay": (
        lambda t: (*_replay(_two_frames(t)), "--frames", "10", "--out", str(t / "o.ply")),
        ["--frames 10", "(2)"]),
    "replay:// for info": (lambda t: ("info", "--port", f"replay://{_two_frames(t)}"),
                           ["is a recording", "info needs a device"]),
    "replay:// for calibrate": (lambda t: ("calibrate", "--port", f"replay://{_two_frames(t)}",
                                           "--target-distance", "1", "--out",
                                           str(t / "c.toml")),
                                ["is a recording", "calibrate needs a device"]),
    "replay:// for capture": (lambda t: ("capture", "--port", f"replay://{_two_frames(t)}",
                                         "--kind", "raw", "--column", "0", "--out",
                                         str(t / "c.npz")),
                              ["is a recording", "capture needs a device"]),
    # busy ports and missing displays
    "view on a taken web port (another view)": (
        lambda t: (*VIEW, "--web", "--web-port", str(_taken()), "--grpc-port",
                   str(_closed_port())), ["--web-port", "is taken", "another view"]),
    "view on a taken --grpc-port": (
        lambda t: (*VIEW, "--web", "--grpc-port", str(_taken()), "--web-port",
                   str(_closed_port())), ["--grpc-port", "is taken"]),
    "view --spawn without a display": (lambda t: (*VIEW, "--spawn"),
                                       ["--spawn needs a display", "--web"]),
    "view --steer with --out": (lambda t: (*VIEW, "--steer", "--out", str(t / "a.ply")),
                                ["--out needs a finished scan", "--steer"]),
    "view --bind of a name": (lambda t: (*VIEW, "--save", str(t / "v.rrd"), "--bind", "home"),
                              ["--bind must be an IP address"]),
    "device on a busy port": (lambda t: ("device", "--scene", "flat-wall", "--tcp",
                                         f"127.0.0.1:{_taken()}", "--insecure"),
                              ["--tcp", "cannot listen", "choose another port"]),
    "tiny --timeout": (lambda t: ("info", "--port", "virtual://flat-wall", "--timeout",
                                  "0.001"), ["--timeout", "from 0.05 to 3600 s"]),
}

#: Sockets listening while a case runs (closed after each test).
_HELD: list[socket.socket] = []


def _taken() -> int:
    """A loopback port something listens on (until the test ends)."""
    s = socket.socket()
    s.bind(("127.0.0.1", 0))
    s.listen()
    _HELD.append(s)
    return int(s.getsockname()[1])


def _toml(tmp: Path, text: str) -> str:
    p = tmp / f"f{len(list(tmp.iterdir()))}.toml"
    p.write_text(text + "\n")
    return str(p)


def _cloud(seed: int = 1) -> PointCloud:
    """A small 6 x 8 cloud (no pixel rejected), stamped."""
    rng = np.random.default_rng(seed)
    r = rng.uniform(1.0, 9.0, (6, 8))
    empty = np.zeros(0, np.int64)
    image = RangeImage(range_m=r, lag=r / 0.6, snr_xc_db=rng.uniform(20, 40, r.shape),
                       peak=rng.integers(1, 5000, r.shape), flags=np.zeros(r.shape, np.uint8),
                       foreign=ForeignReturns(empty, empty, empty, empty, empty, empty,
                                              np.zeros(0)))
    return assemble(image, GratingGeometry(), np.linspace(1550e-9, 1560e-9, 6),
                    np.linspace(-2, 2, 8), stamp_unix_s=1.7e9 + seed)


def _cut(tmp: Path, ext: str, extra: bytes = b"") -> str:
    """A file of ``ext`` with the last half of its 48 points cut off at a record boundary
    (or with ``extra`` bytes after them)."""
    path = tmp / f"cut{ext}"
    write(_cloud(), path)
    raw = path.read_bytes()
    if ext == ".las":
        import laspy

        with laspy.open(str(path)) as fh:
            size = fh.header.point_format.size
            end = fh.header.offset_to_point_data + fh.header.point_count * size
    else:
        size, end = np.dtype(list(POINT_FIELDS)).itemsize, len(raw)
    path.write_bytes(raw[:end] + extra if extra else raw[:end - 24 * size])
    return str(path)


def _two_frames(tmp: Path) -> str:
    path = tmp / "two.mcap"
    write_frames([_cloud(1), _cloud(2)], path)
    return str(path)


CAL = ("offset_m = {offset}\nspread_m = {spread}\ntarget_distance_m = 0.5\nshots = 20\n"
       "samples = 800")
VIEW = ("view", "--port", "virtual://flat-wall?seed=1", "--no-progress")


def _replay(path: str) -> tuple[str, ...]:
    return ("scan", "--port", f"replay://{path}", "--no-progress")


def _file(tmp: Path) -> Path:
    p = tmp / "plain-file"
    p.write_text("x")
    return p


def _partial(tmp: Path) -> str:
    out = tmp / "a.ply"
    state_path(out).write_bytes(b"a partial scan")
    return str(out)


@pytest.fixture(autouse=True)
def _no_display_and_no_held_sockets(monkeypatch):
    """No display (``--spawn`` is refused for it); listening sockets closed afterwards."""
    monkeypatch.delenv("DISPLAY", raising=False)
    monkeypatch.delenv("WAYLAND_DISPLAY", raising=False)
    yield
    while _HELD:
        _HELD.pop().close()


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
