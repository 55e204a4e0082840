"""Calibration histogram: one narrow mode gives the offset; multimodal or wide is an error."""

from __future__ import annotations

import tomllib

import numpy as np
import pytest

from cdma_lidar.errors import CalibrationError, ConfigError
from cdma_lidar.host.calibration import Calibration, analyse_histogram

GAP, SPREAD = 0.6, 0.1
DEVICE = {"name": "virtual", "serial": "V-0001", "firmware": "1.0"}
CONFIG = {"chip_rate_hz": 62.5e6, "samples_per_chip": 4, "channels": 40,
          "poly_u": [11, 2], "poly_v": [11, 8, 5, 2], "averages": 10}


def _shots(centre: float, sigma: float, n: int = 400, seed: int = 1) -> np.ndarray:
    return np.random.default_rng(seed).normal(centre, sigma, n)


def test_offset_is_centre_minus_distance():
    vals = _shots(7.25, 0.02)
    cal = Calibration.from_ranges(vals, 1.5, shots=10, gap_m=GAP, max_spread_m=SPREAD,
                                  device=DEVICE, configuration=CONFIG)
    assert cal.offset_m == pytest.approx(7.25 - 1.5, abs=0.005)
    assert cal.spread_m == pytest.approx(0.02, rel=0.15)
    assert cal.samples == 400 and cal.shots == 10


def test_outliers_and_missing_values_are_dropped():
    vals = np.concatenate([_shots(3.0, 0.01), [40.0, 41.0, np.nan, np.nan]])
    res = analyse_histogram(vals, gap_m=GAP, max_spread_m=SPREAD)
    assert res.kept == 400 and res.outliers == 2
    assert res.centre_m == pytest.approx(3.0, abs=0.003)


def test_multimodal_histogram_is_refused():
    vals = np.concatenate([_shots(3.0, 0.01, 300), _shots(5.0, 0.01, 150, seed=2)])
    pattern = r"multimodal: 2 modes at (2\.99\d|3\.00\d) m.*5\.00\d m"
    with pytest.raises(CalibrationError, match=pattern):
        analyse_histogram(vals, gap_m=GAP, max_spread_m=SPREAD)


def test_too_wide_histogram_is_refused():
    with pytest.raises(CalibrationError, match=r"too wide: spread 0\.1[5-9]\d m exceeds 0\.100 m"):
        analyse_histogram(_shots(3.0, 0.2), gap_m=GAP, max_spread_m=SPREAD)


def test_too_few_returns():
    with pytest.raises(CalibrationError, match="usable returns"):
        analyse_histogram([np.nan] * 10 + [1.0], gap_m=GAP, max_spread_m=SPREAD)


def test_file_round_trip_and_applicability(tmp_path):
    cal = Calibration.from_ranges(_shots(4.0, 0.01), 2.0, shots=10, gap_m=GAP,
                                  max_spread_m=SPREAD, device=DEVICE, configuration=CONFIG)
    path = tmp_path / "cal.toml"
    cal.save(path)
    doc = tomllib.loads(path.read_text())
    assert doc["device"]["serial"] == "V-0001" and doc["configuration"]["channels"] == 40
    assert doc["date"].endswith("+00:00")
    back = Calibration.load(path)
    assert back.offset_m == pytest.approx(cal.offset_m)
    back.check_applies(DEVICE, {**CONFIG, "poly_u": (11, 2), "averages": 20})  # averages free
    with pytest.raises(CalibrationError, match=r"another device.*serial"):
        back.check_applies({**DEVICE, "serial": "V-0002"}, CONFIG)
    with pytest.raises(CalibrationError, match=r"another configuration.*chip_rate_hz"):
        back.check_applies(DEVICE, {**CONFIG, "chip_rate_hz": 125e6})


def test_bad_files(tmp_path):
    with pytest.raises(ConfigError, match="does not exist"):
        Calibration.load(tmp_path / "none.toml")
    (tmp_path / "bad.toml").write_text("offset_m = = 1")
    with pytest.raises(ConfigError, match="not valid TOML"):
        Calibration.load(tmp_path / "bad.toml")
    (tmp_path / "short.toml").write_text("offset_m = 1.0")
    with pytest.raises(ConfigError, match=r"lacks the field 'spread_m'.*cdma-lidar calibrate"):
        Calibration.load(tmp_path / "short.toml")
    (tmp_path / "typed.toml").write_text(
        'offset_m = "x"\nspread_m = 0.1\ntarget_distance_m = 1.0\nshots = 3\n')
    with pytest.raises(ConfigError, match="wrong type"):
        Calibration.load(tmp_path / "typed.toml")
    with pytest.raises(ConfigError, match="target_distance"):
        Calibration.from_ranges([1.0] * 10, -1.0, shots=1, gap_m=GAP, max_spread_m=SPREAD)
