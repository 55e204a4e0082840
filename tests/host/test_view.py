"""The live viewer as a person uses it: ``cdma-lidar view`` headless, its recording read back.

The scan runs on the virtual device with ``--save FILE.rrd``; rerun's own reader
(``rerun.chunk.RrdReader``) then gives every logged entity per frame, which must hold
exactly the frames the scan produced (same points, same power matrices). ``--web``
serves rerun's web viewer from the command's process (checked over HTTP, then ended with
Ctrl-C), and rerun's headless viewer renders the recording to a screenshot.
"""

from __future__ import annotations

import ipaddress
import json
import os
import signal
import socket
import subprocess
import sys
import urllib.request
from pathlib import Path

import numpy as np
import pytest
from cli_helpers import one_line_error, run_cli

rr = pytest.importorskip("rerun", reason="rerun-sdk is in the test extra")
from rerun.chunk import RrdReader  # noqa: E402  (after the skip: only with rerun)

from cdma_lidar.host.view import ENTITIES  # noqa: E402

URL = "virtual://near-far?seed=3"


def recorded(path: Path) -> dict[str, dict[int, dict]]:
    """{entity: {frame: {column: value}}} of every per-frame row in an .rrd file."""
    out: dict[str, dict[int, dict]] = {}
    for chunk in RrdReader(path).stream():
        if chunk.is_static:
            continue
        batch = chunk.to_record_batch()
        batch = batch.drop_columns([n for n in batch.schema.names if "time" in n])
        for row in batch.to_pylist():
            out.setdefault(chunk.entity_path.lstrip("/"), {})[row["frame"]] = row
    return out


