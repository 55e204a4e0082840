"""The one-call Python API: cdma_lidar.open / calibrate / scan / run_study."""

from __future__ import annotations

import subprocess
import sys
import tempfile

import numpy as np
import pytest

import cdma_lidar
from cdma_lidar.errors import ConfigError

URL = "virtual://flat-wall?seed=2&distance=4"


def test_open_virtual_needs_no_other_import() -> None:
    """The docs/host.md snippet failed with "unknown URL scheme 'virtual'" before."""
    code = ("import cdma_lidar\n"
            "with cdma_lidar.open('virtual://flat-wall?seed=1') as dev:\n"
            "    print(dev.channels, dev.columns)\n")
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.split() == ["40", "16"]


def test_scan_in_memory_sees_every_frame_and_leaves_no_file(tmp_path, monkeypatch) -> None:
    monkeypatch.chdir(tmp_path)
    monkeypatch.setattr(tempfile, "tempdir", str(tmp_path))   # where the .npz would go
    seen = []
    with cdma_lidar.open(URL, settings={"averages": 2}) as dev:
        assert dev.config["averages"] == 2
        res = cdma_lidar.scan(dev, frames=3, near_far=True, frame_id=7, progress=False,
                              on_frame=lambda i, cloud, power: seen.append((i, cloud, power)))
    assert [i for i, _, _ in seen] == [0, 1, 2]
    assert all(power.shape == cloud.shape for _, cloud, power in seen)
    assert res.clouds[-1] is seen[-1][1] and res.files == []
    np.testing.assert_array_equal(seen[-1][2], res.powers[-2])   # what frame 2 ran with
    assert not any(tmp_path.iterdir())
    assert res.image.valid.mean() > 0.9


def test_scan_by_url_with_a_calibration_file_writes_out(tmp_path) -> None:
    cal_path = tmp_path / "cal.toml"
    cal = cdma_lidar.calibrate(URL, 0.5, shots=5, out=cal_path, frame_id=0)
    res = cdma_lidar.scan(URL, tmp_path / "wall.ply", calibration=cal_path, frame_id=1,
                          progress=False)
    assert res.files == [tmp_path / "wall.ply"] and (tmp_path / "wall.ply").is_file()
    assert res.image.config.offset_m == pytest.approx(cal.offset_m)
    assert np.nanmedian(res.cloud.x) == pytest.approx(4.0, abs=0.1)


def test_scan_options_are_checked() -> None:
    with pytest.raises(ConfigError, match="combine must be one of"):
        cdma_lidar.scan(URL, combine="max", progress=False)


def test_a_study_table_prints_as_a_table() -> None:
    """``print(run_study(...).table)`` in the README: a header row and aligned rows."""
    from cdma_lidar.study.table import Table

    table = Table(["degree", "snr_db", "scene"],
                  [{"degree": 5, "snr_db": 12.345678, "scene": "flat-wall"},
                   {"degree": 11, "snr_db": None, "scene": "wall"}])
    assert str(table).splitlines() == ["degree  snr_db  scene",
                                       "     5   12.35  flat-wall",
                                       "    11          wall"]
    assert repr(table).splitlines() == ["Table: 2 rows x 3 columns", *str(table).splitlines()]
