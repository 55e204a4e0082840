"""The one acquisition path (scene.acquire): the device and the studies run the same
receiver configuration, power and draws, so a study frame is the device's scan."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from cdma_lidar.column_record import RECORD
from cdma_lidar.firmware_model.receiver import FastReceiver
from cdma_lidar.scene import PRESETS, load_scene
from cdma_lidar.scene.acquire import (
    acquire,
    boot_power_codes,
    out_bits_for_gate,
    power_w_of_codes,
    receiver_config,
)
from cdma_lidar.scene.instrument import Instrument, RenderSettings
from cdma_lidar.study.simulate import simulate_frame
from cdma_lidar.virtual.board import VirtualFirmware

WALL = "flat-wall?distance=6&instrument.columns=5&instrument.wavelengths.count=6"


def test_out_bits_keep_the_noise_sum_of_squares_in_63_bits():
    assert [out_bits_for_gate(g) for g in (1, 64, 128, 255, 256, 8188)] == [32, 29, 28, 28,
                                                                              28, 26]
    for gate in (1, 100, 128, 4096, 2**20):
        b = out_bits_for_gate(gate)
        assert 2 * b - 2 + gate.bit_length() <= 63 or b == 8


@pytest.mark.parametrize("scene", [WALL, "multi-user?instrument.columns=3",
                                   WALL + "&instrument.cancel_rounds=3"
                                   "&instrument.cancel_snr_db=13.5"])
def test_the_device_boots_with_the_receiver_configuration_every_study_uses(scene):
    fw = VirtualFirmware(load_scene(scene), 2)
    cfg, codes = receiver_config(fw.instrument)
    assert fw._receiver_config(fw.get_config()) == cfg
    assert np.array_equal(fw.receiver().codes, codes)
    assert np.array_equal(fw.get_power(), boot_power_codes(fw.instrument))
    assert np.array_equal(fw.power_w(), power_w_of_codes(fw.spec, fw.get_power()))


def test_the_scene_sets_the_receive_chains_interference_cancellation():
    """Two optional [instrument] keys (default: none, 16 dB) become the chain's rounds and
    its Q8 power ratio; paper-massive cancels twice at 13.5 dB, no other preset at all."""
    def chain(name: str) -> tuple[int, int]:
        cfg, _ = receiver_config(Instrument(load_scene(name), seed=0))
        return cfg.cancel_rounds, cfg.cancel_snr_q8

    assert chain(WALL) == (0, 10192)
    assert chain(WALL + "&instrument.cancel_rounds=4&instrument.cancel_snr_db=10") == (4, 2560)
    assert chain("paper-massive?channels=8&columns=2") == (2, 5731)
    assert [n for n in PRESETS if load_scene(n).instrument.cancel_rounds] == ["paper-massive"]


def test_a_study_frame_equals_the_devices_scan_pixel_for_pixel():
    """simulate_frame (no device, no protocol) against the board's scan of the same
    scene, seed and frame id: every record field of every pixel."""
    scan = list(VirtualFirmware(load_scene(WALL), 3).scan(2, 0, 5))
    study = simulate_frame(WALL, seed=3, frame=2).frame
    for f in RECORD:
        got = getattr(study, f.name)
        for col in scan:
            np.testing.assert_array_equal(got[:, col.column], getattr(col, f.name),
                                          err_msg=f.name)
    assert study.done.all()
    other = simulate_frame(WALL, seed=3, frame=1).frame
    assert not np.array_equal(other.noise_sum, study.noise_sum)


def test_acquire_gives_each_column_its_own_draws_whatever_the_batch():
    inst = Instrument(load_scene(WALL), 1)
    settings = RenderSettings.from_spec(inst.spec)
    rx = FastReceiver(*receiver_config(inst))
    power = [inst.default_power_w[:, c] for c in range(inst.columns)]
    whole = acquire(inst, rx, settings, 4, list(range(5)), power)
    parts = [acquire(inst, rx, settings, 4, cols, [power[c] for c in cols])
             for cols in ([3, 0], [4, 1, 2])]
    by_column = dict(zip([3, 0, 4, 1, 2], [o for p in parts for o in p.outputs], strict=True))
    for c, out in enumerate(whole.outputs):
        assert out.same_as(by_column[c]), c
    assert whole.drawn.dtype == bool and whole.drawn.shape == (5,)
    assert whole.render_cpu_s >= 0 and whole.receive_cpu_s >= 0
    assert dataclasses.is_dataclass(whole)
