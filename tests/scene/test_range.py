"""Range sweeps fail where physics says: a flat wall at fixed emitted power and fixed receiver
noise gives a valid fraction that falls with distance and reaches 0 within a few hundred
metres; more averages and longer codes push the limit out (eqs. 27, 43, Fig. 2f)."""

from __future__ import annotations

import itertools

import numpy as np
import pytest

from cdma_lidar.host.frame import FrameData
from cdma_lidar.host.ranging import RangingConfig, estimate_ranges
from cdma_lidar.scene import load_scene
from cdma_lidar.scene.instrument import Instrument
from cdma_lidar.units import SPEED_OF_LIGHT_M_S
from cdma_lidar.virtual.board import VirtualFirmware

COLUMNS = 8


def _valid_fraction(distance_m: float, seed: int = 1, **options: object) -> float:
    """Fraction of pixels the host accepts with a range within 30 cm of the truth."""
    scene = load_scene("flat-wall", overrides={"distance": distance_m,
                                               "instrument.columns": COLUMNS, **options})
    fw = VirtualFirmware(scene, seed)
    spec = scene.instrument
    cfg = fw.get_config()
    data = FrameData.from_columns(fw.scan(1, 0, fw.columns), fw.channels, fw.columns)
    rc = RangingConfig(samples_per_chip=cfg["samples_per_chip"], chip_rate_hz=spec.chip_rate_hz,
                       code_length=spec.code_length,
                       offset_m=spec.system_delay_s * SPEED_OF_LIGHT_M_S / 2)
    image = estimate_ranges(data, rc)
    correct = image.valid & (np.abs(image.range_m - fw.instrument.truth.range_m) < 0.3)
    return float(np.mean(correct))


def test_the_valid_fraction_falls_with_distance_and_reaches_zero():
    distances = [5.0, 10.0, 15.0, 20.0, 30.0, 60.0, 300.0]
    valid = [_valid_fraction(d) for d in distances]
    assert valid[0] > 0.95
    # monotonic: never more than 2 points up from one distance to the next (seed noise)
    assert all(b <= a + 0.02 for a, b in itertools.pairwise(valid)), valid
    assert valid[-3:] == [0.0, 0.0, 0.0], valid


@pytest.mark.parametrize("push", [{"averages": 40}, {"code_degree": 13}],
                         ids=["4x-averages", "4x-code-length"])
def test_more_averages_and_longer_codes_push_the_range_out(push):
    """At 18 m the default instrument keeps under a third of its pixels; 4x the averages
    (6 dB on the noise) or a 4x longer code (6 dB on noise and interference) keeps most."""
    base = _valid_fraction(18.0)
    pushed = _valid_fraction(18.0, **push)
    assert base < 0.35
    assert pushed > base + 0.4, (base, pushed)


def test_eq43_grows_with_the_code_length_and_eq30_falls_with_distance():
    near = Instrument(load_scene("flat-wall", overrides={"distance": 5.0}), 0).link_figures()
    far = Instrument(load_scene("flat-wall", overrides={"distance": 50.0}), 0).link_figures()
    long = Instrument(load_scene("flat-wall", overrides={"distance": 50.0, "code_degree": 13}),
                      0).link_figures()
    # 10x the distance: 1/r^2 in amplitude, 40 dB in signal power
    np.testing.assert_allclose(far["signal_power_v2"], near["signal_power_v2"] / 1e4,
                               rtol=1e-3)
    assert np.nanmedian(far["snr_db"]) < np.nanmedian(near["snr_db"]) - 20
    # noise-limited at 50 m: eq. 43 gains the spreading gain ratio 8191 / 2047 (6.02 dB)
    gain = np.nanmedian(long["snr_ss_db"]) - np.nanmedian(far["snr_ss_db"])
    assert gain == pytest.approx(10 * np.log10(8191 / 2047), abs=0.3)


def test_the_echo_falls_as_one_over_r_squared_and_the_noise_stays():
    a = Instrument(load_scene("flat-wall", overrides={"distance": 4.0}), 0)
    b = Instrument(load_scene("flat-wall", overrides={"distance": 8.0}), 0)
    ratio = b.gain_v_per_w[a.truth.hits.lit] / a.gain_v_per_w[a.truth.hits.lit]
    np.testing.assert_allclose(ratio, 0.25, rtol=1e-3)
    # only the signal's own shot noise changes with distance: a few per cent of the total
    assert b.noise_rms_v == pytest.approx(a.noise_rms_v, rel=0.15)
    assert b.noise_rms_v < a.noise_rms_v
