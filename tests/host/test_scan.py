"""Scans through virtual://: acceptance on paper-scene1, near-far, multi-user, resume."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

import cdma_lidar.virtual  # noqa: F401 - registers virtual:// with pyserial
from cdma_lidar.errors import CalibrationError, ConfigError, LinkError, ScanAborted
from cdma_lidar.host.calibration import Calibration
from cdma_lidar.host.connection import connect
from cdma_lidar.host.ranging import estimate_ranges, precision_eq27_m
from cdma_lidar.host.scan import ScanOptions, calibrate_device, run_scan, state_path, summarise
from cdma_lidar.scene import load_scene
from cdma_lidar.scene.truth import compute_truth
from cdma_lidar.study.simulate import eq27_from_configuration


def _truth(name: str) -> np.ndarray:
    return compute_truth(load_scene(name)).range_m


@pytest.fixture(scope="module")
def paper_scan(tmp_path_factory):
    """Calibrate and scan paper-scene1 once; several tests look at the result."""
    out = tmp_path_factory.mktemp("paper") / "scene1.ply"
    with connect("virtual://paper-scene1?seed=1") as dev:
        cal = calibrate_device(dev, load_scene("paper-scene1").calibration.target_distance_m)
        res = run_scan(dev, out, ScanOptions(offset_m=cal.offset_m), progress=False,
                       pictures_too=True, frame_id=7)
        identity, config = dev.identity(), dev.calibration_config()
    return cal, res, identity, config, out


def test_paper_scene1_acceptance(paper_scan):
    _, res, _, _, _ = paper_scan
    truth = _truth("paper-scene1")
    s = summarise(res.image, truth)
    assert s["object_valid_fraction"] >= 0.95
    assert s["false_valid"] == 0
    rc = res.image.config
    obj_valid = res.image.valid & np.isfinite(truth)
    sigma = float(precision_eq27_m(rc.chip_rate_hz, rc.samples_per_symbol,
                                   snr_xc_db=float(np.median(res.image.snr_xc_db[obj_valid]))))
    assert s["median_error_m"] <= sigma
    # ... and within eq. 27 from the scene's configuration (eq. 30 SNR, median pixel).
    assert s["median_error_m"] <= eq27_from_configuration("paper-scene1")
    # Sub-sample refinement buys an order of magnitude over the integer lag.
    coarse = summarise(estimate_ranges(res.data, dataclasses.replace(rc, method="none")), truth)
    assert coarse["median_error_m"] > 5 * s["median_error_m"]


def test_calibration_finds_the_hidden_delay(paper_scan):
    cal, _, identity, config, _ = paper_scan
    true_offset = load_scene("paper-scene1").instrument.system_delay_s * 299_792_458.0 / 2
    assert cal.offset_m == pytest.approx(true_offset, abs=0.05)
    assert cal.spread_m < 0.15
    cal.check_applies(identity, config)
    with pytest.raises(CalibrationError, match="another device"):
        cal.check_applies({**identity, "serial": "VIRT-other"}, config)


def test_scan_writes_cloud_and_pictures(paper_scan):
    _, res, _, _, out = paper_scan
    assert [f.name for f in res.files] == ["scene1.ply", "scene1_snr.png", "scene1_depth.png",
                                           "scene1_3d.png", "scene1_column.png",
                                           "scene1_hist.png"]
    for f in res.files[1:]:
        assert f.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and f.stat().st_size > 5000
    assert not state_path(out).exists()
    assert res.cloud.has_range.sum() == res.image.valid.sum()


def test_resume_finishes_without_redoing_columns(tmp_path, paper_scan):
    _, full, *_ = paper_scan
    out = tmp_path / "r.npz"

    def stop_at_50(_frame: int, column: int) -> None:
        if column == 49:
            raise KeyboardInterrupt

    with connect("virtual://paper-scene1?seed=1") as dev:
        with pytest.raises(KeyboardInterrupt):
            run_scan(dev, out, ScanOptions(offset_m=full.image.config.offset_m),
                     progress=False, frame_id=7, on_column=stop_at_50)
        assert state_path(out).is_file() and not out.exists()
        res = run_scan(dev, out, ScanOptions(offset_m=full.image.config.offset_m),
                       resume=True, progress=False)
    assert res.columns_scanned == 110
    assert not state_path(out).exists()
    # Same frame id, same noise: identical to the uninterrupted scan.
    np.testing.assert_array_equal(res.image.flags, full.image.flags)
    np.testing.assert_array_equal(res.image.range_m, full.image.range_m)


def test_lost_link_leaves_a_resumable_scan(tmp_path):
    out = tmp_path / "lost.ply"

    def cut(_frame: int, column: int) -> None:
        if column == 3:
            raise LinkError("link lost (test)")

    with connect("virtual://multi-user?seed=2") as dev:
        with pytest.raises(ScanAborted, match="--resume"):
            run_scan(dev, out, progress=False, on_column=cut)
        assert state_path(out).is_file()
        with pytest.raises(ConfigError, match="does not match this scan's options"):
            run_scan(dev, out, ScanOptions(frames=2), resume=True, progress=False)
        res = run_scan(dev, out, resume=True, progress=False)
    assert res.columns_scanned == 4  # columns 4..7 of 8
    assert out.is_file()


@pytest.mark.parametrize("scene, columns", [("near-far", 64), ("paper-scene1", 48),
                                            ("flat-wall", 16)])
def test_near_far_loop_converges_and_stays_for_ten_frames(tmp_path, scene, columns):
    """Object pixels above the threshold never fall more than 2 points below the best
    frame after frame 2, and no column's power ever exceeds the cap."""
    truth = _truth(scene)[:, :columns]
    obj = np.isfinite(truth)
    with connect(f"virtual://{scene}?seed=1") as dev:
        dev.link.set_config(columns_per_frame=columns)
        dev.refresh_config()
        res = run_scan(dev, tmp_path / "nf.npz", ScanOptions(frames=10, near_far=True),
                       progress=False, frame_id=11)
        channels = dev.channels
    spec = load_scene(scene).instrument
    device_cap = spec.total_power_cap_w / spec.max_pixel_power_w
    thr = res.image.config.snr_threshold_db
    above = [100 * float(np.mean(m[obj] >= thr)) for m in res.snr_maps]
    assert len(above) == 10
    best = max(above)
    assert min(above[2:]) >= best - 2.0, above
    cap = channels * ScanOptions().initial_power   # default: the starting column sum
    for p in res.powers:
        assert p.max() <= 1.0
        assert p.sum(axis=0).max() <= cap * (1 + 1e-9)
        assert p.sum(axis=0).max() <= device_cap
    if scene == "near-far":
        assert above[0] < 90.0 and best >= 98.0   # the near block drowns part of the letters
        block = truth < 3.0
        assert np.median(res.powers[-1][block]) < 0.1 * np.median(res.powers[0][block])
    else:
        assert best >= 99.0


