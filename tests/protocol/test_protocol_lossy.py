"""Stateful test over a lossy in-memory link: nothing is lost, nothing is done twice.

The line drops, duplicates, corrupts and reorders frames in both directions. Every
request must either complete with the right effect or fail with LinkTimeout and a
diagnosis; every scan must deliver each column exactly once, in order and intact.
"""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import settings
from hypothesis import strategies as st
from hypothesis.stateful import RuleBasedStateMachine, initialize, invariant, rule
from protocol_fixtures import (
    ScriptedPort,
    SteppedDevice,
    SyntheticApp,
    expected_column,
)

from cdma_lidar.errors import LinkTimeout
from cdma_lidar.protocol.link import HostLink
from cdma_lidar.protocol.requests import DIAG_GARBAGE, DIAG_NO_ANSWER, DIAG_NOISY, DIAG_SILENT
from cdma_lidar.virtual.line import Faults, LineNoise

#: Reply timeout on a lossy line (s), on the threadless device's fake clock: the machine's
#: load cannot make a slow reply look like a lost frame.
TIMEOUT = 0.2
DIAGNOSES = {DIAG_SILENT, DIAG_GARBAGE, DIAG_NO_ANSWER, DIAG_NOISY}
K, C = 6, 40


class LossyLink(RuleBasedStateMachine):
    """Model: the device's configuration and power matrix as the host believes them."""

    @initialize(seed=st.integers(0, 2**16), drop=st.sampled_from([0.0, 0.05, 0.15]),
                dup=st.sampled_from([0.0, 0.1]), corrupt=st.sampled_from([0.0, 0.1]),
                reorder=st.sampled_from([0.0, 0.1]))
    def start(self, seed: int, drop: float, dup: float, corrupt: float, reorder: float) -> None:
        f = Faults(drop=drop, duplicate=dup, corrupt=corrupt, reorder=reorder)
        self.app = SyntheticApp(channels=K, columns=C)
        self.device = SteppedDevice(self.app, faults=f, seed=seed, heartbeat_s=0.02)
        self.link = HostLink(self.device, timeout_s=TIMEOUT, retries=8, clock=self.device.clock)
        self.config = {"peaks": 1, "uid_bits": 1}
        self.power = self.app.power.copy()
        self.timeouts = 0
        self._call(self.link.hello)

    def teardown(self) -> None:
        if hasattr(self, "device"):
            self.device.close()

    def _call(self, fn, *args, **kw):
        """Run a request; a timeout is allowed but must carry a diagnosis.

        After a timeout the effect of the request is unknown: settle the device (one
        STATUS round trip is answered only after everything sent before it, and a late
        copy of the old request is then dropped as stale), then learn its state.
        """
        try:
            return True, fn(*args, **kw)
        except LinkTimeout as exc:
            assert exc.diagnosis in DIAGNOSES, exc
            self.timeouts += 1
            self._settle()
            return False, None

    def _settle(self) -> None:
        for _ in range(10):
            try:
                if self.link.status().state_name == "idle":
                    break
                self.link.abort()
            except LinkTimeout:
                continue
        self.config = {k: self.app.config[k] for k in self.config}
        self.power = self.app.power.copy()

    @rule(peaks=st.integers(1, 4), uid_bits=st.integers(1, 4))
    def set_config(self, peaks: int, uid_bits: int) -> None:
        ok, _ = self._call(self.link.set_config, peaks=peaks, uid_bits=uid_bits)
        if ok:
            self.config = {"peaks": peaks, "uid_bits": uid_bits}

    @rule()
    def get_config(self) -> None:
        ok, got = self._call(self.link.get_config, "peaks", "uid_bits")
        if ok:
            assert got == self.config

    @rule(first=st.integers(0, C - 1), count=st.integers(1, C))
    def scan(self, first: int, count: int) -> None:
        count = min(count, C - first)
        ok, cols = self._call(lambda: list(self.link.scan(first_column=first, columns=count)))
        if not ok:
            return
        assert [c.column for c in cols] == list(range(first, first + count))
        p, n = self.config["peaks"], self.config["uid_bits"]
        for c in cols:
            assert c == expected_column(c.frame, c.column, K, p, n), c.column
        assert len({c.frame for c in cols}) == 1

    @rule(stop_after=st.integers(0, 5))
    def scan_left_early(self, stop_after: int) -> None:
        """The user leaves the loop: the scan is aborted and the device is idle again."""
        seen = []

        def run() -> None:
            for c in self.link.scan(columns=C):
                seen.append(c.column)
                if len(seen) > stop_after:
                    break

        ok, _ = self._call(run)
        if ok:
            assert seen == list(range(stop_after + 1))

    @rule(r0=st.integers(0, K - 1), c0=st.integers(0, C - 1), value=st.integers(0, 65535))
    def set_power(self, r0: int, c0: int, value: int) -> None:
        block = np.full((min(2, K - r0), min(5, C - c0)), value, dtype=np.int64)
        ok, _ = self._call(self.link.set_power, block, channel_start=r0, column_start=c0)
        if ok:
            self.power[r0:r0 + block.shape[0], c0:c0 + block.shape[1]] = value

    @rule()
    def status(self) -> None:
        ok, st_ = self._call(self.link.status)
        if ok:
            assert st_.state_name == "idle"

    @invariant()
    def device_matches_model(self) -> None:
        if hasattr(self, "app"):
            assert {k: self.app.config[k] for k in self.config} == self.config
            np.testing.assert_array_equal(self.app.power, self.power)


