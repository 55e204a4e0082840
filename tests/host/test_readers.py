"""Every format the toolkit writes opens in the reader people use, at 16, 160 and 1,200 rows.

Open3D for .ply and .pcd (legacy and tensor readers), laspy for .las, the mcap ROS 2
reader for .mcap and rerun's own reader for the viewer's .rrd, each on a synthetic
K x 160 cloud (K = 16, 160, 1,200 channels; some pixels rejected). Open3D aborts the
whole process on a header line longer than RPly's 1,024 characters (issue 43: the PLY's
``angles_deg`` comment of a 160-column scan), so it reads in a child process: a crash
there is this test failing, not the test run dying.
"""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest

from cdma_lidar.host.cloud_formats import write_frames
from cdma_lidar.host.pointcloud import (
    FIELD_UNITS,
    POINT_FIELDS,
    PointCloud,
    assemble,
    file_metadata,
)
from cdma_lidar.host.ranging import FLAG_REJECTED, RangeImage
from cdma_lidar.host.uid_filter import ForeignReturns
from cdma_lidar.optics.grating import GratingGeometry

COLUMNS = 160
ROWS = (16, 160, 1200)
NAMES = [n for n, _ in POINT_FIELDS]


def synthetic(k: int, c: int = COLUMNS, seed: int = 5) -> PointCloud:
    """A K x C cloud, about 10 % of its pixels rejected, stamped."""
    rng = np.random.default_rng(seed)
    r = rng.uniform(1.0, 9.0, (k, c))
    flags = np.where(rng.random((k, c)) < 0.1, FLAG_REJECTED, 0).astype(np.uint8)
    r[flags != 0] = np.nan
    empty = np.zeros(0, np.int64)
    image = RangeImage(range_m=r, lag=r / 0.6, snr_xc_db=rng.uniform(5, 40, (k, c)),
                       peak=rng.integers(-5000, 5000, (k, c)), flags=flags,
                       foreign=ForeignReturns(empty, empty, empty, empty, empty, empty,
                                              np.zeros(0)))
    return assemble(image, GratingGeometry(), np.linspace(1540e-9, 1570e-9, k),
                    np.linspace(-4, 4, c), intensity=rng.uniform(0, 2, (k, c)),
                    timestamps_us=np.arange(c) * 50, stamp_unix_s=1.7e9)


@pytest.fixture(scope="module", params=ROWS, ids=[f"{k}rows" for k in ROWS])
def files(request, tmp_path_factory):
    """(cloud, {extension: path}) of one synthetic cloud in every format."""
    k = request.param
    cloud = synthetic(k)
    folder = tmp_path_factory.mktemp(f"rows{k}")
    meta = file_metadata(17.5, "reflectance")
    paths = {ext: folder / f"cloud{ext}" for ext in (".ply", ".pcd", ".las", ".mcap")}
    for path in paths.values():
        write_frames([cloud], path, meta)
    return cloud, paths


#: Reads each file named on the command line with Open3D's legacy and tensor readers;
#: prints {path: [legacy points, tensor points, {field: values}]} as JSON.
_OPEN3D = """
import json, sys
import open3d as o3d
out = {}
for path in sys.argv[1:]:
    legacy = o3d.io.read_point_cloud(path, remove_nan_points=False)
    pc = o3d.t.io.read_point_cloud(path, remove_nan_points=False)
    fields = {n: pc.point[n].numpy().ravel().tolist() for n in ("range", "ring", "column")
              if n in pc.point}
    out[path] = [len(legacy.points), int(pc.point.positions.shape[0]), fields]
print(json.dumps(out))
"""


