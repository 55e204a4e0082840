"""Scene files: presets load, every field is validated with its name and allowed range."""

from __future__ import annotations

import numpy as np
import pytest

from cdma_lidar.errors import ConfigError
from cdma_lidar.scene import PRESETS, load_scene
from cdma_lidar.scene.scenefile import parse_scene


def _doc(**instrument):
    inst = {"wavelengths": {"count": 4}, "columns": 4, "azimuth_deg": [-1.0, 1.0]}
    inst.update(instrument)
    return {"instrument": inst, "objects": [
        {"kind": "plane", "position_m": [5.0, 0.0, 0.0]},
        {"kind": "sphere", "position_m": [3.0, 0.0, 0.0], "radius_m": 0.1},
        {"kind": "box", "position_m": [4.0, 0.0, 0.0], "size_m": [0.1, 0.1, 0.1]},
        {"kind": "sphere", "position_m": [6.0, 0.0, 0.0], "radius_m": 0.2},
    ]}


@pytest.mark.parametrize("name", PRESETS)
def test_presets_load(name):
    scene = load_scene(name)
    assert scene.name == name
    assert scene.instrument.channels == (1200 if name == "paper-massive" else 40)
    assert scene.instrument.rotations_deg.size == scene.instrument.columns


def test_paper_scene1_is_the_paper_frame():
    spec = load_scene("paper-scene1").instrument
    assert (spec.channels, spec.columns) == (40, 160)
    assert spec.chip_rate_hz == 62.5e6 and spec.code_degree == 11
    assert spec.poly_u == (11, 2) and spec.poly_v == (11, 8, 5, 2)
    assert spec.grooves_per_mm == 600.0
    # the true incidence differs from the announced nominal one
    assert spec.incidence_deg != spec.nominal_incidence_deg


def test_flat_wall_distance_option():
    a = load_scene("flat-wall?distance=7.5")
    assert a.objects[0].position_m[0] == 7.5
    b = load_scene("flat-wall", overrides={"distance": 3.25, "instrument.snr_db": 5.0})
    assert b.objects[0].position_m[0] == 3.25 and b.instrument.snr_db == 5.0


def test_bad_radius_names_the_field_and_range():
    doc = _doc()
    doc["objects"][3]["radius_m"] = -1.0
    with pytest.raises(ConfigError) as info:
        parse_scene(doc)
    assert info.value.field == "objects[3].radius_m"
    assert "objects[3].radius_m must be" in str(info.value) and "1e-06" in str(info.value)


@pytest.mark.parametrize(("change", "field"), [
    ({"adc_bits": 20}, "instrument.adc_bits"),
    ({"samples_per_chip": 0}, "instrument.samples_per_chip"),
    ({"averages": 1.5}, "instrument.averages"),
    ({"chip_rate_hz": "fast"}, "instrument.chip_rate_hz"),
    ({"laser_power_w": 1.0}, "instrument.laser_power_w"),
    ({"uid_bits": 3, "uid": 9}, "instrument.uid"),
    ({"poly_v": [10, 3]}, "instrument.poly_v"),
    ({"code_index": [0, 1]}, "instrument.code_index"),
    ({"detector_bandwidth_hz": 0.0}, "instrument.detector_bandwidth_hz"),
    ({"cancel_rounds": 5}, "instrument.cancel_rounds"),
    ({"cancel_rounds": 1.5}, "instrument.cancel_rounds"),
    ({"cancel_snr_db": 73.0}, "instrument.cancel_snr_db"),
    ({"cancel_snr_db": -1.0}, "instrument.cancel_snr_db"),
    ({"snr_db": 3.0, "noise_rms_v": 0.1}, "instrument.noise_rms_v"),
    ({"colums": 3}, "instrument.colums"),
    ({"azimuth_deg": [-80.0, 1.0]}, "instrument.azimuth_deg"),
    ({"ghosts": [{"distance_m": 3.0, "amplitude_v": 0.1, "channels": [7]}]},
     "instrument.ghosts[0].channels"),
    ({"other_users": [{"uid": 8, "amplitude_v": 0.1, "distance_m": 2.0}]},
     "instrument.other_users[0].uid"),
])
def test_instrument_fields_are_checked(change, field):
    with pytest.raises(ConfigError) as info:
        parse_scene(_doc(**change))
    assert info.value.field == field, str(info.value)
    assert str(info.value).startswith(field)


def test_object_kind_and_unknown_fields():
    doc = _doc()
    doc["objects"][0]["kind"] = "cone"
    with pytest.raises(ConfigError, match=r"objects\[0\]\.kind must be one of plane, box"):
        parse_scene(doc)
    doc = _doc()
    doc["objects"][2]["radius_m"] = 1.0  # not a box field
    with pytest.raises(ConfigError, match=r"objects\[2\]\.radius_m is not a known field"):
        parse_scene(doc)
    doc = _doc()
    doc["objects"][1]["reflectivity"] = 1.5
    with pytest.raises(ConfigError, match=r"objects\[1\]\.reflectivity must be a number from 0"):
        parse_scene(doc)


def test_unknown_scene_and_bad_toml(tmp_path):
    with pytest.raises(ConfigError, match="scene must be a preset"):
        load_scene("no-such-scene")
    bad = tmp_path / "bad.toml"
    bad.write_text("[instrument\n")
    with pytest.raises(ConfigError, match="not valid TOML"):
        load_scene(bad)
    good = tmp_path / "mine.toml"
    good.write_text('[instrument]\ncolumns = 3\n[[objects]]\nkind = "plane"\n'
                    "position_m = [2.0, 0.0, 0.0]\n")
    scene = load_scene(good)
    assert scene.name == "mine" and scene.instrument.columns == 3
    with pytest.raises(ConfigError, match="scene option"):
        load_scene("flat-wall?nonsense[=3")


def test_wavelength_list_and_rotation_list():
    scene = parse_scene({"instrument": {"wavelengths_m": [1.55e-6, 1.56e-6],
                                        "rotations_deg": [-1.0, 0.0, 1.0]}})
    assert scene.instrument.channels == 2
    np.testing.assert_array_equal(scene.instrument.rotations_deg, [-1.0, 0.0, 1.0])
