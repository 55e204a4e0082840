"""The host at 1,200 channels: the default power matrix within the caps the device states.

Issue 40: a 1,024-channel device with a 0.1 W pixel maximum refused every power matrix
the host sent ("column 0 would get 25598828 µW"): the default was a quarter of the pixel
maximum everywhere, 25.6 W a column against a 0.2 W cap.
"""

from __future__ import annotations

from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

import cdma_lidar.virtual  # noqa: F401 - registers virtual:// with pyserial
from cdma_lidar.host.connection import connect
from cdma_lidar.host.ranging import default_snr_threshold_db, mai_ceiling_db
from cdma_lidar.host.scan import ScanOptions, default_power_level, open_scan
from cdma_lidar.scene import PRESETS


def _device(k: int, pixel_uw: int, cap_uw: int) -> SimpleNamespace:
    """What default_power_level reads of a device: K and the two INFO fields."""
    return SimpleNamespace(channels=k, info=SimpleNamespace(pixel_power_max_uw=pixel_uw,
                                                            column_power_cap_uw=cap_uw))


@pytest.mark.parametrize(("k", "pixel_uw", "cap_uw", "fraction"), [
    (1024, 100_000, 200_000, 0.25),     # the device
    (1200, 100_000, 6_000_000, 0.25),   # paper-massive with a 0.1 W pixel maximum
    (1200, 10_000, 6_000_000, 0.25),    # paper-massive itself: the cap does not bind
    (40, 10_000, 200_000, 1.0),         # paper-scene1 at full power: capped at 0.5
    (7, 3, 20, 0.9),                    # a cap that is no multiple of anything
])
def test_the_default_level_is_the_largest_the_stated_caps_accept(k, pixel_uw, cap_uw, fraction):
    level = default_power_level(_device(k, pixel_uw, cap_uw), fraction)
    code = round(level * 65535)
    assert code / 65535 == level and 0 < level <= fraction
    # the device's own integer check (virtual/board.py): sum(codes) * pixel <= cap * 65535
    assert k * code * pixel_uw <= cap_uw * 65535
    assert code == int(fraction * 65535) or k * (code + 1) * pixel_uw > cap_uw * 65535


def test_no_stated_cap_leaves_the_fraction_on_the_grid():
    assert default_power_level(_device(1200, 0, 0), 0.25) == int(0.25 * 65535) / 65535
    assert default_power_level(_device(1200, 10_000, 0), 1.0) == 1.0


@pytest.fixture(scope="module")
def massive_device():
    """paper-massive (1,200 x 160) with the issue's 0.1 W pixel maximum: a 0.25 start
    would put 30 W on a column under its 6 W cap."""
    with connect("virtual://paper-massive?seed=1&instrument.max_pixel_power_w=0.1") as dev:
        yield dev


@pytest.mark.parametrize("near_far", [False, True])
def test_a_1200_by_160_scan_starts_within_the_device_caps(massive_device, tmp_path, near_far):
    dev = massive_device
    assert (dev.channels, dev.columns) == (1200, 160)
    options = ScanOptions(frames=2, near_far=near_far) if near_far else ScanOptions()
    scan = open_scan(dev, tmp_path / "m.ply", options, frame_id=1)   # refused before
    sent = dev.link.get_power().astype(np.int64)
    assert sent.shape == (1200, 160)
    column_uw = sent.sum(axis=0) * dev.info.pixel_power_max_uw / 65535
    assert column_uw.max() <= dev.info.column_power_cap_uw
    assert column_uw.min() > 0.99 * dev.info.column_power_cap_uw  # the cap, not far under
    np.testing.assert_allclose(scan._power(), sent / 65535)  # what intensity is told
    if near_far:
        assert scan._controller.limits.total_cap * dev.info.pixel_power_max_uw <= \
            dev.info.column_power_cap_uw


# ---------------------------------------------------------------------------------------
# pictures of a 1,200 x 160 frame

K, C = 1200, 160
#: ten channels, one row each, that stand out from a 10 m wall (at 5 m)
STRIPES = np.arange(50, 1200, 115)


def _massive_cloud():
    """A synthetic 1,200 x 160 frame: a wall at 10 m, two objects, ten one-channel stripes."""
    from cdma_lidar.host.cloud_formats.grid import cloud_from_records
    from cdma_lidar.host.pointcloud import empty_records

    cloud = cloud_from_records(empty_records(0), shape=(K, C))
    rng = np.random.default_rng(40)
    r = np.full((K, C), 10.0)
    r[200:500, 30:60], r[600:700, 100:120], r[STRIPES] = 5.0, 6.5, 5.0
    el, az = np.meshgrid(np.linspace(2.0, -0.6, K), np.linspace(4.9, -4.9, C), indexing="ij")
    e, a = np.deg2rad(el), np.deg2rad(az)
    cloud.range[:] = r
    cloud.x[:] = cloud.range * np.cos(e) * np.cos(a)
    cloud.y[:] = cloud.range * np.cos(e) * np.sin(a)
    cloud.z[:] = cloud.range * np.sin(e)
    cloud.snr_xc[:] = 20.0 + rng.normal(0.0, 3.0, (K, C))
    cloud.flags[:] = cloud.snr_xc < 16.0
    return cloud, el, az