def test_multi_user_reports_only_own_ranges(tmp_path):
    scene = load_scene("multi-user")
    truth = _truth("multi-user")
    with connect("virtual://multi-user?seed=1") as dev:
        dev.link.set_config(peaks=8, peak_exclude=3)
        dev.refresh_config()
        cal_offset = scene.instrument.system_delay_s * 299_792_458.0 / 2
        # a fixed frame id fixes the noise: the default is random, and user 3 (6.5 mV at
        # 15 m) is missed in an occasional column (seen once in a CI run: {0: 8, 3: 7})
        res = run_scan(dev, tmp_path / "mu.ply", ScanOptions(offset_m=cal_offset),
                       progress=False, frame_id=3)
    img = res.image
    assert np.mean(img.valid) >= 0.95
    err = np.abs(img.range_m - truth)[img.valid]
    assert np.median(err) < 0.1  # our wall at 8 m, not the other users' delays
    # The other users share our channel 0's Gold code; users 0 (UID 000, 4.5 m) and 3
    # (UID 011, 15 m) are named in every column, and nowhere else. User 7 (45 m,
    # 3.9 mV) stays under the noise (scene/presets/multi-user.toml).
    users = img.foreign.users()
    assert users == {0: 8, 3: 8}
    assert set(img.foreign.channel.tolist()) == {0}
    assert scene.instrument.uid not in set(img.foreign.observed.tolist())
    assert np.all(img.flags[0] == 0)  # our own range on channel 0 too


def test_calibration_file_round_trip_refuses_other_device(tmp_path):
    with connect("virtual://calibration?seed=3") as dev:
        cal = calibrate_device(dev, load_scene("calibration").calibration.target_distance_m,
                               shots=10)
    path = tmp_path / "cal.toml"
    cal.save(path)
    back = Calibration.load(path)
    with connect("virtual://paper-scene1?seed=1") as dev:
        with pytest.raises(CalibrationError, match="another device"):
            back.check_applies(dev.identity(), dev.calibration_config())


def test_interpolation_fills_rejected_object_pixels(paper_scan):
    """At 20 dB some object pixels fall below the threshold; --interpolate fills short runs
    of them along the column (flag 1, bit 2 cleared) close to the truth."""
    from cdma_lidar.host.ranging import FLAG_INTERPOLATED, FLAG_REJECTED

    _, res, *_ = paper_scan
    truth = _truth("paper-scene1")
    obj = np.isfinite(truth)
    strict = dataclasses.replace(res.image.config, snr_threshold_db=20.0)
    plain = estimate_ranges(res.data, strict)
    filled = estimate_ranges(res.data, dataclasses.replace(strict, interpolate=True))
    new = filled.flags == FLAG_INTERPOLATED
    assert new.sum() >= 20
    assert np.all(plain.flags[new] & FLAG_REJECTED) and np.all(np.isnan(plain.range_m[new]))
    assert np.all(np.isfinite(filled.range_m[new]))
    # Measured pixels are untouched; only rejected ones change.
    np.testing.assert_array_equal(filled.range_m[plain.valid], plain.range_m[plain.valid])
    assert np.all(filled.flags[~new] == plain.flags[~new])
    # Filled pixels lie between measured neighbours of the same letter: close to the truth.
    err = np.abs(filled.range_m - truth)[new & obj]
    assert np.median(err) < 0.05 and np.mean(new[obj]) > np.mean(new[~obj])


def test_saturated_pixels_are_flagged(tmp_path):
    """An 8-bit output with a small shift clips the strong peaks only: flag 16 marks exactly
    the pixels whose column record says ``saturated`` (a clipped plateau's lag may be early)."""
    from cdma_lidar.host.ranging import FLAG_SATURATED

    with connect("virtual://paper-scene1?seed=2") as dev:
        dev.link.set_config(out_bits=8, out_shift=8)
        dev.refresh_config()
        res = run_scan(dev, tmp_path / "sat.npz", ScanOptions(), progress=False, frame_id=5)
    sat = np.asarray(res.data.saturated, bool)
    assert sat.any() and not sat.all()  # the test needs both kinds of pixel
    np.testing.assert_array_equal((res.image.flags & FLAG_SATURATED) != 0, sat)