def test_open3d_reads_ply_and_pcd(files) -> None:
    cloud, paths = files
    proc = subprocess.run([sys.executable, "-c", _OPEN3D, str(paths[".ply"]),
                           str(paths[".pcd"])], capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, f"Open3D ended {proc.returncode}: {proc.stderr[-1500:]}"
    got = json.loads(proc.stdout.splitlines()[-1])
    ok = cloud.has_range
    for ext, rows in ((".ply", ok), (".pcd", np.ones_like(ok))):
        legacy, tensor, fields = got[str(paths[ext])]
        assert legacy == tensor == int(rows.sum()), ext
        np.testing.assert_array_equal(fields["ring"], cloud.ring[rows], err_msg=ext)
        np.testing.assert_array_equal(fields["column"], cloud.column[rows], err_msg=ext)
        np.testing.assert_allclose(fields["range"], cloud.range[rows].astype(np.float32),
                                   err_msg=ext)


def test_our_ply_header_lines_fit_rply(files) -> None:
    """Every header line under RPly's 1,024 characters, and the long lists come back."""
    from cdma_lidar.host.cloud_formats import read_frames

    cloud, paths = files
    raw = paths[".ply"].read_bytes()
    header = raw[:raw.index(b"end_header\n")].split(b"\n")
    assert max(map(len, header)) < 1024
    back = read_frames(paths[".ply"])[0]
    np.testing.assert_array_equal(back.angles_deg, cloud.angles_deg)
    np.testing.assert_array_equal(back.wavelengths_m, cloud.wavelengths_m)


def test_laspy_reads_las_with_descriptions_and_intensity_scale(files) -> None:
    import laspy  # in the las and test extras

    cloud, paths = files
    las = laspy.read(str(paths[".las"]))
    ok = cloud.has_range
    assert len(las.points) == int(ok.sum())
    np.testing.assert_array_equal(np.asarray(las.ring), cloud.ring[ok])
    np.testing.assert_allclose(np.asarray(las.x), cloud.x[ok], atol=1e-4)
    extra = {d.name: d.description for d in las.point_format.extra_dimensions}
    assert set(extra) == set(NAMES) - {"x", "y", "z", "intensity"}
    for name, description in extra.items():
        assert description.startswith(FIELD_UNITS[name][0][:8]), (name, description)
    (vlr,) = [v for v in las.header.vlrs if v.user_id == "cdma_lidar"]
    meta = json.loads(vlr.record_data)
    assert meta["intensity_scale"] == 4096 and meta["snr_threshold_db"] == 17.5
    assert meta["field_units"]["range"] == "m" and meta["cdma_lidar_version"]
    assert las.header.generating_software.startswith("cdma-lidar ")
    np.testing.assert_allclose(np.asarray(las.intensity) / meta["intensity_scale"],
                               cloud.intensity[ok], atol=0.5 / 4096)


def test_mcap_ros2_reader_reads_pointcloud2_with_units_threshold_version(files) -> None:
    from mcap.reader import make_reader
    from mcap_ros2.decoder import DecoderFactory  # the mcap ROS 2 reader's decoder

    cloud, paths = files
    with open(paths[".mcap"], "rb") as fh:
        reader = make_reader(fh, decoder_factories=[DecoderFactory()])
        ((*_, pc2),) = list(reader.iter_decoded_messages(topics=["/cdma_lidar/points"]))
    assert (pc2.height, pc2.width) == cloud.shape
    assert [f.name for f in pc2.fields] == NAMES
    assert len(pc2.data) == pc2.row_step * pc2.height
    with open(paths[".mcap"], "rb") as fh:
        (meta,) = [m.metadata for m in make_reader(fh).iter_metadata()]
    assert json.loads(meta["snr_threshold_db"]) == 17.5
    assert json.loads(meta["field_units"]) == {
        n: ("reflectance" if u == "intensity_unit" else u) for n, (u, _) in FIELD_UNITS.items()}
    assert json.loads(meta["cdma_lidar_version"])


def test_rerun_reads_the_viewers_recording(files, tmp_path) -> None:
    rr = pytest.importorskip("rerun", reason="rerun-sdk is in the test extra")
    from rerun.chunk import RrdReader

    from cdma_lidar.host.view import LiveView, ViewOptions

    cloud, _ = files
    rrd = tmp_path / "cloud.rrd"
    live = LiveView(ViewOptions(save=str(rrd)), rr=rr)
    live.log_frame(0, cloud, np.full(cloud.shape, 0.5))
    live.close()
    points = [c for c in RrdReader(rrd).stream()
              if c.entity_path.lstrip("/") == "cloud" and not c.is_static]
    batch = points[0].to_record_batch()
    col = next(n for n in batch.schema.names if n.endswith("Points3D:positions"))
    assert len(batch.column(col)[0]) == int(cloud.has_range.sum())
