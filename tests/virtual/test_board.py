"""The virtual device end to end: virtual:// through HostLink, limits and NAKs, power caps,
calibration, capture, line errors, determinism, and the pty server as a subprocess."""

from __future__ import annotations

import contextlib
import math
import os
import select
import signal
import subprocess
import sys
import time

import numpy as np
import pytest
import serial
from hypothesis import given, settings
from hypothesis import strategies as st

import cdma_lidar.virtual  # noqa: F401 - registers virtual:// with pyserial
from cdma_lidar.errors import ConfigError, DeviceError, LinkError
from cdma_lidar.firmware_model.snr import snr_xc_db
from cdma_lidar.protocol.endpoint import DeviceApp, Engine
from cdma_lidar.protocol.link import HostLink
from cdma_lidar.protocol.ports import open_port
from cdma_lidar.scene import load_scene
from cdma_lidar.units import SPEED_OF_LIGHT_M_S
from cdma_lidar.virtual.board import VirtualFirmware

FS = 62.5e6 * 4
# a quieter receiver than the default (about 6 mV of noise against 2 mV echoes at 7.5 m),
# so that echo ratios are measured to a few per cent in one column
URL = ("virtual://flat-wall?seed=3&distance=7.5&instrument.wavelengths.count=8&instrument.columns=4"
       "&instrument.tia_noise_a_per_rthz=3e-12")


@pytest.fixture
def link():
    with HostLink(open_port(URL), timeout_s=1.0) as lk:
        lk.hello()
        yield lk


def _true_lags(distance_m):
    return (2 * distance_m / SPEED_OF_LIGHT_M_S + 37.3e-9) * FS


def test_virtual_firmware_is_a_device_app():
    assert isinstance(VirtualFirmware(load_scene("calibration"), 0), DeviceApp)


def test_importing_the_virtual_package_registers_its_url_scheme():
    import cdma_lidar.virtual as virtual  # the import under test (already done by the board)

    assert serial.protocol_handler_packages.count(virtual.URL_HANDLER_PACKAGE) == 1
    port = serial.serial_for_url("virtual://calibration?seed=1", timeout=0.1)
    try:
        assert port.is_open and port.in_waiting == 0
        assert port.read(1) == b""  # nothing unless asked
    finally:
        port.close()
    with pytest.raises(serial.SerialException, match="scene must be a preset"):
        serial.serial_for_url("virtual://nowhere")


@pytest.mark.parametrize(("query", "words"), [
    ("seed=-1", "seed must be a non-negative integer"),
    ("line_seed=-2", "line_seed must be a non-negative integer"),
    ("seed=abc", "seed='abc' is not a number"),
    ("line_error_rate=2", "line_error_rate must be a probability from 0 to 0.5"),
    ("line_baud=0", "baud must be an integer from 1 to"),
    ("bogus=3", "bogus is not a known field"),
])
def test_bad_url_options_name_the_option(query, words):
    with pytest.raises(LinkError, match=words):
        open_port(f"virtual://flat-wall?{query}")


def test_handshake_reports_what_the_host_needs(link):
    info = link.info
    assert info.channels == 8 and info.column_count == 4
    assert info.chip_rate_hz == 62_500_000
    assert info.incidence_deg == pytest.approx(60.0)  # nominal, not the true 60.02
    assert info.grooves_per_mm == pytest.approx(600.0)
    spec = load_scene(URL.split("://")[1].replace("flat-wall?seed=3&", "flat-wall?")).instrument
    np.testing.assert_allclose(info.column_angles_deg, spec.rotations_deg, atol=2e-6)
    np.testing.assert_allclose(info.wavelengths_m, spec.wavelengths_m, atol=1e-12)
    cfg = link.get_config()
    assert cfg["samples_per_chip"] == 4 and cfg["averages"] == 10
    assert cfg["gate_len"] >= 128


def test_scan_through_hostlink_ranges_the_wall(link):
    cols = list(link.scan())
    assert [c.column for c in cols] == [0, 1, 2, 3]
    lags = np.array([c.peak_lag for c in cols])
    assert np.all(np.abs(lags - _true_lags(7.5)) <= 1)
    snr = np.array([snr_xc_db(c.peak, c.noise_count, c.noise_sum, c.noise_sumsq) for c in cols])
    assert np.all(snr > 15)
    # several scans in a row
    again = list(link.scan(frames=2))
    assert len(again) == 8