@pytest.fixture(scope="module")
def near_far_view(tmp_path_factory):
    """`view` of three near-far frames saved to an .rrd, and the same scan's npz."""
    folder = tmp_path_factory.mktemp("view")
    rrd, npz = folder / "nf.rrd", folder / "nf.npz"
    proc = subprocess.run(
        [sys.executable, "-m", "cdma_lidar.cli", "view", "--port", URL, "--frames", "3",
         "--near-far", "--frame-id", "5", "--save", str(rrd), "--out", str(npz),
         "--no-progress", "--color-by", "snr"],
        capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr
    return rrd, npz, proc.stdout


def test_view_help_exits_0(capsys) -> None:
    code, out, _ = run_cli(capsys, "view", "--help")
    assert code == 0 and "--save FILE.rrd" in out and "--near-far" in out


def test_every_frame_is_recorded_with_every_entity(near_far_view) -> None:
    rrd, _, stdout = near_far_view
    assert "viewed 3 frames" in stdout
    rec = recorded(rrd)
    assert set(rec) == set(ENTITIES)
    for entity in ENTITIES:
        assert sorted(rec[entity]) == [0, 1, 2], entity


def test_the_recorded_frames_are_the_scans(near_far_view) -> None:
    """The last frame's cloud in the recording is the one written to --out, point for point."""
    rrd, npz, _ = near_far_view
    rec = recorded(rrd)
    with np.load(npz) as z:
        x, y, zz, snr = z["x"], z["y"], z["z"], z["snr_xc"]
    ok = np.isfinite(x)
    got = np.array(rec["cloud"][2]["Points3D:positions"], dtype=np.float32)
    np.testing.assert_array_equal(got, np.stack([x[ok], y[ok], zz[ok]], 1).astype(np.float32))
    np.testing.assert_array_equal(rec["cloud"][2]["snr_xc_db"], snr[ok].astype(np.float32))
    tensor = rec["snr_xc"][2]["Tensor:data"][0]
    assert tensor["shape"] == list(snr.shape)


def test_the_power_matrix_is_the_control_variable(near_far_view) -> None:
    """Near-far moves power between pixels: frame 0 is uniform, later frames are not."""
    rec = recorded(near_far_view[0])
    powers = []
    for frame in range(3):
        tensor = rec["power"][frame]["Tensor:data"][0]
        shape = tensor["shape"]
        powers.append(np.array(tensor["buffer"], np.float32).reshape(shape))
    assert np.ptp(powers[0]) == 0 and np.ptp(powers[1]) > 0
    cap = powers[0].shape[0] * 0.25   # default cap: the starting column sum, K x 0.25
    assert all(p.sum(axis=0).max() <= cap * (1 + 1e-6) for p in powers)
    texts = [rec["log"][f]["TextLog:text"][0] for f in range(3)]
    assert texts[0].startswith("frame 0: ") and "% of pixels above 16 dB" in texts[0]
    valid = [rec["valid_percent"][f]["Scalars:scalars"][0] for f in range(3)]
    assert valid[1] > valid[0]   # the paper's point: power control lifts pixels over 16 dB


def test_view_without_out_writes_nothing_but_the_recording(tmp_path, capsys,
                                                           monkeypatch) -> None:
    monkeypatch.chdir(tmp_path)
    code, out, err = run_cli(capsys, "view", "--port", "virtual://flat-wall?seed=1",
                             "--save", "wall.rrd", "--no-progress", "--frame-id", "1")
    assert code == 0, err
    assert "wrote" not in out and sorted(p.name for p in tmp_path.iterdir()) == ["wall.rrd"]
    assert sorted(recorded(tmp_path / "wall.rrd")["cloud"]) == [0]


def test_bad_view_arguments_end_in_one_line(tmp_path, capsys) -> None:
    assert "--save must be an .rrd file" in one_line_error(
        capsys, "view", "--port", URL, "--save", str(tmp_path / "x.txt"))
    assert "need --out FILE" in one_line_error(capsys, "view", "--port", URL, "--save",
                                               str(tmp_path / "x.rrd"), "--pictures")
    assert "--out is required" in one_line_error(capsys, "scan", "--port", URL)


def test_view_without_rerun_names_the_extra(tmp_path, capsys, monkeypatch) -> None:
    monkeypatch.setitem(sys.modules, "rerun", None)   # what `import rerun` sees uninstalled
    line = one_line_error(capsys, "view", "--port", URL, "--save", str(tmp_path / "x.rrd"))
    assert line.endswith("the live viewer needs rerun-sdk: pip install 'cdma-lidar[view]'")


def listeners() -> dict[int, set[str]]:
    """{port: {local addresses}} of every listening TCP socket (IPv4 and IPv6) here."""
    out: dict[int, set[str]] = {}
    for name, size in (("/proc/net/tcp", 4), ("/proc/net/tcp6", 16)):
        for line in Path(name).read_text().splitlines()[1:]:
            local, state = line.split()[1], line.split()[3]
            if state != "0A":  # LISTEN
                continue
            addr, port = local.split(":")
            raw = bytes.fromhex(addr)
            # /proc prints each 32-bit word in host (little-endian) order
            ip = b"".join(raw[i:i + 4][::-1] for i in range(0, size, 4))
            out.setdefault(int(port, 16), set()).add(
                str(ipaddress.ip_address(ip)))
    return out


def test_listeners_sees_a_socket_on_every_interface() -> None:
    """The check above can fail: a socket on 0.0.0.0 shows as such."""
    with socket.socket() as s:
        s.bind(("0.0.0.0", 0))  # the case the check must catch
        s.listen()
        assert listeners()[s.getsockname()[1]] == {"0.0.0.0"}


def test_bind_reaches_the_viewer_commands() -> None:
    from cdma_lidar.host.view import ViewOptions

    wide = ViewOptions(web=True, spawn=True, bind="0.0.0.0")
    assert all(argv[argv.index("--bind") + 1] == "0.0.0.0" for argv in wide.viewer_commands())
    assert wide.grpc_urls()[0].startswith("rerun+http://127.0.0.1:")
    default = ViewOptions(web=True).viewer_commands()[0]
    assert default[default.index("--bind") + 1] == "127.0.0.1"


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


#: Python code that gives SIGINT Python's handler, as a terminal's Ctrl-C finds it: a test
#: run started in the background by a non-interactive shell (``make test &``) hands its
#: children SIGINT ignored, and the command under test would never see the signal.
_AS_FROM_A_TERMINAL = ("import runpy, signal\n"
                       "signal.signal(signal.SIGINT, signal.default_int_handler)\n")


def test_web_viewer_is_served_until_ctrl_c(tmp_path) -> None:
    web, grpc = _free_port(), _free_port()
    proc = subprocess.Popen(
        [sys.executable, "-c", _AS_FROM_A_TERMINAL + "runpy.run_module('cdma_lidar.cli', "
         "run_name='__main__')", "view", "--port", "virtual://flat-wall",
         "--web", "--web-port", str(web), "--grpc-port", str(grpc), "--no-progress"],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=tmp_path)
    try:
        lines = []
        for line in proc.stdout:   # the command says where to look, then scans and serves
            lines.append(line)
            if line.startswith("serving the web viewer"):
                break
        assert any(ln.startswith(f"web viewer: http://127.0.0.1:{web}/?url=") for ln in lines)
        # everything served listens on loopback only (issue 43: not 0.0.0.0)
        listening = listeners()
        assert listening.get(web) == {"127.0.0.1"} and listening.get(grpc) == {"127.0.0.1"}, \
            listening
        page = urllib.request.urlopen(f"http://127.0.0.1:{web}/", timeout=30).read()
        assert b"<html" in page.lower() and b"rerun" in page.lower()
        proc.send_signal(signal.SIGINT)
        assert proc.wait(timeout=60) == 0
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()


def _wait_ended_by(signal_code: str) -> subprocess.CompletedProcess:
    """Run wait_forever in a fresh interpreter (SIGINT's handler as from a terminal) while a
    second thread runs ``signal_code`` once the main thread is inside wait_forever (seen in
    its stack: no timing is assumed, however slowly the child starts); the child prints
    ``ended`` when the wait ends in KeyboardInterrupt."""
    code = (_AS_FROM_A_TERMINAL + "import os, signal, sys, threading, time\n"
            "from cdma_lidar.host.view import wait_forever\n"
            "main = threading.get_ident()\n"
            "def inside():\n"
            "    frame = sys._current_frames().get(main)\n"
            "    while frame is not None:\n"
            "        if frame.f_code is wait_forever.__code__:  # and past its set-up:\n"
            "            return signal.getsignal(signal.SIGTERM) is signal.default_int_handler\n"
            "        frame = frame.f_back\n"
            "    return False\n"
            "def hit():\n"
            "    while not inside():\n"
            "        time.sleep(0.01)\n"
            "    " + signal_code + "\n"
            "threading.Thread(target=hit, daemon=True).start()\n"
            "try:\n"
            "    wait_forever()\n"
            "except KeyboardInterrupt:\n"
            "    print('ended')\n")
    return subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                          timeout=120)


