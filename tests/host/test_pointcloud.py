"""Point-cloud assembly and writers: PLY (plyfile), PCD (Open3D and a plain parser), NPZ, LAS."""

from __future__ import annotations

import numpy as np
import pytest

from cdma_lidar.errors import ConfigError
from cdma_lidar.host.cloud_formats import write
from cdma_lidar.host.cloud_formats.npz import read as read_npz
from cdma_lidar.host.pointcloud import POINT_FIELDS, PointCloud, assemble, column_times_s
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
    ts = 1_000_000 + 250 * np.arange(C)          # us, one column every 0.25 ms
    return assemble(_image(), GratingGeometry(), paper_wavelengths_m(K),
                    np.linspace(-5, 5, C), timestamps_us=ts,
                    intensity=np.full((K, C), 0.5), stamp_unix_s=1.7e9)


NAMES = [n for n, _ in POINT_FIELDS]


def test_point_fields_are_the_ones_lidar_tools_look_for():
    assert NAMES == ["x", "y", "z", "intensity", "t", "ring", "range", "snr_xc", "flags",
                     "column", "user_id", "peak"]


def test_time_and_ring(cloud):
    np.testing.assert_allclose(cloud.t[0], 250e-6 * np.arange(C))
    np.testing.assert_array_equal(cloud.ring[:, 0], np.arange(K))
    # The device clock wraps at 2^32 us: times keep increasing across the wrap.
    ts = (2**32 - 500 + 250 * np.arange(4)) % 2**32
    np.testing.assert_allclose(column_times_s(ts, np.ones(4, bool)), 250e-6 * np.arange(4))
    assert np.isnan(column_times_s(ts, np.array([True, False, True, True]))[1])


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
    assert names == NAMES
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
    code = {("F", "4"): "<f4", ("I", "4"): "<i4", ("U", "2"): "<u2", ("U", "1"): "u1",
            ("I", "2"): "<i2"}
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
    np.testing.assert_array_equal(grid["ring"], cloud.ring)
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
    np.testing.assert_array_equal(np.asarray(las.ring), cloud.ring.ravel()[ok])
    assert set(las.point_format.extra_dimension_names) == set(NAMES) - {"x", "y", "z",
                                                                         "intensity"}
    # gps_time: adjusted standard GPS time of the host stamp plus t (bit 0 of the encoding)
    assert las.header.global_encoding.gps_time_type == laspy.header.GpsTimeType.STANDARD
    t = np.asarray(las.gps_time) - (1.7e9 - 315_964_800 + 18 - 1e9)
    np.testing.assert_allclose(t, cloud.t.ravel()[ok], atol=1e-6)
    np.testing.assert_array_equal(np.asarray(las.intensity), 2048)   # 0.5 x 4096
    # point format 6 needs the WKT bit and a WKT coordinate system (LAS 1.4 R15, 2.4)
    assert las.header.global_encoding.wkt
    wkt = [v for v in las.header.vlrs if isinstance(v, laspy.vlrs.known.WktCoordinateSystemVlr)]
    assert len(wkt) == 1 and wkt[0].string.startswith('LOCAL_CS["cdma_lidar sensor frame')


def test_las_warns_where_intensity_saturates(cloud, tmp_path, caplog):
    import laspy

    cloud.intensity = np.where(cloud.has_range, 20.0, np.nan)
    cloud.intensity[0, :3] = 1.0
    write(cloud, tmp_path / "s.las")
    assert f"{int(cloud.has_range.sum()) - 3} of {int(cloud.has_range.sum())} points" in \
        caplog.text and "saturates" in caplog.text
    assert int(np.asarray(laspy.read(str(tmp_path / "s.las")).intensity).max()) == 65535


def test_bad_extension_and_folder(cloud, tmp_path):
    with pytest.raises(ConfigError, match="must end in one of"):
        write(cloud, tmp_path / "c.xyz")
    with pytest.raises(ConfigError, match="does not exist"):
        write(cloud, tmp_path / "missing" / "c.ply")
    assert not list(tmp_path.iterdir())  # nothing half-written


def test_ply_fields_survive_open3d_tensor_reader(cloud, tmp_path):
    import open3d as o3d  # open3d-cpu in the test extra

    path = tmp_path / "c.ply"
    n = write(cloud, path)
    pc = o3d.t.io.read_point_cloud(str(path))
    ok = cloud.has_range.ravel()
    assert pc.point.positions.shape[0] == n
    for name in NAMES[3:]:
        assert name in pc.point, name
        got = pc.point[name].numpy().ravel()
        np.testing.assert_allclose(got, getattr(cloud, name).ravel()[ok].astype(got.dtype))