def test_same_seed_same_results_across_devices():
    results = []
    for _ in range(2):
        with HostLink(open_port(URL), timeout_s=1.0) as lk:
            lk.hello()
            results.append([c.records.tobytes() for c in lk.scan(frame=1234)])
    assert results[0] == results[1]
    with HostLink(open_port(URL.replace("seed=3", "seed=4")), timeout_s=1.0) as lk:
        lk.hello()
        other = [c.records.tobytes() for c in lk.scan(frame=1234)]
    assert other != results[0]


@pytest.mark.parametrize("level", ["exact", "accumulated"])
def test_scans_that_share_the_boards_sums_array_keep_their_results(level):
    """The board renders every batch into one array: results already handed out, and a
    scan interleaved with another, are what a fresh board gives (nothing refers to it)."""
    scene = load_scene(f"flat-wall?instrument.columns=6&fidelity={level}")
    fw, fresh = VirtualFirmware(scene, 3), VirtualFirmware(scene, 3)
    first = [c.records.tobytes() for c in fw.scan(1, 0, 6)]
    one, two = fw.scan(1, 0, 6), fw.scan(2, 0, 6)  # generators, run alternately
    mixed = [(a.records.tobytes(), b.records.tobytes()) for a, b in zip(one, two, strict=True)]
    assert first == [c.records.tobytes() for c in fresh.scan(1, 0, 6)]
    assert [a for a, _ in mixed] == first
    assert [b for _, b in mixed] == [c.records.tobytes() for c in fresh.scan(2, 0, 6)] != first


def test_config_limits_are_refused_with_the_field(link):
    for change, field in [({"averages": 5000}, "averages"), ({"samples_per_chip": 40},
                                                            "samples_per_chip"),
                          ({"code_index": list(range(7))}, "code_index"),
                          ({"gate_start": 2047 * 4}, "gate_start"),
                          ({"uid_bits": 3, "uid": 8}, "uid")]:
        with pytest.raises(DeviceError) as info:
            link.set_config(**change)
        assert info.value.field == field
    # all or nothing: the refused keys did not change anything
    assert link.get_config()["averages"] == 10
    link.set_config(averages=4, peaks=2, gate_len=96)
    cfg = link.get_config()
    assert (cfg["averages"], cfg["peaks"], cfg["gate_len"]) == (4, 2, 96)
    cols = list(link.scan(columns=1))
    assert cols[0].peaks == 2


def test_power_matrix_scales_the_echo_and_the_caps_hold(link):
    (base_col,) = link.scan(columns=1)
    base = base_col.peak.astype(float)
    power = np.full((8, 4), 0.125)  # default is 2.5 mW of 10 mW max = 0.25
    link.set_power(power)
    (half_col,) = link.scan(columns=1)
    half = half_col.peak.astype(float)
    np.testing.assert_allclose(half / base, 0.5, rtol=0.1)
    link.set_power(np.ones((8, 4)))  # 8 x 10 mW per column: under the 0.2 W cap
    (full_col,) = link.scan(columns=1)
    full = full_col.peak.astype(float)
    np.testing.assert_allclose(full / base, 4.0, rtol=0.1)
    with pytest.raises(DeviceError) as info:
        link.set_power(np.ones((2, 2)), channel_start=7)
    assert info.value.field == "channel_start"


def test_total_eye_safety_cap():
    scene = load_scene("flat-wall", overrides={"instrument.total_power_cap_w": 0.05,
                                               "instrument.laser_power_w": 1e-3})
    fw = VirtualFirmware(scene, 0)
    with pytest.raises(ConfigError) as info:
        fw.set_power(0, 0, np.full((40, 16), 65535, dtype=np.uint16))
    assert info.value.field == "power"
    assert "eye-safety" in str(info.value)
    fw.set_power(0, 0, np.full((40, 16), 1000, dtype=np.uint16))  # 40 x 0.15 mW is fine
    url = ("virtual://flat-wall?instrument.total_power_cap_w=0.05&instrument.laser_power_w=1e-3"
           "&instrument.columns=2")
    with HostLink(open_port(url), timeout_s=1.0) as lk:
        lk.hello()
        with pytest.raises(DeviceError) as nak:
            lk.set_power(np.ones((40, 2)))
        assert nak.value.field == "power" and "eye-safety" in str(nak.value)