@pytest.fixture(scope="module")
def massive_pictures(tmp_path_factory):
    """Every picture of a 1,200 x 160 scan, with the figures they were saved from."""
    from cdma_lidar.host import pictures
    from cdma_lidar.host.scan import picture_paths

    cloud, el, az = _massive_cloud()
    figures, save = {}, pictures._save

    def keep(fig, path):   # records the figure, then saves it as usual
        figures[Path(path).name] = fig
        save(fig, path)

    mp = pytest.MonkeyPatch()
    mp.setattr(pictures, "_save", keep)
    try:
        paths = picture_paths(tmp_path_factory.mktemp("pictures") / "m.ply")
        power = np.full((K, C), 0.25)
        files = pictures.scan_pictures(paths, cloud, [cloud.snr_xc], 16.0, title="massive",
                                       frame_titles=["frame 0", "frame 1"],
                                       angles=pictures.Angles(el, az), powers=[power, power])
        # without angles the rows are channel numbers
        pictures.depth_image(cloud, paths["depth"].with_name("m_depth_channels.png"))
    finally:
        mp.undo()
    return files, figures, paths


def test_every_axis_of_a_1200_row_picture_has_a_readable_number_of_tick_labels(
        massive_pictures):
    files, figures, _ = massive_pictures
    assert len(figures) == 7 and all(p.stat().st_size > 5000 for p in files[:-1])
    for name, fig in figures.items():
        fig.canvas.draw()
        for ax in fig.axes:
            for axis in (ax.xaxis, ax.yaxis):
                labels = [t for t in axis.get_ticklabels() if t.get_visible() and t.get_text()]
                assert len(labels) <= 12, (name, ax.get_title(), len(labels))


def _bands(column: np.ndarray, background: np.ndarray) -> int:
    """Runs of consecutive pixel rows whose colour differs from ``background``."""
    differs = np.abs(column[:, :3] - background[:3]).max(axis=1) > 0.02
    return int(np.count_nonzero(np.diff(differs.astype(int)) == 1) + differs[0])


@pytest.mark.parametrize("png", ["m_depth.png", "m_depth_channels.png"])
def test_a_one_channel_feature_of_1200_rows_shows_in_the_picture(massive_pictures, png):
    """The depth image is about 300 pixels tall for 1,200 rows: drawn by the nearest row,
    three of four channels never reach a pixel, and most one-channel stripes vanish."""
    from matplotlib.image import imread

    _, figures, paths = massive_pictures
    fig = figures[png]
    img = imread(paths["depth"].with_name(png))
    ax = fig.axes[0]
    box = ax.get_window_extent().transformed(fig.dpi_scale_trans.inverted())  # inches
    dpi = img.shape[0] / fig.get_size_inches()[1]
    col = round((box.x0 + 0.1 * box.width) * dpi)  # inside columns 0..29: wall only
    top = img.shape[0] - round(box.y1 * dpi) + 3
    bottom = img.shape[0] - round(box.y0 * dpi) - 3
    pixels = img[top:bottom, col]
    assert pixels.shape[0] < K / 3    # fewer pixel rows than channels: the case in question
    assert _bands(pixels, np.median(pixels, axis=0)) == STRIPES.size


@pytest.mark.parametrize("preset", sorted(set(PRESETS) - {"paper-massive"}))
def test_every_other_preset_keeps_the_16_db_default(preset):
    with connect(f"virtual://{preset}?seed=1") as dev:
        assert dev.ranging_config().snr_threshold_db == 16.0


def test_paper_massive_gets_the_derived_default_and_an_explicit_threshold_wins(massive_device,
                                                                                tmp_path):
    dev, cfg = massive_device, massive_device.config
    thr = dev.ranging_config().snr_threshold_db
    assert thr == default_snr_threshold_db(1200, 32767, int(cfg["samples_per_chip"]),
                                           int(cfg["gate_len"]), int(cfg["peak_exclude"]),
                                           int(cfg["uid_bits"]))
    assert thr < mai_ceiling_db(1200, 32767) < 16.0 + 0.2
    assert open_scan(dev, tmp_path / "a.npz").ranging.snr_threshold_db == thr
    explicit = open_scan(dev, tmp_path / "b.npz", ScanOptions(snr_threshold_db=16.0))
    assert explicit.ranging.snr_threshold_db == 16.0
