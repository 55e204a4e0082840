"""capture, --combine, intensity calibration, multi-user defaults and bad inputs."""

from __future__ import annotations

import json

import numpy as np
import pytest
from cli_helpers import one_line_error as _one_line_error
from cli_helpers import run_cli as _run

from cdma_lidar.host.cloud_formats.npz import read as read_npz
from cdma_lidar.host.combine import combine
from cdma_lidar.host.connection import connect
from cdma_lidar.host.scan import ScanOptions, image_from_cloud, run_scan
from cdma_lidar.scene import load_scene
from cdma_lidar.scene.truth import compute_truth
from cdma_lidar.units import delay_to_range_m


def test_capture_corr_finds_the_echo(capsys, tmp_path):
    truth = compute_truth(load_scene("flat-wall")).range_m
    out = tmp_path / "c.npz"
    code, text, _ = _run(capsys, "capture", "--port", "virtual://flat-wall?seed=1", "--kind",
                         "corr", "--column", "3", "--channel", "7", "--out", str(out),
                         "--plot", "--frame-id", "4")
    assert code == 0 and "wrote" in text
    with np.load(out) as z:
        data, lag, rng = z["data"], z["lag"], z["range_m"]
        assert str(z["kind"]) == "corr" and int(z["channel"]) == 7
        assert data.shape == lag.shape == rng.shape
        # The trace's maximum is the wall, at the lag the receiver reported; uncalibrated,
        # so the range is the wall's plus the system delay.
        assert int(lag[np.argmax(np.abs(data))]) == int(z["peak_lag"])
        delay = delay_to_range_m(load_scene("flat-wall").instrument.system_delay_s)
        assert rng[np.argmax(np.abs(data))] == pytest.approx(truth[7, 3] + delay, abs=0.7)
    assert out.with_suffix(".png").read_bytes()[:4] == b"\x89PNG"


def test_capture_raw_writes_sigmf(capsys, tmp_path):
    out = tmp_path / "r.npz"
    code, _, _ = _run(capsys, "capture", "--port", "virtual://flat-wall?seed=1", "--kind",
                      "raw", "--column", "0", "--out", str(out))
    assert code == 0
    with np.load(out) as z:
        data, rate = z["data"], float(z["sample_rate_hz"])
    meta = json.loads((tmp_path / "r.sigmf-meta").read_text())
    assert meta["global"]["core:datatype"] == "ri16_le"
    assert meta["global"]["core:sample_rate"] == rate
    assert meta["global"]["core:version"].startswith("1.")
    assert meta["captures"][0]["core:sample_start"] == 0
    raw = np.fromfile(tmp_path / "r.sigmf-data", dtype="<i2")
    np.testing.assert_array_equal(raw, data)
    assert raw.std() > 0


@pytest.mark.parametrize("argv, words", [
    (["capture", "--kind", "corr", "--column", "99", "--out", "x.npz"], "--column must be"),
    (["capture", "--kind", "corr", "--column", "0", "--channel", "40", "--out", "x.npz"],
     "--channel must be"),
    (["capture", "--kind", "raw", "--column", "0", "--out", "x.txt"], "--out must be a .npz"),
    # ScanOptions checks these once and names its field
    (["scan", "--out", "x.ply", "--snr-threshold", "1e9"], "snr_threshold_db must be from 0"),
    (["scan", "--out", "x.ply", "--snr-threshold", "-3"], "snr_threshold_db must be from 0"),
    (["scan", "--out", "x.ply", "--near-far"], "frames must be at least 2 with near_far"),
    (["scan", "--out", "x.ply", "--frames", "0"], "frames must be from 1"),
    (["scan", "--out", "x.ply", "--combine", "mean"], "frames must be at least 2 with combine"),
    (["scan", "--out", "x.ply", "--calibrate-intensity", "0.5"], "needs --calibration"),
    (["scan", "--out", "x.ply", "--calibrate-intensity", "1.5"], "reflectivity in (0, 1]"),
])
def test_bad_inputs_exit_2_with_one_line(capsys, tmp_path, monkeypatch, argv, words):
    monkeypatch.chdir(tmp_path)
    line = _one_line_error(capsys, argv[0], "--port", "virtual://flat-wall?seed=1", *argv[1:])
    assert words in line