def test_calibration_sees_the_zeroth_order_target(link):
    shots = link.calibrate(6)
    assert len(shots) == 6 and all(s.calibration for s in shots)
    assert [s.column for s in shots] == list(range(6))
    lags = np.array([s.peak_lag for s in shots])
    target = load_scene("flat-wall").calibration.target_distance_m
    assert np.all(np.abs(lags - _true_lags(target)) <= 1)
    assert shots[0].angle_deg == pytest.approx(90.0)


def test_capture_raw_and_correlation(link):
    cols = list(link.scan(columns=1))
    raw = link.capture("raw", 0)
    assert raw.size == 10 * 2047 * 4 and raw.dtype == np.int16
    corr = link.capture("corr", 0, 5)
    cfg = link.get_config()
    assert corr.size == cfg["gate_len"]
    j = int(np.argmax(np.abs(corr)))
    assert (cfg["gate_start"] + j) == cols[0].peak_lag[5]
    assert int(corr[j]) == cols[0].peak[5]


def test_line_errors_lose_nothing():
    with HostLink(open_port(URL), timeout_s=0.5) as lk:
        lk.hello()
        clean = [c.records.tobytes() for c in lk.scan(frame=77)]
    url = URL + "&line_error_rate=2e-4&line_seed=9"
    with HostLink(open_port(url), timeout_s=0.5, retries=8) as lk:
        lk.hello()
        for _ in range(3):
            cols = list(lk.scan(frame=77))
            assert [c.column for c in cols] == [0, 1, 2, 3]
            # the same frame id through a clean line: the same, intact results
            assert [c.records.tobytes() for c in cols] == clean
        port = lk.port
        assert port._noise.flipped + port._noise_up.flipped > 0  # errors really were injected
        st = lk.decoder.stats  # damage: corrected by the Reed-Solomon code, or dropped
        assert (lk.coded and st.corrected + st.errors > 0) or lk.stats.retries > 0
    # The same through a line with a UART's pace (and errors): still the same results.
    with HostLink(open_port(url + "&line_baud=2000000"), timeout_s=0.5, retries=8) as lk:
        lk.hello()
        assert lk.port._to_device.baud == 2_000_000
        assert [c.records.tobytes() for c in lk.scan(frame=77)] == clean


def test_uid_scene_reports_our_uid():
    url = ("virtual://multi-user?seed=2&instrument.wavelengths.count=4&instrument.columns=2"
           "&instrument.averages=2")
    with HostLink(open_port(url), timeout_s=1.0) as lk:
        lk.hello()
        cfg = lk.get_config()
        assert (cfg["uid_bits"], cfg["uid"]) == (3, 1)
        cols = list(lk.scan())
    assert all(bool(c.uid_match[0]) and int(c.uid_observed[0]) == 1 for c in cols)


def _readline(proc, timeout_s=60.0):
    deadline = time.monotonic() + timeout_s
    buf = b""
    fd = proc.stdout.fileno()
    while not buf.endswith(b"\n"):
        left = deadline - time.monotonic()
        assert left > 0, "device did not print its pty path"
        r, _, _ = select.select([fd], [], [], left)
        if r:
            chunk = os.read(fd, 1)
            assert chunk, proc.stderr.read().decode()
            buf += chunk
    return buf.decode().strip()


@contextlib.contextmanager
def _device_process(cmd):
    """Run ``cdma-lidar device ...``; on exit stop it with SIGTERM and expect status 0."""
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    try:
        yield proc
    finally:
        proc.send_signal(signal.SIGTERM)
        try:
            rc = proc.wait(timeout=20)
        finally:
            if proc.poll() is None:
                proc.kill()
    assert rc == 0


