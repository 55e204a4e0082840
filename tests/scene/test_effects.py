"""Effects switchable in the scene file: speckle, ambient light, sequential mixing (Note 4);
each off by default and each changing what the link budget says it changes."""

from __future__ import annotations

import numpy as np
import pytest

from cdma_lidar.scene import load_scene
from cdma_lidar.scene.instrument import Instrument, RenderSettings
from cdma_lidar.scene.noise import ELEMENTARY_CHARGE_C, apd_excess_noise

WALL = "flat-wall?distance=5&instrument.columns=64"


def test_effects_are_off_by_default():
    spec = load_scene("paper-scene1").instrument
    assert (spec.speckle_cells, spec.ambient_power_w, spec.sequential_mixing) == (0.0, 0.0,
                                                                                  False)
    assert Instrument(load_scene("paper-scene1"), 0).speckle is None


@pytest.mark.parametrize("cells", [1.0, 4.0])
def test_speckle_fades_each_pixel_with_the_gamma_statistics(cells):
    plain = Instrument(load_scene(WALL), 0)
    inst = Instrument(load_scene(f"{WALL}&instrument.speckle_cells={cells}"), 0)
    lit = plain.truth.hits.lit
    fade = inst.gain_v_per_w[lit] / plain.gain_v_per_w[lit]  # power (and amplitude) factor
    assert fade.size == 40 * 64
    assert fade.mean() == pytest.approx(1.0, abs=4 / np.sqrt(cells * fade.size))
    assert fade.var() == pytest.approx(1 / cells, rel=0.15)
    # a static scene: the same pattern in every frame, a new one for another seed
    again = Instrument(load_scene(f"{WALL}&instrument.speckle_cells={cells}"), 0)
    np.testing.assert_array_equal(again.speckle, inst.speckle)
    other = Instrument(load_scene(f"{WALL}&instrument.speckle_cells={cells}"), 1)
    assert not np.array_equal(other.speckle, inst.speckle)


def test_ambient_light_adds_its_shot_noise():
    amb = 2e-6  # W on the photodiode
    dark = Instrument(load_scene(WALL), 0)
    sunny = Instrument(load_scene(f"{WALL}&instrument.ambient_power_w={amb}"), 0)
    spec = sunny.spec
    gm = sunny.budget.volts_per_rx_w / spec.responsivity_a_per_w
    b = spec.chip_rate_hz * spec.samples_per_chip / 2
    want = gm**2 * 2 * ELEMENTARY_CHARGE_C * apd_excess_noise(spec.apd_gain, spec.apd_k_ratio) \
        * spec.responsivity_a_per_w * amb * b
    assert sunny.noise_rms_v**2 - dark.noise_rms_v**2 == pytest.approx(want, rel=1e-9)
    # and the samples carry it: measured variance of a column follows
    cfg = RenderSettings.from_spec(spec)
    for inst in (dark, sunny):
        echo, sigma = inst.column_model(3, cfg)
        raw = inst.render_exact(3, cfg, 0).astype(float)
        lsb = spec.adc_full_scale_v / (1 << (spec.adc_bits - 1))
        resid = raw.reshape(cfg.averages, -1) * lsb - echo[None, :]
        assert resid.std() == pytest.approx(np.hypot(sigma, lsb / np.sqrt(12)), rel=0.02)


def test_sequential_mixing_adds_the_signal_independent_noise_k_times():
    """Note 4, eq. 20: summing K sequential records adds their noise K times (K = 40)."""
    par = Instrument(load_scene(WALL), 0)
    seq = Instrument(load_scene(f"{WALL}&instrument.sequential_mixing=true"), 0)
    p = par.default_power_w
    a = par.noise.terms(p, par.budget.rx_per_w, 4)
    b = seq.noise.terms(p, seq.budget.rx_per_w, 4)
    for key in ("thermal", "dark", "ambient", "ase"):
        np.testing.assert_allclose(b[key], 40 * a[key])
    np.testing.assert_allclose(b["signal_shot"], a["signal_shot"])  # each record its own
    # eq. 30 of a lone channel falls by nearly 10 log10(K) where the noise dominates: K = 8
    # channels recorded one at a time, only channel 0 lit (the signal shot noise stays)
    one = "&instrument.wavelengths.count=8&objects[0].position_m=[5.0, 0.0, 0.0519]" \
          "&objects[0].size_m=[20.0, 0.002]"
    lone = Instrument(load_scene(WALL + one), 0)
    lone_par = lone.link_figures()["snr_db"]
    assert lone.truth.hits.lit.sum(axis=0).max() <= 1
    lone_seq = Instrument(load_scene(WALL + one + "&instrument.sequential_mixing=true"),
                          0).link_figures()["snr_db"]
    drop = np.nanmedian(lone_par) - np.nanmedian(lone_seq)
    assert 8.0 < drop < 10 * np.log10(8) + 0.01