LossyLink.TestCase.settings = settings(max_examples=12, stateful_step_count=8, deadline=None)
TestLossyLink = LossyLink.TestCase


@pytest.mark.parametrize("seed", range(3))
def test_heavy_loss_every_request_completes_or_times_out_clearly(seed: int) -> None:
    f = Faults(drop=0.4, duplicate=0.2, corrupt=0.2, reorder=0.2)
    app = SyntheticApp(channels=K, columns=C)
    port = SteppedDevice(app, faults=f, seed=seed, heartbeat_s=0.02)
    with port:
        link = HostLink(port, timeout_s=TIMEOUT, retries=3, clock=port.clock)
        outcomes = []
        for k in range(12):
            try:
                if k % 3 == 0:
                    cols = list(link.scan(columns=10))
                    assert [c.column for c in cols] == list(range(10))
                    assert all(c == expected_column(c.frame, c.column, K, 1, 1) for c in cols)
                else:
                    link.status()
                outcomes.append("ok")
            except LinkTimeout as exc:
                assert exc.diagnosis in DIAGNOSES
                outcomes.append(exc.diagnosis)
        assert "ok" in outcomes


def test_dead_line_fails_after_the_retries() -> None:
    port = ScriptedPort()  # the device hears; nothing it says reaches the host
    link = HostLink(port, retries=2, clock=port.clock)
    with pytest.raises(LinkTimeout) as exc:
        link.hello()
    assert exc.value.diagnosis == DIAG_SILENT
    assert link.stats.retries == 2 and port.clock() >= 3 * link.timeout_s


def test_scan_through_bit_errors_is_repaired() -> None:
    """Bit errors on the way up: damaged columns are asked for again; none is lost or doubled."""
    port = SteppedDevice(SyntheticApp(channels=K, columns=C), seed=7, heartbeat_s=0.02)
    port.host.rx.faults = Faults(bit_error_rate=2e-4)  # on the way up only
    port.host.rx.noise = LineNoise(2e-4, 8)
    with port:
        link = HostLink(port, timeout_s=TIMEOUT, retries=10, clock=port.clock)
        link.hello()
        cols = list(link.scan())
        assert [c.column for c in cols] == list(range(C))
        assert all(c == expected_column(c.frame, c.column, K, 1, 1) for c in cols)
        assert link.stats.resend_requests >= 1
        assert link.decoder.stats.crc + link.decoder.stats.cobs >= 1


