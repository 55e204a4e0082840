"""Point-cloud assembly and writers: PLY (plyfile), PCD (Open3D and a plain parser), NPZ, LAS."""

from __future__ import annotations

import numpy as np
import pytest

from cdma_lidar.errors import ConfigError
from cdma_lidar.host.cloud_formats import write
from cdma_lidar.host.cloud_formats.npz import read as read_npz
from cdma_lidar.host.pointcloud import assemble
from cdma_lidar.host.ranging import FLAG_INTERPOLATED, FLAG_REJECTED, RangeImage
from cdma_lidar.host.uid_filter import ForeignReturns
from cdma_lidar.optics.grating import GratingGeometry, paper_wavelengths_m

K, C = 6, 9


def _image(seed: int = 3) -> RangeImage:
    rng = np.random.default_rng(seed)
    r = rng.uniform(2.0, 8.0, (K, C))
    flags = np.zeros((K, C), np.uint8)
    flags[1, 2] = FLAG_REJECTED
    flags[4, 0] = FLAG_REJECTED | 4
    flags[3, 5] = FLAG_INTERPOLATED
    r[flags & FLAG_REJECTED != 0] = np.nan
    empty = np.zeros(0, np.int64)
    return RangeImage(range_m=r, lag=r / 0.6, snr_xc_db=rng.uniform(5, 40, (K, C)),
                      peak=rng.integers(-5000, 5000, (K, C)), flags=flags,
                      foreign=ForeignReturns(empty, empty, empty, empty, empty, empty,
                                             np.zeros(0)))


@pytest.fixture
def cloud():
    return assemble(_image(), GratingGeometry(), paper_wavelengths_m(K),
                    np.linspace(-5, 5, C))


def test_assemble_places_points_at_range(cloud):
    ok = cloud.has_range
    assert ok.sum() == K * C - 2
    norm = np.sqrt(cloud.x**2 + cloud.y**2 + cloud.z**2)
    np.testing.assert_allclose(norm[ok], cloud.range[ok], rtol=1e-12)
    assert np.all(cloud.x[ok] > 0)  # forward
    # Columns sweep left to right with the grating angle: azimuth changes monotonically.
    az = np.degrees(np.arctan2(cloud.y[0], cloud.x[0]))
    assert np.all(np.diff(az) > 0) or np.all(np.diff(az) < 0)
    assert np.isnan(cloud.x[1, 2]) and cloud.flags[1, 2] & FLAG_REJECTED


def test_assemble_checks_shapes():
    with pytest.raises(ConfigError, match="wavelengths_m"):
        assemble(_image(), GratingGeometry(), paper_wavelengths_m(K + 1), np.zeros(C))
    with pytest.raises(ConfigError, match="angles_deg"):
        assemble(_image(), GratingGeometry(), paper_wavelengths_m(K), np.zeros(C - 1))


def test_ply_opens_with_plyfile(cloud, tmp_path):
    import plyfile  # in the test extra

    path = tmp_path / "c.ply"
    n = write(cloud, path)
    assert n == K * C - 2
    ply = plyfile.PlyData.read(str(path))
    assert ply.text is False and ply.byte_order == "<"
    v = ply["vertex"]
    assert v.count == n
    names = [p.name for p in v.properties]
    assert names == ["x", "y", "z", "range", "snr_xc", "peak", "channel", "column", "flags"]
    ok = cloud.has_range.ravel()
    np.testing.assert_allclose(v["x"], cloud.x.ravel()[ok].astype(np.float32))
    np.testing.assert_array_equal(v["column"], cloud.column.ravel()[ok])
    np.testing.assert_array_equal(v["flags"], cloud.flags.ravel()[ok])
    assert int(v["flags"][np.flatnonzero(ok)[:].tolist().index(3 * C + 5)]) == FLAG_INTERPOLATED


def _read_pcd(path):
    raw = path.read_bytes()
    head, _, body = raw.partition(b"DATA binary\n")
    meta = {}
    for line in head.decode().splitlines():
        if line and not line.startswith("#"):
            key, *vals = line.split()
            meta[key] = vals
    code = {("F", "4"): "<f4", ("I", "4"): "<i4", ("U", "2"): "<u2", ("U", "1"): "u1"}
    dt = np.dtype([(n, code[t, s]) for n, t, s in
                   zip(meta["FIELDS"], meta["TYPE"], meta["SIZE"], strict=True)])
    return meta, np.frombuffer(body, dtype=dt)


def test_pcd_is_organised_and_opens_with_open3d(cloud, tmp_path):
    path = tmp_path / "c.pcd"
    assert write(cloud, path) == K * C
    meta, rec = _read_pcd(path)
    assert meta["VERSION"] == ["0.7"]
    assert meta["WIDTH"] == [str(C)] and meta["HEIGHT"] == [str(K)]
    assert rec.size == K * C
    grid = rec.reshape(K, C)
    np.testing.assert_array_equal(grid["channel"], cloud.channel)
    np.testing.assert_array_equal(grid["column"], cloud.column)
    assert np.isnan(grid["x"][1, 2])
    np.testing.assert_allclose(grid["range"][0], cloud.range[0].astype(np.float32))

    import open3d as o3d  # open3d-cpu in the test extra (needs Debian's libusb-1.0-0)

    pcd = o3d.io.read_point_cloud(str(path), remove_nan_points=False)
    pts = np.asarray(pcd.points)
    assert pts.shape == (K * C, 3)
    ok = cloud.has_range.ravel()
    np.testing.assert_allclose(pts[ok, 0], cloud.x.ravel()[ok], rtol=1e-6)


def test_npz_round_trip(cloud, tmp_path):
    path = tmp_path / "c.npz"
    write(cloud, path)
    back = read_npz(path)
    np.testing.assert_array_equal(back.flags, cloud.flags)
    np.testing.assert_array_equal(back.range, cloud.range)
    np.testing.assert_array_equal(back.wavelengths_m, cloud.wavelengths_m)


def test_las_round_trip(cloud, tmp_path):
    import laspy  # in the las and test extras

    path = tmp_path / "c.las"
    n = write(cloud, path)
    las = laspy.read(str(path))
    assert str(las.header.version) == "1.4" and las.header.point_format.id == 6
    assert len(las.points) == n == K * C - 2
    ok = cloud.has_range.ravel()
    np.testing.assert_allclose(np.asarray(las.x), cloud.x.ravel()[ok], atol=1e-4)
    np.testing.assert_array_equal(np.asarray(las.flags), cloud.flags.ravel()[ok])
    np.testing.assert_array_equal(np.asarray(las.channel), cloud.channel.ravel()[ok])


def test_bad_extension_and_folder(cloud, tmp_path):
    with pytest.raises(ConfigError, match="extension"):
        write(cloud, tmp_path / "c.xyz")
    with pytest.raises(ConfigError, match="does not exist"):
        write(cloud, tmp_path / "missing" / "c.ply")
    assert not list(tmp_path.iterdir())  # nothing half-written
