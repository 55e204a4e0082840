"""The host at 1,200 channels: the default power matrix within the caps the device states.

Issue 40: a 1,024-channel device with a 0.1 W pixel maximum refused every power matrix
the host sent ("column 0 would get 25598828 µW"): the default was a quarter of the pixel
maximum everywhere, 25.6 W a column against a 0.2 W cap.
"""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

import cdma_lidar.virtual  # noqa: F401 - registers virtual:// with pyserial
from cdma_lidar.host.connection import connect
from cdma_lidar.host.scan import ScanOptions, default_power_level, open_scan


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