def test_pty_device_end_to_end():
    cmd = [sys.executable, "-m", "cdma_lidar.cli", "device", "--scene",
           "flat-wall?instrument.wavelengths.count=4&instrument.columns=3", "--pty",
           "--seed", "5"]
    with _device_process(cmd) as proc:
        path = _readline(proc)
        assert path.startswith("/dev/")
        for _ in range(2):  # connect twice; two scans each
            with HostLink(open_port(path), timeout_s=2.0) as lk:
                info = lk.hello()
                assert info.channels == 4
                first = list(lk.scan(frame=5))
                second = list(lk.scan(frame=6))
                assert [c.column for c in first] == [0, 1, 2]
                assert len(second) == 3


def test_tcp_device_end_to_end():
    cmd = [sys.executable, "-m", "cdma_lidar.cli", "device", "--scene",
           "flat-wall?instrument.wavelengths.count=4&instrument.columns=2", "--tcp",
           "127.0.0.1:0", "--insecure"]
    with _device_process(cmd) as proc:
        url = _readline(proc)
        assert url.startswith("socket://127.0.0.1:")
        for _ in range(2):  # the board outlives a connection
            with HostLink(open_port(url), timeout_s=2.0) as lk:
                assert lk.hello().channels == 4
                assert [c.column for c in lk.scan(frame=9)] == [0, 1]


def test_paper_scene1_lit_pixels_stand_out_from_empty_ones():
    """What the host's acceptance relies on: with the default configuration, lit pixels
    range correctly and their SNR_XC sits above every pixel that sees nothing."""
    fw = VirtualFirmware(load_scene("paper-scene1"), seed=0)
    cols = list(fw.scan(3, 40, 48))  # the "DMA" and "LI" columns and the gap between
    lit = fw.instrument.truth.hits.lit[:, 40:88]
    lag = np.array([c.peak_lag for c in cols]).T
    true = fw.instrument.delay_s[:, 40:88] * FS
    snr = np.array([snr_xc_db(c.peak, c.noise_count, c.noise_sum, c.noise_sumsq)
                    for c in cols]).T
    assert lit.sum() > 200 and (~lit).sum() > 1000
    assert np.mean(np.abs(lag[lit] - true[lit]) <= 1) >= 0.97
    assert np.percentile(snr[lit], 5) > snr[~lit].max() + 1.0


def test_the_column_clock_keeps_eq29s_frame_rate():
    """Eq. 29: 1 Gchip/s, a degree-13 code (N = 8191), 1000 columns -> 122 Hz, not the 125 Hz
    of a clock that rounds each column (8.191 us) to whole microseconds."""
    scene = load_scene("flat-wall", overrides={
        "instrument.chip_rate_hz": 1e9, "code_degree": 13, "averages": 1,
        "instrument.columns": 1000, "instrument.wavelengths.count": 2})
    fw = VirtualFirmware(scene, 0)
    cfg = fw.render_settings()
    stamps = [fw._timestamp(cfg) for _ in range(2000)]
    frame_us = stamps[999]  # the end of the first frame of 1000 columns
    assert frame_us == 8191  # floor(1000 * 8191 chips / 1 Gchip/s) exactly
    assert 1e6 / frame_us == pytest.approx(122.08, abs=0.01)
    assert stamps[1999] == 16382  # no drift: the second frame ends at twice the time
    assert stamps[0] == 8  # a column's own time, floored
    assert np.all(np.diff(stamps) >= 8) and np.all(np.diff(stamps) <= 9)