@pytest.mark.parametrize(("ber", "max_frame"), [(1e-3, 80), (3e-4, 256), (1e-4, 65535)])
def test_a_noisy_line_scans_byte_identical_in_fragments(ber: float, max_frame: int) -> None:
    """40-channel columns through bit errors on both directions, frames sized to the line."""
    port = SteppedDevice(SyntheticApp(channels=40, columns=25), faults=Faults(bit_error_rate=ber),
                         seed=7, heartbeat_s=0.02)
    with port:
        link = HostLink(port, timeout_s=0.05, retries=20, max_frame=max_frame, clock=port.clock)
        assert link.hello().channels == 40
        link.set_config(peaks=2)
        cols = list(link.scan(frame=11))
        link.close()
    assert cols == [expected_column(11, c, 40, 2, 1) for c in range(25)]
    st = link.decoder.stats
    assert st.damaged > 0  # the line really was noisy


def test_a_line_that_damages_everything_is_diagnosed_as_noisy_not_as_a_baud_rate() -> None:
    port = SteppedDevice(SyntheticApp(channels=40, columns=4), faults=Faults(bit_error_rate=3e-3),
                         seed=3, heartbeat_s=0.02)
    with port:
        link = HostLink(port, timeout_s=0.03, retries=3, column_retries=2, clock=port.clock)
        with pytest.raises(LinkTimeout) as exc:
            link.hello()
            list(link.scan())
    msg = str(exc.value)
    assert "damaged frames of" in msg and "\n" not in msg, msg


def test_reed_solomon_frames_carry_a_1e3_line_whole() -> None:
    """FEC: 1.7 kB columns never pass a 1e-3 line plain; coded, nearly all are repaired
    on arrival and RESEND fetches the rest."""
    port = SteppedDevice(SyntheticApp(channels=40, columns=12), faults=Faults(bit_error_rate=1e-3),
                         seed=5, heartbeat_s=0.02)
    with port:
        link = HostLink(port, timeout_s=0.2, retries=20, fec=True, clock=port.clock)
        link.hello()
        assert link.coded
        cols = list(link.scan(frame=2))
        link.close()
    assert cols == [expected_column(2, c, 40, 1, 1) for c in range(12)]
    assert link.decoder.stats.corrected >= 12


def _scan_seconds(seed: int, drop: float) -> float:
    """Host-clock seconds of a 16-column scan of 40 channels (5 ms a column on the
    device) while the line drops ``drop`` of the writes each way, from SCAN_START on."""
    app = SyntheticApp(channels=40, columns=16)
    port = SteppedDevice(app, seed=seed, heartbeat_s=0.2)
    app.tick = lambda: port.now.__setitem__(0, port.now[0] + 0.005)
    with port:
        link = HostLink(port, timeout_s=0.5, fec=True, clock=port.clock)
        link.hello()
        link.get_config()
        port.host.rx.faults = port.host.tx.faults = Faults(drop=drop)
        start = port.clock()
        cols = list(link.scan(frame=7))
    assert cols == [expected_column(7, c, 40, 1, 1) for c in range(16)]
    return port.clock() - start


def test_a_lost_frame_costs_round_trips_not_a_fixed_wait() -> None:
    """Issue 42 item 2 on the fake clock: 30 short scans through a line that drops 10 %
    of the frames, each against the clean scan: the median at most 1.5x, the worst at
    most 3x (a repair asked a fixed quarter timeout apart made the worst 5.7x)."""
    clean = _scan_seconds(1, 0.0)
    ratios = [_scan_seconds(seed, 0.1) / clean for seed in range(101, 131)]
    assert np.median(ratios) <= 1.5 and max(ratios) <= 3.0, ratios
    assert max(ratios) > 1.0  # frames were lost and repaired