def test_ctrl_c_ends_the_wait_when_another_thread_takes_the_signal() -> None:
    """SIGINT handled on a thread other than the main one (the viewer runs many) still
    ends wait_forever: the main thread wakes from its sleep and raises KeyboardInterrupt."""
    proc = _wait_ended_by("signal.pthread_kill(threading.get_ident(), signal.SIGINT)")
    assert proc.stdout.strip() == "ended", proc.stderr[-2000:]


def test_sigterm_ends_the_wait_as_ctrl_c_does() -> None:
    """``kill`` (SIGTERM) ends a served viewer the way Ctrl-C does, so the recording is
    flushed: the one way to end a viewer started in the background with SIGINT ignored."""
    proc = _wait_ended_by("os.kill(os.getpid(), signal.SIGTERM)")
    assert proc.stdout.strip() == "ended", (proc.returncode, proc.stderr[-2000:])


def _renders_headless() -> bool:
    """Whether a software Vulkan driver (Debian's mesa-vulkan-drivers) is installed."""
    return any(Path("/usr/share/vulkan/icd.d").glob("lvp_icd*.json"))


@pytest.mark.skipif(not _renders_headless(), reason="needs mesa-vulkan-drivers (make sysdeps)")
def test_headless_viewer_screenshot_shows_the_scan(near_far_view, tmp_path) -> None:
    """rerun's own viewer, headless, draws the recording; the range panel is in colour."""
    from PIL import Image

    env = {**os.environ, "XDG_RUNTIME_DIR": str(tmp_path)}
    coloured = []
    for attempt in range(3):  # the headless viewer may shoot before a loaded machine drew
        shot = tmp_path / f"view-{attempt}.png"
        proc = subprocess.run(
            [sys.executable, "-m", "rerun", str(near_far_view[0]), "--headless",
             "--screenshot-to", str(shot), "--window-size", "1200x700",
             "--port", str(_free_port())],
            capture_output=True, text=True, timeout=180, env=env)
        assert shot.is_file(), proc.stderr[-2000:]
        img = np.asarray(Image.open(shot).convert("RGB"), dtype=np.int64)
        assert img.shape[1] >= 1200 and img.shape[0] >= 700
        # the dark theme is grey; the range and SNR_XC images, the points and the colour
        # scale add saturated colour
        saturation = img.max(axis=2) - img.min(axis=2)
        coloured.append(int(np.count_nonzero(saturation > 100)))
        if coloured[-1] > 2000:
            break
    assert coloured[-1] > 2000, (coloured, json.dumps(img.mean(axis=(0, 1)).tolist()))


def test_view_steer_takes_commands_on_stdin(tmp_path) -> None:
    """``view --steer`` end to end: settings typed on stdin, ``quit`` ends it; the colour
    change reaches the recording (the colour scale names SNR_XC's fixed span)."""
    rrd = tmp_path / "steer.rrd"
    proc = subprocess.run(
        [sys.executable, "-m", "cdma_lidar.cli", "view", "--port", "virtual://flat-wall?seed=1",
         "--steer", "--save", str(rrd), "--no-progress", "--frame-id", "1"],
        input="color snr\nthreshold 18\nquit\n", capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert proc.stdout.startswith("steer: type threshold DB")
    spans = [row["TextDocument:text"][0] for row in recorded(rrd)["color_scale/span"].values()]
    assert spans[-1].startswith("snr: 0 dB")
