"""Scene options: the fidelity levels, the link-budget fields and the effects are reachable
from a URL-style option and from the Python API; meaningless values are refused naming the
field and its allowed range."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest

from cdma_lidar.errors import ConfigError
from cdma_lidar.scene import load_scene
from cdma_lidar.scene.instrument import Instrument
from cdma_lidar.scene.linkbudget import link_gain_v_m2_per_w
from cdma_lidar.scene.model import FIDELITY_LEVELS


def test_fidelity_is_a_scene_option_with_one_list_of_levels():
    assert FIDELITY_LEVELS[0] == "exact" and "accumulated" in FIDELITY_LEVELS
    assert load_scene("flat-wall").fidelity == "exact"
    for level in FIDELITY_LEVELS:
        assert load_scene(f"flat-wall?distance=80&fidelity={level}").fidelity == level
        assert load_scene("paper-scene1", overrides={"fidelity": level}).fidelity == level
    with pytest.raises(ConfigError) as info:
        load_scene("flat-wall?fidelity=fast")
    assert info.value.field == "fidelity" and "exact, accumulated" in str(info.value)


def test_link_budget_and_effects_are_options():
    s = load_scene("flat-wall?instrument.apd_gain=20&instrument.ambient_power_w=1e-6"
                   "&instrument.speckle_cells=4&instrument.sequential_mixing=true&power=0.005")
    spec = s.instrument
    assert (spec.apd_gain, spec.ambient_power_w, spec.speckle_cells) == (20.0, 1e-6, 4.0)
    assert spec.sequential_mixing is True
    np.testing.assert_array_equal(spec.laser_power_w, 0.005)
    base = load_scene("flat-wall").instrument
    assert link_gain_v_m2_per_w(spec) == pytest.approx(2 * link_gain_v_m2_per_w(base))
    assert load_scene("flat-wall?code_degree=13").instrument.poly_u == (13, 4, 3, 1)


@pytest.mark.parametrize(("option", "field", "allowed"), [
    ("distance=-3", "scene option distance", "from 0.1 to 10000 m"),
    ("distance=0", "scene option distance", "from 0.1 to 10000 m"),
    ("reflectivity=-0.2", "scene option reflectivity", "from 0 to 1"),
    ("objects[0].reflectivity=1.5", "objects[0].reflectivity", "from 0 to 1"),
    ("power=-1", "scene option power", "from 0 to 0.01 W"),
    ("instrument.apd_gain=0.5", "instrument.apd_gain", "from 1"),
    ("instrument.tia_noise_a_per_rthz=-1e-12", "instrument.tia_noise_a_per_rthz", "from 0"),
    ("instrument.rx_aperture_m=0", "instrument.rx_aperture_m", "> 0"),
    ("instrument.speckle_cells=0.5", "instrument.speckle_cells", "0 (off)"),
    ("instrument.ambient_power_w=-1", "instrument.ambient_power_w", "from 0"),
    ("instrument.sequential_mixing=2", "instrument.sequential_mixing", "true or false"),
    ("code_degree=12", "instrument.code_degree", "degrees with preferred pairs"),
    ("instrument.averages=0", "instrument.averages", "1"),
])
def test_meaningless_values_are_refused_naming_the_field(option, field, allowed):
    with pytest.raises(ConfigError) as info:
        load_scene(f"flat-wall?{option}")
    assert info.value.field == field
    assert allowed in str(info.value)


def test_the_cli_refuses_a_negative_distance_in_one_line_with_status_2(tmp_path):
    proc = subprocess.run(
        [sys.executable, "-m", "cdma_lidar.cli", "scene", "show", "flat-wall?distance=-3"],
        capture_output=True, text=True, timeout=120)
    assert proc.returncode == 2
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and "distance must be a number from 0.1 to 10000 m" in lines[0]


def test_truth_export_has_the_link_budget_and_the_papers_snrs(tmp_path):
    out = tmp_path / "truth.npz"
    proc = subprocess.run(
        [sys.executable, "-m", "cdma_lidar.cli", "scene", "truth", "paper-scene1", "--out",
         str(out)], capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr
    with np.load(out) as z:
        lit = np.isfinite(z["range_m"])
        for key in ("rx_power_w", "signal_power_v2", "snr_db", "snr_ss_db", "snr_ss_avg_db"):
            assert z[key].shape == lit.shape
            assert np.all(np.isfinite(z[key][lit])) and np.all(np.isnan(z[key][~lit]))
        # eq. 43 adds the spreading gain and shrinks the interference: always above eq. 30
        assert np.all(z["snr_ss_db"][lit] > z["snr_db"][lit] + 10 * np.log10(2047))
        assert np.all(z["snr_ss_avg_db"][lit] >= z["snr_ss_db"][lit])
        # one pixel by hand: eq. 30 with the column's other echoes as interference
        k, c = np.argwhere(lit)[0]
        ps = z["signal_power_v2"][:, c]
        want = ps[k] / (z["noise_power_v2"][k, c] + np.nansum(ps) - ps[k])
        assert z["snr_db"][k, c] == pytest.approx(10 * np.log10(want))
    inst = Instrument(load_scene("paper-scene1"), 0)
    fig = inst.link_figures()
    np.testing.assert_allclose(fig["amplitude_v"][lit], (inst.gain_v_per_w
                                                         * inst.default_power_w)[lit])