@pytest.fixture(scope="module")
def wall_frames(tmp_path_factory):
    """Two independent 8-frame scans of flat-wall with perfect calibration."""
    scene = load_scene("flat-wall")
    offset = delay_to_range_m(scene.instrument.system_delay_s)
    runs = []
    for fid in (100, 200):
        with connect("virtual://flat-wall?seed=1") as dev:
            res = run_scan(dev, tmp_path_factory.mktemp("wall") / "w.npz",
                           ScanOptions(frames=8, offset_m=offset), progress=False,
                           frame_id=fid)
        runs.append([image_from_cloud(cl, res.image.config) for cl in res.clouds])
    return compute_truth(scene).range_m, runs


def test_combining_frames_improves_precision_as_sqrt_n_but_not_the_bias(wall_frames):
    truth, (a, b) = wall_frames
    spread, bias = {}, {}
    for n in (1, 4):
        ra = combine(a[:n], "mean").range_m
        rb = combine(b[:n], "mean").range_m
        ok = np.isfinite(ra) & np.isfinite(rb)
        # Frame-to-frame precision: two independent combinations differ by noise only.
        spread[n] = float(np.std((ra - rb)[ok]) / np.sqrt(2))
        # The deterministic part (cross-talk, sub-sample bias) is in both alike.
        bias[n] = float(np.median(np.abs(0.5 * (ra + rb) - truth)[ok]))
    assert spread[1] / spread[4] == pytest.approx(2.0, rel=0.35)
    assert bias[4] > 0.5 * bias[1]
    med = combine(a[:5], "median").range_m
    assert np.isfinite(med).mean() > 0.95


def test_intensity_calibrated_on_flat_wall_reads_reflectivity(capsys, tmp_path):
    cal = tmp_path / "cal.toml"
    assert _run(capsys, "calibrate", "--port", "virtual://flat-wall?seed=1",
                "--target-distance", "0.5", "--out", str(cal))[0] == 0
    code, text, _ = _run(capsys, "scan", "--port", "virtual://flat-wall?seed=1", "--out",
                         str(tmp_path / "w.npz"), "--calibration", str(cal),
                         "--calibrate-intensity", "0.5", "--no-progress")
    assert code == 0 and "intensity gain" in text
    for url, want in (("flat-wall?distance=8&seed=1", 0.5),
                      ("flat-wall?reflectivity=0.2&seed=1", 0.2)):
        out = tmp_path / "x.npz"
        assert _run(capsys, "scan", "--port", f"virtual://{url}", "--out", str(out),
                    "--calibration", str(cal), "--no-progress")[0] == 0
        cloud = read_npz(out)
        ok = cloud.flags == 0
        assert np.median(cloud.intensity[ok]) == pytest.approx(want, rel=0.1)
        assert np.median(cloud.range[ok]) == pytest.approx(
            8.0 if "distance" in url else 5.0, abs=0.1)


def test_multi_user_defaults_and_keep_foreign(capsys, tmp_path):
    out = tmp_path / "mu.npz"
    code, text, _ = _run(capsys, "scan", "--port", "virtual://multi-user?seed=1", "--out",
                         str(out), "--no-progress", "--frame-id", "3", "--keep-foreign")
    assert code == 0
    assert "asking for 4 peaks" in text and "kept in the cloud" in text
    cloud = read_npz(out)
    assert (cloud.flags == 0).all()            # every pixel of our wall found
    assert set(cloud.extra["user_id"].tolist()) <= {0, 3} and cloud.extra.size > 0
    assert (cloud.extra["flags"] & 4).all()
    assert (cloud.user_id == 1).all()          # our UID


def test_scan_to_mcap_writes_one_pointcloud2_per_frame(capsys, tmp_path):
    from mcap.reader import make_reader  # mcap extra, in the test extra
    from mcap_ros2.decoder import DecoderFactory

    out = tmp_path / "s.mcap"
    code, _, _ = _run(capsys, "scan", "--port", "virtual://flat-wall?seed=1", "--out", str(out),
                      "--frames", "3", "--no-progress", "--frame-id", "9")
    assert code == 0
    with open(out, "rb") as fh:
        msgs = [m for *_, m in make_reader(fh, decoder_factories=[DecoderFactory()])
                .iter_decoded_messages(topics=["/cdma_lidar/points"])]
    assert len(msgs) == 3
    stamps = [m.header.stamp.sec + 1e-9 * m.header.stamp.nanosec for m in msgs]
    assert stamps == sorted(stamps) and stamps[0] > 1.6e9
    for m in msgs:
        assert (m.height, m.width) == (40, 16) and m.header.frame_id == "cdma_lidar"
        names = [f.name for f in m.fields]
        assert {"t", "ring", "intensity", "user_id"} <= set(names)
        assert len(m.data) == m.point_step * m.height * m.width
