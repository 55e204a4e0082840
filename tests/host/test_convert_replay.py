"""convert between every format, replay://, and what an .mcap from a scan says about itself.

Each written file is read back by the readers of cdma_lidar and checked value for value
against the cloud it came from; the independent readers (plyfile, laspy, mcap, Open3D)
check the same files in test_pointcloud.py.
"""

from __future__ import annotations

import json

import numpy as np
import pytest
from cli_helpers import one_line_error, run_cli

import cdma_lidar.virtual  # noqa: F401 - registers virtual:// with pyserial
from cdma_lidar.host.cloud_formats import read_frames
from cdma_lidar.host.cloud_formats.las import INTENSITY_SCALE
from cdma_lidar.host.connection import connect
from cdma_lidar.host.scan import ScanOptions, run_scan

FORMATS = [".ply", ".pcd", ".npz", ".las", ".mcap"]


@pytest.fixture(scope="module")
def recording(tmp_path_factory):
    """A 2-frame flat-wall scan recorded to .mcap, and its clouds."""
    folder = tmp_path_factory.mktemp("rec")
    with connect("virtual://flat-wall?seed=1") as dev:
        res = run_scan(dev, folder / "s.mcap", ScanOptions(frames=2), progress=False,
                       frame_id=4)
    return folder / "s.mcap", res.clouds


def _same(a, b, ext):
    ok = a.has_range
    np.testing.assert_array_equal(b.has_range, ok)
    for name in ("x", "y", "z", "range", "snr_xc", "t"):
        np.testing.assert_allclose(getattr(b, name)[ok], getattr(a, name)[ok].astype(np.float32),
                                   rtol=1e-6, atol=2e-4 if ext == ".las" else 1e-7)
    for name in ("ring", "column", "flags", "user_id", "peak"):
        np.testing.assert_array_equal(getattr(b, name)[ok], getattr(a, name)[ok])
    tol = 0.5 / INTENSITY_SCALE if ext == ".las" else 1e-6 * np.nanmax(a.intensity)
    np.testing.assert_allclose(b.intensity[ok], a.intensity[ok], atol=tol)


@pytest.mark.parametrize("src", FORMATS)
@pytest.mark.parametrize("dst", FORMATS)
def test_convert_between_every_pair_keeps_every_value(capsys, tmp_path, recording, src, dst):
    mcap_path, clouds = recording
    first = tmp_path / f"a{src}"
    code, _, err = run_cli(capsys, "convert", str(mcap_path), str(first))
    assert code == 0, err
    out = tmp_path / f"b{dst}"
    code, _, err = run_cli(capsys, "convert", str(first), str(out))
    assert code == 0, err
    frames = read_frames(out)
    assert len(frames) == (2 if src == dst == ".mcap" else 1)
    _same(clouds[-1], frames[-1], ".las" if ".las" in (src, dst) else dst)
    if not {".pcd", ".las", ".ply"} & {src, dst}:  # the others keep the stamp
        assert frames[-1].stamp_unix_s == pytest.approx(clouds[-1].stamp_unix_s, abs=1e-6)


def test_a_scan_mcap_carries_beam_angles_configuration_and_intensity_unit(recording):
    from mcap.reader import make_reader

    with open(recording[0], "rb") as fh:
        (meta,) = [m for m in make_reader(fh).iter_metadata() if m.name == "cdma_lidar"]
    el = np.array(json.loads(meta.metadata["beam_elevation_deg"]))
    az = np.array(json.loads(meta.metadata["beam_azimuth_deg"]))
    assert el.shape == az.shape == (40, 16)
    assert np.all(np.diff(el[:, 8]) < 0)   # ring 0 is the top beam
    assert np.all(np.diff(az[20]) < 0)     # column 0 is the leftmost (azimuth positive left)
    assert json.loads(meta.metadata["configuration"])["samples_per_chip"] == 4
    assert json.loads(meta.metadata["intensity_unit"]).startswith("ADC full scales")
    assert len(json.loads(meta.metadata["wavelengths_m"])) == 40


def test_replay_feeds_a_recording_back_through_the_host(capsys, tmp_path, recording):
    mcap_path, clouds = recording
    code, text, err = run_cli(capsys, "scan", "--port", f"replay://{mcap_path}", "--out",
                              str(tmp_path / "r.mcap"), "--pictures")
    assert code == 0, err
    assert "replayed 2 frames" in text
    again = read_frames(tmp_path / "r.mcap")
    assert len(again) == 2
    for a, b in zip(clouds, again, strict=True):
        _same(a, b, ".mcap")
    assert (tmp_path / "r_snr.png").read_bytes()[:4] == b"\x89PNG"


@pytest.mark.parametrize("argv, words", [
    (["convert", "{tmp}/none.ply", "{tmp}/x.npz"], "does not exist"),
    (["convert", "{tmp}/bad.ply", "{tmp}/x.npz"], "not a PLY file"),
    (["convert", "{tmp}/bad.ply", "{tmp}/x.xyz"], "OUT must end in one of"),
    (["scan", "--port", "replay://{tmp}/bad.ply", "--out", "{tmp}/x.ply", "--frames", "2",
      "--combine", "mean"], "--combine last only"),
    (["scan", "--port", "replay://{tmp}/none.mcap", "--out", "{tmp}/x.ply"], "does not exist"),
])
def test_bad_convert_and_replay_inputs(capsys, tmp_path, argv, words):
    (tmp_path / "bad.ply").write_bytes(b"not a ply\n")
    line = one_line_error(capsys, *(a.format(tmp=tmp_path) for a in argv))
    assert words in line, line


@pytest.mark.parametrize("name, content", [
    ("g.las", b"garbage"), ("g.mcap", b"garbage"), ("g.pcd", b"# .PCD\nFIELDS x\nDATA binary\nxx"),
    ("g.ply", b"ply\nformat binary_little_endian 1.0\nelement vertex 1\nproperty float32 x\n"
              b"end_header\nabcd"),
    ("g.npz", b"PK garbage"),
])
def test_convert_refuses_garbage_in_one_line(capsys, tmp_path, name, content):
    (tmp_path / name).write_bytes(content)
    line = one_line_error(capsys, "convert", str(tmp_path / name), str(tmp_path / "o.ply"))
    assert name in line and not (tmp_path / "o.ply").exists()


def test_convert_refuses_an_npz_that_is_not_a_cloud(capsys, tmp_path):
    np.savez(tmp_path / "other.npz", data=np.arange(3))
    line = one_line_error(capsys, "convert", str(tmp_path / "other.npz"),
                          str(tmp_path / "o.ply"))
    assert "other.npz" in line
