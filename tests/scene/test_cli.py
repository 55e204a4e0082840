"""``cdma-lidar scene ...``: truth export, listing, and one-line errors."""

from __future__ import annotations

import os

import numpy as np
import pytest

from cdma_lidar.cli import main
from cdma_lidar.scene import PRESETS, load_scene
from cdma_lidar.scene.presetfiles import preset_description, preset_names


def test_truth_npz(tmp_path, capsys):
    out = tmp_path / "truth.npz"
    assert main(["scene", "truth", "paper-scene1", "--out", str(out)]) == 0
    assert "40 x 160 pixels" in capsys.readouterr().out
    with np.load(out) as z:
        rng, pts, obj, refl = z["range_m"], z["point_m"], z["object_id"], z["reflectivity"]
        assert rng.shape == (40, 160) and pts.shape == (40, 160, 3)
        miss = obj < 0
        assert miss.any() and (~miss).any()
        assert np.all(np.isnan(rng[miss])) and np.all(np.isnan(pts[miss]))
        assert np.all(np.isnan(refl[miss])) and np.all(refl[~miss] == 0.5)
        # the point is range times the unit ray direction
        np.testing.assert_allclose(np.linalg.norm(pts[~miss], axis=-1), rng[~miss], rtol=1e-12)
        np.testing.assert_allclose(pts[~miss], z["directions"][~miss] * rng[~miss][:, None])
        assert list(z["object_names"]) == ["CDMA", "LI", "DAR"]
        assert str(z["scene"]) == "paper-scene1"


def test_truth_with_option_and_list(tmp_path, capsys):
    out = tmp_path / "wall.npz"
    assert main(["scene", "truth", "flat-wall?distance=7.5", "--out", str(out)]) == 0
    with np.load(out) as z:
        assert np.all(z["object_id"] == 0)
        assert np.nanmin(z["range_m"]) >= 7.5 and np.nanmax(z["range_m"]) < 7.51
    capsys.readouterr()
    assert main(["scene", "list"]) == 0
    listed = capsys.readouterr().out
    assert all(name in listed for name in PRESETS)
    assert main(["scene", "show", "near-far"]) == 0
    shown = capsys.readouterr().out
    assert "block" in shown
    target = load_scene("near-far").calibration.target_distance_m
    assert f"--target-distance {target:g}" in shown


def test_scene_list_reads_what_load_scene_loads(capsys):
    """`scene list` reads the files without loading them: the same names and descriptions."""
    assert preset_names() == PRESETS
    for name in PRESETS:
        assert preset_description(name) == load_scene(name).description
    assert main(["scene", "list"]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert [line.split(None, 1) for line in lines] == [
        [name, load_scene(name).description] for name in PRESETS]


def test_errors_are_one_line_exit_2(tmp_path, capsys):
    assert main(["scene", "truth", "no-such", "--out", str(tmp_path / "x.npz")]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "scene must be a preset" in err
    assert main(["scene", "truth", "flat-wall", "--out", str(tmp_path / "no" / "x.npz")]) == 2
    assert "does not exist" in capsys.readouterr().err
    bad = tmp_path / "bad.toml"
    bad.write_text('[[objects]]\nkind = "sphere"\nposition_m = [1.0, 0.0, 0.0]\nradius_m = -2\n')
    assert main(["scene", "truth", str(bad), "--out", str(tmp_path / "y.npz")]) == 2
    err = capsys.readouterr().err
    assert "objects[0].radius_m must be" in err and err.count("\n") == 1
    assert main(["device", "--scene", "flat-wall", "--tcp", "nonsense"]) == 2
    assert "--tcp must be HOST:PORT" in capsys.readouterr().err
    assert main(["scene", "truth", "flat-wall", "--out", str(tmp_path / "t.txt")]) == 2
    assert ".npz" in capsys.readouterr().err and not (tmp_path / "t.txt").exists()


@pytest.mark.skipif(not os.path.isdir("/proc/self"), reason="needs Linux /proc")
def test_truth_into_a_folder_that_refuses_files(capsys):
    """/proc refuses new files even to root (whom os.access always lets through)."""
    assert main(["scene", "truth", "flat-wall", "--out", "/proc/t.npz"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "cannot write" in err
