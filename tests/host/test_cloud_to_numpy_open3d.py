"""PointCloud.to_numpy() and .to_open3d(): the points a file would hold, in memory."""

from __future__ import annotations

import sys

import numpy as np
import pytest

from cdma_lidar.errors import ConfigError, MissingExtra
from cdma_lidar.host.pointcloud import POINT_FIELDS, assemble
from cdma_lidar.host.ranging import FLAG_FOREIGN, FLAG_REJECTED, RangeImage
from cdma_lidar.host.uid_filter import ForeignReturns
from cdma_lidar.optics.grating import GratingGeometry, paper_wavelengths_m

K, C = 5, 7


@pytest.fixture
def cloud():
    rng = np.random.default_rng(11)
    r = rng.uniform(1.0, 9.0, (K, C))
    flags = np.zeros((K, C), np.uint8)
    flags[0, 3] = flags[2, 6] = FLAG_REJECTED
    r[flags != 0] = np.nan
    empty = np.zeros(0, np.int64)
    image = RangeImage(range_m=r, lag=r / 0.6, snr_xc_db=rng.uniform(5, 40, (K, C)),
                       peak=rng.integers(-5000, 5000, (K, C)), flags=flags,
                       foreign=ForeignReturns(empty, empty, empty, empty, empty, empty,
                                              np.zeros(0)))
    cl = assemble(image, GratingGeometry(), paper_wavelengths_m(K), np.linspace(-4, 4, C),
                  intensity=rng.uniform(0, 1, (K, C)))
    extra = np.zeros(2, dtype=cl.extra.dtype)   # two kept foreign returns
    extra["x"], extra["range"], extra["flags"], extra["user_id"] = 3.0, 3.0, FLAG_FOREIGN, 5
    cl.extra = extra
    return cl


def test_to_numpy_is_xyz_of_every_point_with_a_range(cloud):
    xyz = cloud.to_numpy()
    ok = cloud.has_range
    assert xyz.shape == (int(ok.sum()) + 2, 3) and xyz.dtype == np.float64
    np.testing.assert_array_equal(xyz[:-2, 0], cloud.x[ok].astype(np.float32))
    np.testing.assert_array_equal(xyz[:-2, 2], cloud.z[ok].astype(np.float32))
    np.testing.assert_array_equal(xyz[-2:, 0], [3.0, 3.0])
    assert np.all(np.isfinite(xyz))


def test_to_numpy_takes_any_point_field_and_refuses_others(cloud):
    got = cloud.to_numpy(("range", "ring", "user_id"), keep_rejected=True)
    assert got.shape == (K * C + 2, 3)
    np.testing.assert_array_equal(got[:K * C, 1], cloud.ring.ravel())
    np.testing.assert_array_equal(got[-2:, 2], [5, 5])
    with pytest.raises(ConfigError, match="fields must be some of x, y, z"):
        cloud.to_numpy(("x", "colour"))


def test_to_open3d_keeps_every_field(cloud):
    pytest.importorskip("open3d", reason="open3d-cpu is in the test extra")
    pcd = cloud.to_open3d()
    rec = cloud.records()
    np.testing.assert_array_equal(pcd.point.positions.numpy(),
                                  np.stack([rec["x"], rec["y"], rec["z"]], 1))
    for name, dtype in POINT_FIELDS[3:]:
        got = pcd.point[name].numpy()
        assert got.shape == (len(rec), 1) and got.dtype == np.dtype(dtype), name
        np.testing.assert_array_equal(got.ravel(), rec[name], err_msg=name)
    assert len(pcd.to_legacy().points) == len(rec)


def test_to_open3d_without_open3d_names_the_extra(cloud, monkeypatch):
    monkeypatch.setitem(sys.modules, "open3d", None)   # what `import open3d` sees uninstalled
    with pytest.raises(MissingExtra, match=r"pip install 'cdma-lidar\[open3d\]'") as exc:
        cloud.to_open3d()
    assert isinstance(exc.value, ImportError) and exc.value.extra == "open3d"
