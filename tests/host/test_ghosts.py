"""Grating ghosts: a ghost map from an empty field, then ghost-free ranges behind it."""

from __future__ import annotations

import numpy as np
import pytest

from cdma_lidar.cli import main
from cdma_lidar.host.frame import FrameData
from cdma_lidar.host.ranging import (
    FLAG_GHOST,
    FLAG_REJECTED,
    RangingConfig,
    estimate_ranges,
    ghost_windows_from_image,
)
from cdma_lidar.scene import load_scene
from cdma_lidar.scene.truth import compute_truth

SCENE = """
name = "{name}"
description = "a wall at 6 m and a strong grating ghost at 2 m in channels 0-7"
[instrument]
wavelengths = {{ start_m = 1570e-9, spacing_m = 0.875e-9, count = 40 }}
incidence_deg = 60.02
nominal_incidence_deg = 60.0
azimuth_deg = [-1.0, 1.0]
columns = 8
laser_power_w = 2.5e-3
link_gain_v_m2_per_w = 100.0
noise_rms_v = 0.004
[[instrument.ghosts]]
distance_m = 2.0
amplitude_v = 0.005
channels = [0, 1, 2, 3, 4, 5, 6, 7]
"""
WALL = """
[[objects]]
kind = "plane"
name = "wall"
position_m = [6.0, 0.0, 0.0]
size_m = [20.0, 20.0]
reflectivity = 0.5
"""


@pytest.fixture(scope="module")
def scenes(tmp_path_factory):
    d = tmp_path_factory.mktemp("ghost")
    empty, wall = d / "empty.toml", d / "wall.toml"
    empty.write_text(SCENE.format(name="ghost-empty"))
    wall.write_text(SCENE.format(name="ghost-wall") + WALL)
    return d, empty, wall


def test_ghost_map_then_scan_through_the_cli(scenes, capsys):
    d, empty, wall = scenes
    gmap = d / "ghosts.toml"
    assert main(["scan", "--port", f"virtual://{empty}?seed=1", "--out", str(d / "e.npz"),
                 "--no-progress", "--save-ghost-map", str(gmap)]) == 0
    assert "ghost map: 1 windows" in capsys.readouterr().out
    spec = load_scene(str(wall)).instrument
    offset = spec.system_delay_s * 299_792_458.0 / 2
    truth = compute_truth(load_scene(str(wall))).range_m
    cal = d / "cal.toml"
    cal.write_text(f'offset_m = {offset}\nspread_m = 0.0\ntarget_distance_m = 1.0\nshots = 1\n')
    errors = {}
    for name, extra in (("plain", []), ("mapped", ["--ghost-map", str(gmap)])):
        out = d / f"{name}.npz"
        assert main(["scan", "--port", f"virtual://{wall}?seed=1", "--out", str(out),
                     "--no-progress", "--set", "peaks=2", "--set", "peak_exclude=4",
                     "--snr-threshold", "12",
                     "--calibration", str(cal), *extra]) == 0
        with np.load(out) as z:
            rng, flags = z["range"], z["flags"]
        ok = flags == 0
        errors[name] = np.abs(rng - truth)[ok]
        if name == "mapped":
            # The ghost channels are ranged from their second peak (integer lag: no
            # neighbours are sent for extra peaks, hence the 0.5 m bound below).
            assert np.mean(flags[:8] == 0) >= 0.9
    capsys.readouterr()
    assert np.max(errors["plain"]) > 3.0  # the ghost at 2 m was taken for the wall
    assert np.max(errors["mapped"]) < 0.5


def test_ghost_windows_from_image_merges_and_wraps():
    f = FrameData.empty(3, 4)
    f.done[:] = True
    f.uid_match[:] = True
    f.uid_signs[:] = 1
    f.noise_count[:], f.noise_sumsq[:] = 40, 4000
    f.peak[:] = 10000
    f.peak_lag[:] = [[13, 13, 14, 13], [13, 14, 13, 13], [8187, 8187, 8187, 8187]]
    cfg = RangingConfig(samples_per_chip=4, code_length=2047, method="none", min_support=0)
    img = estimate_ranges(f, cfg)
    wins = ghost_windows_from_image(img, margin=2)
    assert wins == ((11, 6), (8185, 5))
    # Those windows turn the same frame into ghosts.
    ghost = estimate_ranges(f, RangingConfig(samples_per_chip=4, code_length=2047,
                                             ghost_windows=wins, min_support=0))
    assert np.all(ghost.flags == FLAG_GHOST | FLAG_REJECTED)
