"""The scan as open / frames / finish, the scan profile (--config) and the device-link type."""

from __future__ import annotations

import inspect

import numpy as np
import pytest
from cli_helpers import one_line_error, run_cli

import cdma_lidar.virtual  # noqa: F401 - registers virtual:// with pyserial
from cdma_lidar.errors import ConfigError
from cdma_lidar.host.connection import DeviceLink, connect
from cdma_lidar.host.scan import (
    ScanOptions,
    frames_path,
    open_scan,
    run_scan,
    state_path,
)
from cdma_lidar.protocol.link import HostLink


def test_frames_iterator_yields_each_frame_and_finish_equals_run_scan(tmp_path):
    opts = ScanOptions(frames=3, near_far=True)
    with connect("virtual://near-far?seed=1") as dev:
        dev.link.set_config(columns_per_frame=16)
        dev.refresh_config()
        scan = open_scan(dev, tmp_path / "a.npz", opts, frame_id=5)
        seen = [(f.index, f.cloud.shape, f.power.shape) for f in scan.frames(progress=False)]
        res = scan.finish()
        whole = run_scan(dev, tmp_path / "b.npz", opts, frame_id=5, progress=False)
    assert seen == [(i, (40, 16), (40, 16)) for i in range(3)]
    np.testing.assert_array_equal(res.image.range_m, whole.image.range_m)
    assert len(res.powers) == 4 and not frames_path(tmp_path / "a.npz").exists()


def test_near_far_resume_across_a_frame_boundary_equals_the_whole_scan(tmp_path):
    """Finished frames come back from OUT.partial.frames/, with their powers."""
    opts = ScanOptions(frames=3, near_far=True)
    out = tmp_path / "r.npz"

    def stop(frame: int, column: int) -> None:
        if frame == 1 and column == 7:
            raise KeyboardInterrupt

    with connect("virtual://near-far?seed=1") as dev:
        dev.link.set_config(columns_per_frame=16)
        dev.refresh_config()
        whole = run_scan(dev, tmp_path / "w.npz", opts, frame_id=9, progress=False)
        with pytest.raises(KeyboardInterrupt):
            run_scan(dev, out, opts, frame_id=9, progress=False, on_column=stop)
        assert sorted(p.name for p in frames_path(out).iterdir()) == ["frame-00000.npz"]
        res = run_scan(dev, out, opts, resume=True, progress=False)
    assert res.columns_scanned == 2 * 16 - 8
    for a, b in zip(res.powers, whole.powers, strict=True):
        np.testing.assert_array_equal(a, b)
    np.testing.assert_array_equal(res.image.range_m, whole.image.range_m)
    assert not state_path(out).exists() and not frames_path(out).exists()


def test_a_consumer_that_stops_early_leaves_a_resumable_scan(tmp_path):
    out = tmp_path / "c.npz"
    with connect("virtual://flat-wall?seed=1") as dev:
        scan = open_scan(dev, out, ScanOptions(frames=2), frame_id=1)
        for _ in scan.frames(progress=False):
            break
        assert state_path(out).is_file()
        res = run_scan(dev, out, ScanOptions(frames=2), resume=True, progress=False)
    assert res.columns_scanned == 16


@pytest.mark.parametrize("kwargs, field", [
    ({"frames": 0}, "frames"), ({"frames": 1, "near_far": True}, "frames"),
    ({"combine": "mean"}, "frames"), ({"combine": "max", "frames": 2}, "combine"),
    ({"min_support": 9}, "min_support"), ({"initial_power": 0.0}, "initial_power"),
    ({"power_cap": float("inf")}, "power_cap"), ({"snr_threshold_db": -1.0}, "snr_threshold_db"),
    ({"offset_m": 1e12}, "offset_m"), ({"intensity_gain": 0.0}, "intensity_gain"),
    ({"ghost_windows": ((-1, 2),)}, "ghost_windows"), ({"frames": 2.0}, "frames"),
    ({"frames": True}, "frames"),
])
def test_scan_options_are_checked_at_construction(kwargs, field):
    with pytest.raises(ConfigError) as err:
        ScanOptions(**kwargs)
    assert err.value.field == field and field in str(err.value)


def test_host_link_is_a_device_link():
    """Every method the host relies on exists on HostLink with the same parameters."""
    for name, member in inspect.getmembers(DeviceLink, inspect.isfunction):
        if name.startswith("_"):
            continue
        ours = list(inspect.signature(member).parameters)
        theirs = list(inspect.signature(getattr(HostLink, name)).parameters)
        assert theirs[:len(ours)] == ours, name


def test_scan_profile_fills_options_and_the_command_line_wins(capsys, tmp_path):
    prof = tmp_path / "scan.toml"
    prof.write_text('port = "virtual://flat-wall?seed=1"\nframes = 2\ncombine = "mean"\n'
                    'no-progress = true\nset = ["averages=2"]\n'
                    f'out = "{tmp_path / "p.ply"}"\n')
    code, out, err = run_cli(capsys, "scan", "--config", str(prof))
    assert code == 0, err
    assert (tmp_path / "p.ply").is_file() and "scanned 32 columns" in out
    code, out, err = run_cli(capsys, "scan", "--config", str(prof), "--frames", "3",
                             "--out", str(tmp_path / "q.npz"))
    assert code == 0, err
    assert (tmp_path / "q.npz").is_file() and "scanned 48 columns" in out


@pytest.mark.parametrize("text, words", [
    ('frames = "many"\n', ["frames", "whole number"]),
    ("colour = 3\n", ["unknown option 'colour'"]),
    ("near-far = 1\n", ["near-far", "true or false"]),
    ('combine = "max"\n', ["combine", "one of"]),
    ("power-cap = -1\n", ["power-cap", "positive"]),
    ("frames = [", ["not a readable TOML"]),
])
def test_bad_scan_profile_is_one_line(capsys, tmp_path, text, words):
    prof = tmp_path / "scan.toml"
    prof.write_text(text)
    line = one_line_error(capsys, "scan", "--config", str(prof), "--port",
                          "virtual://flat-wall", "--out", str(tmp_path / "a.ply"))
    assert all(w in line for w in words), line


def test_scan_options_take_numpy_integers():
    assert ScanOptions(frames=np.int64(3), min_support=np.int32(2)).frames == 3
