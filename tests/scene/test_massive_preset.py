"""The ``paper-massive`` preset and the two scene-file shorthands it needs.

``wavelengths = { start_m, stop_m, count }`` spreads the comb over a band (the spacing
follows the count) and ``total_power_cap_per_channel_w`` states the column cap per channel
(so it scales with K).
"""

from __future__ import annotations

import numpy as np
import pytest

from cdma_lidar.errors import ConfigError
from cdma_lidar.scene import load_scene
from cdma_lidar.scene.scenefile import parse_scene


def test_paper_massive_is_the_order_15_instrument_over_the_c_and_l_bands():
    spec = load_scene("paper-massive").instrument
    assert (spec.channels, spec.columns, spec.code_degree) == (1200, 160, 15)
    assert spec.samples_per_chip == 2 and spec.chip_rate_hz == 62.5e6
    assert spec.wavelengths_m[0] == 1530e-9 and spec.wavelengths_m[-1] == pytest.approx(1605e-9)
    assert spec.total_power_cap_w == pytest.approx(1200 * 5e-3)


def test_fewer_channels_keep_the_band_and_scale_the_cap():
    spec = load_scene("paper-massive?channels=400&columns=2").instrument
    assert (spec.channels, spec.columns) == (400, 2)
    assert spec.wavelengths_m[-1] == pytest.approx(1605e-9)
    np.testing.assert_allclose(np.diff(spec.wavelengths_m), 75e-9 / 399)
    assert spec.total_power_cap_w == pytest.approx(400 * 5e-3)


def test_paper_massive_has_objects_from_5_to_10_m_over_many_rows():
    from cdma_lidar.scene.truth import compute_truth

    r = compute_truth(load_scene("paper-massive?columns=40")).range_m
    for lo, hi in ((4.9, 5.2), (6.3, 6.7), (7.8, 8.3), (9.9, 10.6)):
        rows = np.unique(np.nonzero((r > lo) & (r < hi))[0])
        assert rows.size > 200, (lo, hi)


@pytest.mark.parametrize(("instrument", "field"), [
    ({"wavelengths": {"start_m": 1.53e-6, "stop_m": 1.6e-6, "spacing_m": 1e-9}},
     "instrument.wavelengths.spacing_m"),
    ({"wavelengths": {"count": 4000}}, "instrument.wavelengths.count"),
    ({"total_power_cap_per_channel_w": 5e-3, "total_power_cap_w": 1.0},
     "instrument.total_power_cap_w"),
    ({"total_power_cap_per_channel_w": 0.0}, "instrument.total_power_cap_per_channel_w"),
    ({"total_power_cap_per_channel_w": 1e-3}, "instrument.laser_power_w"),
])
def test_bad_band_or_cap_names_the_field(instrument, field):
    with pytest.raises(ConfigError) as info:
        parse_scene({"instrument": instrument})
    assert info.value.field == field
