"""The pictures of a scan (Fig. 3a, 3c, 3e, 4d and the near-far power) and capture --plot."""

from __future__ import annotations

import numpy as np
import pytest
from cli_helpers import run_cli

import cdma_lidar.virtual  # noqa: F401 - registers virtual:// with pyserial
from cdma_lidar.host import pictures
from cdma_lidar.host.connection import connect
from cdma_lidar.host.scan import ScanOptions, picture_paths, run_scan, scene_name


def _png(path) -> bool:
    return path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and path.stat().st_size > 5000


def test_near_far_pictures_save_and_draw_the_power_matrix_per_frame(tmp_path):
    out = tmp_path / "nf.npz"
    with connect("virtual://near-far?seed=1") as dev:
        dev.link.set_config(columns_per_frame=24)
        dev.refresh_config()
        res = run_scan(dev, out, ScanOptions(frames=3, near_far=True), progress=False,
                       pictures_too=True, frame_id=2)
        assert scene_name(dev) == "near-far"
    paths = picture_paths(out)
    assert [p.name for p in res.files[1:]] == [paths[k].name for k in (
        "snr", "depth", "view", "column", "histogram", "power", "power_npz")]
    assert all(_png(p) for p in res.files[1:-1])
    with np.load(paths["power_npz"]) as z:
        np.testing.assert_array_equal(z["power"], np.stack(res.powers[:-1]))
        np.testing.assert_array_equal(z["snr_xc_db"], np.stack(res.snr_maps))
        assert z["power"].shape == (3, 40, 24)


def test_angles_put_ring_0_at_the_top_and_column_0_at_the_left():
    with connect("virtual://paper-scene1") as dev:
        el, az = dev.beam_angles_deg()
    left, right, bottom, top = pictures.Angles(el, az).extent()
    assert top > 0 > bottom and top == pytest.approx(el[0, 80], abs=0.02)
    assert left > 0 > right          # azimuth positive left, drawn on the left
    assert pictures.Angles(np.full((4, 3), np.nan), np.zeros((4, 3))).extent() is None


def test_busiest_column_is_the_one_with_most_ranged_pixels():
    from cdma_lidar.host.cloud_formats.grid import cloud_from_records
    from cdma_lidar.host.pointcloud import empty_records

    cloud = cloud_from_records(empty_records(0), shape=(4, 5))
    for col, n in ((0, 2), (3, 3), (4, 3)):
        cloud.range[:n, col] = cloud.x[:n, col] = 5.0
    assert pictures.busiest_column(cloud) == 3   # 3 and 4 tie: 3 is nearer the middle


@pytest.mark.parametrize("calibrated", [False, True])
def test_capture_plot_says_whether_its_range_is_calibrated(capsys, tmp_path, calibrated):
    extra = []
    if calibrated:
        code, _, err = run_cli(capsys, "calibrate", "--port", "virtual://paper-scene1",
                               "--target-distance", "0.5", "--shots", "5", "--out",
                               str(tmp_path / "c.toml"))
        assert code == 0, err
        extra = ["--calibration", str(tmp_path / "c.toml")]
    code, _, err = run_cli(capsys, "capture", "--port", "virtual://paper-scene1", "--kind",
                           "corr", "--column", "17", "--channel", "13", "--out",
                           str(tmp_path / "c.npz"), "--plot", *extra)
    assert code == 0, err
    with np.load(tmp_path / "c.npz") as z:
        assert bool(z["calibrated"]) is calibrated
        peak_m = float(z["range_m"][int(z["peak_lag"]) - int(z["lag"][0])])
    # the letter is at about 4.85 m; the raw range holds the system delay (about 5.6 m)
    assert (abs(peak_m - 4.85) < 0.5) is calibrated
    assert _png(tmp_path / "c.png")