@given(rate=st.floats(1e3, 1e10), chips=st.integers(1, 2**40))
@settings(max_examples=200, deadline=None)
def test_the_clock_floors_chips_over_the_exact_chip_rate(rate, chips):
    """The timestamp in integers equals floor(chips * 1e6 / rate) with the rate's exact
    binary value (fractions.Fraction), to the last microsecond, 32 bits; the board's
    clock is that function of its chip count."""
    from fractions import Fraction

    from cdma_lidar.scene.acquire import clock_us

    assert clock_us(chips, rate) == int(chips * 1_000_000 // Fraction(rate)) & 0xFFFFFFFF
    fw = _CLOCK_BOARD
    cfg = fw.render_settings()
    fw._clock_chips = chips - cfg.averages * cfg.frame_chips
    assert fw._timestamp(cfg) == clock_us(chips, fw.spec.chip_rate_hz)


_CLOCK_BOARD = VirtualFirmware(load_scene("flat-wall?instrument.columns=1"
                                          "&instrument.wavelengths.count=1"), 0)


@pytest.mark.parametrize("config", [{}, {"peaks": 3, "uid_bits": 2, "uid": 2}])
def test_batched_column_results_equal_the_one_column_path(config, monkeypatch):
    """The scan checks and packs a batch's records in one call (virtual.board._column_results);
    every column must equal ColumnResult.from_receiver of the same receiver output, extra
    peaks and UID signs included, and batches split anywhere must give the same columns."""
    from cdma_lidar.protocol.columns import ColumnResult
    from cdma_lidar.scene import acquire

    fw = VirtualFirmware(load_scene("flat-wall", overrides={
        "distance": 7.5, "instrument.wavelengths.count": 8, "instrument.columns": 7}), 5)
    fw.set_config(config)
    cfg = fw.render_settings()
    cols = list(range(fw.columns))
    outs = fw._receive(2, cols, [fw.power_w()[:, c] for c in cols], cfg, False)
    angles = fw.spec.rotations_deg
    want = [ColumnResult.from_receiver(2, c, float(angles[c]), o, timestamp_us=0)
            for c, o in zip(cols, outs, strict=True)]

    def key(col):
        return (col.frame, col.column, col.angle_udeg, col.uid_bits, col.calibration,
                col.records.dtype, col.records.tobytes())

    got = list(fw.scan(2, 0, fw.columns))
    assert [key(c) for c in got] == [key(c) for c in want]
    assert want[0].peaks == config.get("peaks", 1)
    assert [c.timestamp_us for c in got] == sorted({c.timestamp_us for c in got})
    monkeypatch.setattr(acquire, "BATCH_VALUES", 2 * cfg.frame_samples)  # batches of 2
    assert [key(c) for c in fw.scan(2, 0, fw.columns)] == [key(c) for c in want]
    assert not got[0].records.flags.writeable


@pytest.mark.parametrize(("change", "field", "allowed"), [
    ({"out_bits": 40}, "out_bits", "8"), ({"out_shift": 63}, "out_shift", "62"),
    ({"rounding": "up"}, "rounding", "truncate"), ({"peaks": 9}, "peaks", "8"),
    ({"averages": 0}, "averages", "1024"), ({"uid": 2}, "uid", "1"),
    ({"gate_len": 2047 * 4 + 1}, "gate_len", str(2047 * 4)),
    ({"samples_per_chip": 17}, "samples_per_chip", "16"),
    ({"peak_exclude": 2047 * 4 + 1}, "peak_exclude", str(2047 * 4)),
    ({"cancel_rounds": 5}, "cancel_rounds", "0..4"),
    ({"cancel_snr_q8": -1}, "cancel_snr_q8", str(2**32 - 1))])
def test_a_bad_key_is_refused_once_naming_the_field_and_its_range(change, field, allowed):
    """The board checks its own limits, the receive chain's configuration checks its
    fields (ReceiverConfig): each refusal names the field and the allowed range, and
    leaves the configuration as it was."""
    fw = VirtualFirmware(load_scene("flat-wall?instrument.columns=2"), 0)
    before = fw.get_config()
    with pytest.raises(ConfigError) as info:
        fw.set_config(change)
    assert info.value.field == field
    assert allowed in str(info.value)
    assert fw.get_config() == before


def test_the_board_states_its_column_time_and_status_carries_it():
    """A batch's columns times (acquisition R n N / f_chip + compute): at least the
    a-priori compute bound before any batch, and never below what a batch took."""
    from cdma_lidar.protocol.endpoint import DeviceEndpoint
    from cdma_lidar.scene.acquire import column_batches
    from cdma_lidar.virtual.board import COMPUTE_S_PER_VALUE, VirtualFirmware

    fw = VirtualFirmware(load_scene("flat-wall?instrument.columns=6"), 3)
    cfg, k = fw.render_settings(), fw.channels
    batch = len(next(column_batches(0, 6, cfg.frame_samples)))
    acq = cfg.averages * cfg.frame_chips / fw.spec.chip_rate_hz
    before = fw.column_time_s()
    assert before == pytest.approx(batch * (acq + COMPUTE_S_PER_VALUE["model"] * k
                                            * cfg.frame_samples))
    fw.set_config({"averages": 2 * cfg.averages})
    assert fw.column_time_s() == pytest.approx(
        before + batch * acq)  # the acquisition doubles, the compute bound does not
    t0 = time.perf_counter()
    list(fw.scan(0, 0, 6))
    took = time.perf_counter() - t0
    assert fw.column_time_s() >= before
    assert fw.column_time_s() <= batch * (2 * acq + max(took, COMPUTE_S_PER_VALUE["model"]
                                                         * k * cfg.frame_samples)) + 1e-9
    ep = DeviceEndpoint(_NullPort(), fw, session_id=1, poll_s=0.0,
                        engine=Engine(threaded=False))
    assert ep.status().column_time_ms == math.ceil(fw.column_time_s() * 1000)


class _NullPort:
    """A port that never delivers a byte and swallows every write."""

    timeout = 0.0
    in_waiting = 0

    def read(self, n: int = 1) -> bytes:
        return b""

    def write(self, data: bytes) -> int:
        return len(data)

    def flush(self) -> None:
        pass


def test_the_chains_interference_cancellation_travels_over_the_wire(link):
    """CONFIG_SET takes the two keys, CONFIG returns them, the board's chain runs them;
    the host refuses a value outside the key's range before it is sent."""
    cfg = link.get_config()
    assert (cfg["cancel_rounds"], cfg["cancel_snr_q8"]) == (0, 10192)   # the scene's
    link.set_config(cancel_rounds=2, cancel_snr_q8=5731)
    cfg = link.get_config()
    assert (cfg["cancel_rounds"], cfg["cancel_snr_q8"]) == (2, 5731)
    assert len(list(link.scan(columns=1))) == 1
    with pytest.raises(ConfigError, match="cancel_rounds"):
        link.set_config(cancel_rounds=5)
    with pytest.raises(DeviceError) as refused:   # the own-echo table's longest gate
        link.set_config(gate_len=4097)
    assert refused.value.field == "gate_len"
    assert link.get_config()["cancel_rounds"] == 2


def test_the_rtl_engine_refuses_interference_cancellation(monkeypatch):
    """The RTL correlates once: cancel_rounds > 0 is refused at boot (a scene that sets
    it, as paper-massive does) and by CONFIG_SET, naming the field and the value allowed,
    before anything is built (no simulator needed)."""
    import cdma_lidar.virtual.board as board
    from cdma_lidar.firmware_model.receiver import ReceiverConfig
    from cdma_lidar.hdl_ref.engine import RtlReceiver

    monkeypatch.setattr(board, "missing_simulator", lambda: None)
    with pytest.raises(LinkError) as info:
        open_port("virtual://flat-wall?engine=rtl&instrument.cancel_rounds=1")
    text = str(info.value)
    assert "\n" not in text and "cancel_rounds must be 0" in text and "RTL" in text
    with pytest.raises(ConfigError, match="cancel_rounds must be 0"):
        VirtualFirmware(load_scene("paper-massive?channels=4&columns=1"), 0, engine="rtl")
    fw = VirtualFirmware(load_scene("flat-wall?instrument.columns=2"), 0, engine="rtl")
    before = fw.get_config()
    with pytest.raises(ConfigError) as refused:
        fw.set_config({"cancel_rounds": 2})
    assert refused.value.field == "cancel_rounds" and "0 on the RTL engine" in str(refused.value)
    assert fw.get_config() == before
    fw.set_config({"cancel_snr_q8": 5731})   # the threshold alone changes nothing there
    with pytest.raises(ConfigError, match="cancel_rounds"):
        RtlReceiver(ReceiverConfig(cancel_rounds=1), (11, 2), (11, 8, 5, 2), (0, 1))
    VirtualFirmware(load_scene("paper-massive?channels=4&columns=1"), 0)   # the model runs it