def test_pcd_fields_survive_open3d_tensor_reader(cloud, tmp_path):
    import open3d as o3d  # open3d-cpu in the test extra

    path = tmp_path / "c.pcd"
    write(cloud, path)
    pc = o3d.t.io.read_point_cloud(str(path), remove_nan_points=False)
    for name in ("t", "ring", "column", "flags", "user_id", "intensity"):
        got = pc.point[name].numpy().ravel()
        np.testing.assert_allclose(got, getattr(cloud, name).ravel().astype(got.dtype))


def read_mcap(path, topic="/cdma_lidar/points"):
    """(schema, channel, message, decoded) of every message on ``topic``, with the mcap
    reader."""
    from mcap.reader import make_reader  # mcap extra, in the test extra
    from mcap_ros2.decoder import DecoderFactory

    with open(path, "rb") as fh:
        reader = make_reader(fh, decoder_factories=[DecoderFactory()])
        return list(reader.iter_decoded_messages(topics=[topic]))


def _empty() -> PointCloud:
    img = _image()
    img.range_m[:] = np.nan
    img.flags[:] = FLAG_REJECTED
    return assemble(img, GratingGeometry(), paper_wavelengths_m(K), np.linspace(-5, 5, C))


@pytest.mark.parametrize("ext", [".ply", ".pcd", ".las", ".npz", ".mcap"])
def test_empty_cloud_writes_a_valid_file(tmp_path, ext):
    import laspy
    import open3d as o3d
    import plyfile
    path = tmp_path / f"e{ext}"
    n = write(_empty(), path)
    if ext == ".ply":
        assert n == 0 and plyfile.PlyData.read(str(path))["vertex"].count == 0
        pc = o3d.t.io.read_point_cloud(str(path))
        assert pc.point.positions.shape[0] == 0 if "positions" in pc.point else True
    elif ext == ".pcd":
        # Every pixel is still there (organised, NaN coordinates).
        pc = o3d.t.io.read_point_cloud(str(path), remove_nan_points=False)
        assert pc.point.positions.shape[0] == K * C
    elif ext == ".las":
        assert len(laspy.read(str(path)).points) == 0
    elif ext == ".npz":
        assert read_npz(path).range.shape == (K, C)
    else:
        msgs = read_mcap(path)
        assert len(msgs) == 1 and msgs[0][3].height * msgs[0][3].width == K * C


def test_mcap_one_pointcloud2_per_frame(cloud, tmp_path):
    from cdma_lidar.host.cloud_formats import mcap, write_frames

    second = assemble(_image(seed=4), GratingGeometry(), paper_wavelengths_m(K),
                      np.linspace(-5, 5, C), stamp_unix_s=1.7e9 + 0.1)
    path = tmp_path / "s.mcap"
    assert write_frames([cloud, second], path) == 2 * K * C
    msgs = read_mcap(path)
    assert [ch.topic for _, ch, _, _ in msgs] == [mcap.TOPIC] * 2
    assert msgs[0][0].name == "sensor_msgs/msg/PointCloud2"
    # fields aligned to their size: a reader may view them as float32 in place
    assert all(f.offset % {7: 4, 5: 4, 4: 2}[f.datatype] == 0 for f in msgs[0][3].fields)
    assert msgs[0][3].point_step == 44
    # the identity transform base_link -> cdma_lidar on /tf_static, at the first stamp
    (_, _, tfm, tf), = read_mcap(path, mcap.TF_TOPIC)
    assert tfm.log_time == 1_700_000_000 * 10**9
    (tr,) = tf.transforms
    assert (tr.header.frame_id, tr.child_frame_id) == (mcap.PARENT_FRAME, mcap.FRAME_ID)
    assert (tr.transform.rotation.w, tr.transform.translation.x) == (1.0, 0.0)
    assert [m.log_time for _, _, m, _ in msgs] == [1_700_000_000 * 10**9,
                                                   1_700_000_000 * 10**9 + 10**8]
    first = msgs[0][3]
    assert first.header.frame_id == mcap.FRAME_ID
    assert (first.header.stamp.sec, first.header.stamp.nanosec) == (1_700_000_000, 0)
    assert msgs[1][3].header.stamp.nanosec == pytest.approx(1e8, abs=1e3)
    assert (first.height, first.width) == (K, C)
    assert [f.name for f in first.fields] == NAMES
    dt = np.dtype({"names": [f.name for f in first.fields],
                   "formats": [{7: "<f4", 5: "<i4", 4: "<u2"}[f.datatype] for f in first.fields],
                   "offsets": [f.offset for f in first.fields], "itemsize": first.point_step})
    rec = np.frombuffer(bytes(first.data), dtype=dt).reshape(K, C)
    np.testing.assert_array_equal(rec["ring"], cloud.ring)
    np.testing.assert_allclose(rec["t"], cloud.t.astype(np.float32))
    np.testing.assert_array_equal(rec["flags"], cloud.flags)
    assert not first.is_dense
