"""Sessions: one owner per device, BUSY for others, take-over, idle expiry, fresh defaults."""

from __future__ import annotations

import socket
import struct
import subprocess
import sys
import threading
import time
from collections.abc import Iterator

import pytest
from protocol_fixtures import RunningDevice, SteppedDevice, SyntheticApp, hello_fields

from cdma_lidar.errors import DeviceError
from cdma_lidar.protocol.endpoint import DeviceCore, Engine
from cdma_lidar.protocol.framing import FrameDecoder, encode_frame
from cdma_lidar.protocol.link import HostLink, SessionLost
from cdma_lidar.protocol.messages import (
    ErrorCode,
    MsgType,
    SessionLostReason,
    decode_payload,
    encode_payload,
)
from cdma_lidar.protocol.ports import FdPort, open_port
from cdma_lidar.virtual.line import pipe_pair

TIMEOUT = 0.2  # s of the injected clock: nothing here waits in real time


class Device:
    """One device (one core) reachable over several connections at once, as over TCP.

    Threadless: each connection is a :class:`SteppedDevice`; all share one clock.
    """

    def __init__(self, app: SyntheticApp, idle_s: float = 10.0) -> None:
        self.app = app
        self.now = [100.0]
        self.core = DeviceCore(app, session_idle_s=idle_s, clock=lambda: self.now[0],
                               engine=Engine(threaded=False))
        self.ports: list[SteppedDevice] = []

    def host(self, **kw: object) -> HostLink:
        port = SteppedDevice(None, core=self.core, now=self.now, heartbeat_s=0.05)
        self.ports.append(port)
        return HostLink(port, timeout_s=TIMEOUT, retries=2, clock=port.clock, **kw)

    def close(self) -> None:
        for port in self.ports:
            port.close()


@pytest.fixture
def device() -> Iterator[Device]:
    d = Device(SyntheticApp(channels=4, columns=40))
    yield d
    d.close()


def test_a_second_host_is_told_busy_with_the_owners_age_and_idle_time(device) -> None:
    a, b = device.host(), device.host()
    a.hello()
    with pytest.raises(DeviceError) as exc:
        b.hello()
    assert exc.value.code == ErrorCode.BUSY and exc.value.field == "session"
    msg = str(exc.value)
    assert "opened" in msg and "idle" in msg and "take-over" in msg and "\n" not in msg
    a.status()  # the owner is untouched
    a.close()
    b.hello()  # a closed session (SESSION_END) frees the device at once


def test_every_hello_opens_a_fresh_session(device) -> None:
    a = device.host()
    ids = {a.hello().session_id for _ in range(5)}
    assert len(ids) == 5 and 0 not in ids


def test_take_over_tells_the_first_host_in_one_line_even_mid_scan(device) -> None:
    a, b = device.host(), device.host(take_over=True)
    info_a = a.hello()
    scan = a.scan(columns=40)
    got = [next(scan) for _ in range(3)]
    assert [c.column for c in got] == [0, 1, 2]
    b.hello()
    with pytest.raises(SessionLost) as exc:
        for _ in scan:
            pass
    assert exc.value.reason == SessionLostReason.TAKEN_OVER
    assert "took over" in str(exc.value) and "\n" not in str(exc.value)
    assert a.session is None
    assert b.status().state == 0  # the first host's scan stopped; b owns an idle device
    a.session = info_a.session_id  # a host that ignores SESSION_LOST is refused
    with pytest.raises(DeviceError) as refused:
        a.status()
    assert refused.value.code == ErrorCode.WRONG_SESSION


def test_an_idle_session_expires_for_another_host() -> None:
    d = Device(SyntheticApp(channels=4, columns=8), idle_s=0.3)
    try:
        a, b = d.host(), d.host()
        info = a.hello()
        assert info.session_idle_ms == 300
        with pytest.raises(DeviceError):
            b.hello()  # not idle long enough
        d.now[0] += 0.4
        b.hello()
        with pytest.raises(SessionLost) as exc:
            a.status()
        assert exc.value.reason == SessionLostReason.EXPIRED
    finally:
        d.close()


def test_a_new_session_starts_from_the_defaults_unless_asked_to_keep(device) -> None:
    a = device.host()
    a.hello()
    default = a.get_config()["peaks"]
    a.set_config(peaks=3)
    a.set_power([[7] * 40] * 4)
    a.close()
    b = device.host()
    b.hello()
    assert b.get_config()["peaks"] == default
    assert int(device.app.power.max()) == 65535  # the boot matrix is back
    b.set_config(peaks=2)
    b.close()
    c = device.host(keep_config=True)
    c.hello()
    assert c.get_config()["peaks"] == 2


def _cli(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "cdma_lidar.cli", *args], capture_output=True,
                          text=True, timeout=120)


def test_cli_busy_and_take_over_over_tcp() -> None:
    proc = subprocess.Popen(
        [sys.executable, "-m", "cdma_lidar.cli", "device", "--scene",
         "flat-wall?instrument.wavelengths.count=4&instrument.columns=2", "--tcp",
         "127.0.0.1:0", "--insecure", "--session-idle", "600"], stdout=subprocess.PIPE,
        stderr=subprocess.PIPE)  # long idle: two CLI starts on a loaded machine take > 10 s
    try:
        url = proc.stdout.readline().decode().strip()
        assert url.startswith("socket://127.0.0.1:")
        first = HostLink(open_port(url), timeout_s=2.0)
        first.hello()
        busy = _cli("info", "--port", url)
        assert busy.returncode == 2
        assert busy.stderr.count("\n") == 1 and "busy" in busy.stderr
        assert "--take-over" in busy.stderr
        took = _cli("info", "--port", url, "--take-over")
        assert took.returncode == 0, took.stderr
        with pytest.raises(SessionLost, match="took over"):
            first.status()
        first.close()
    finally:
        proc.terminate()
        proc.wait(10)


def test_lost_session_stops_a_cli_scan_with_exit_2_and_one_line(tmp_path) -> None:
    proc = subprocess.Popen(
        [sys.executable, "-m", "cdma_lidar.cli", "-v", "device", "--scene",
         "flat-wall?instrument.wavelengths.count=4&instrument.columns=1500", "--tcp",
         "127.0.0.1:0", "--insecure"], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
        text=True)
    try:
        url = proc.stdout.readline().strip()
        scan = subprocess.Popen(
            [sys.executable, "-m", "cdma_lidar.cli", "scan", "--port", url, "--out",
             str(tmp_path / "cloud.npz"), "--no-progress"], stdout=subprocess.PIPE,
            stderr=subprocess.PIPE, text=True)
        for line in proc.stderr:  # the device's log: wait until the scan owns a session
            if "HELLO from host" in line:
                break
        taker = HostLink(open_port(url), timeout_s=2.0, take_over=True)
        taker.hello()
        _out, err = scan.communicate(timeout=60)
        assert scan.returncode == 2, err
        errors = [line for line in err.splitlines() if not line.startswith("WARNING")]
        assert len(errors) == 1 and "took over" in errors[0], err
        taker.close()
    finally:
        proc.terminate()
        proc.wait(10)


def test_requests_keep_flowing_on_an_owned_device(device) -> None:
    """Sanity: the owner's scan is byte-identical with a BUSY host knocking meanwhile."""
    a, b = device.host(), device.host()
    a.hello()
    results: list[int] = []
    t = threading.Thread(target=lambda: results.extend(c.column for c in a.scan(columns=40)))
    t.start()
    for _ in range(3):
        with pytest.raises(DeviceError):
            b.hello()
    t.join(10)
    assert results == list(range(40))


def test_a_peer_that_stops_reading_cannot_hold_the_device_up() -> None:
    """FdPort.write gives up (OSError) instead of blocking the device's threads forever."""
    a, b = socket.socketpair()
    port = FdPort(a.detach(), write_timeout=0.2)
    try:
        with pytest.raises(OSError, match="does not read"):
            for _ in range(10_000):  # b never reads: the socket buffers fill up
                port.write(b"\x55" * 65536)
    finally:
        port.close()
        b.close()


def test_two_hosts_on_one_serial_line_are_told_apart_by_their_nonce() -> None:
    """A second host's HELLO on the same line no longer aborts the first host's scan."""
    app = SyntheticApp(channels=4, columns=30)
    host = SteppedDevice(app, heartbeat_s=0.05)  # threadless: both hosts write to it
    with host as ep:
        a = HostLink(host, timeout_s=TIMEOUT, retries=2, clock=host.clock)
        a.hello()
        scan = a.scan(frame=3)
        first = [next(scan) for _ in range(2)]
        other = hello_fields(0xB0B)  # another host on the same wire
        host.write(encode_frame(MsgType.HELLO, encode_payload(MsgType.HELLO, other), 77, 0))
        rest = list(scan)  # the first host's scan carries on, untouched
        assert [c.column for c in first + rest] == list(range(30))
        assert ep.stats.naks >= 1 and app.aborts == 0
        a.status()
        host.write(encode_frame(MsgType.HELLO, encode_payload(
            MsgType.HELLO, hello_fields(0xB0B, flags=1)), 78, 0))  # now it takes over
        with pytest.raises(SessionLost):
            for _ in range(20):
                a.status()


def test_a_version_1_host_gets_nak_version_in_its_own_version() -> None:
    """What a v1 peer gets (docs/protocol.md): its HELLO is answered NAK VERSION, not acted on."""
    host, dev = pipe_pair()
    app = SyntheticApp(channels=4, columns=8)
    with RunningDevice(dev, app, heartbeat_s=0.05) as ep:
        v1_hello = struct.pack("<IH", 0x1234, 4096)  # version 1: host_nonce u32, max frame
        host.write(encode_frame(MsgType.HELLO, v1_hello, 5, 0, version=1))
        dec = FrameDecoder()
        got: list = []
        deadline = time.monotonic() + 5
        while not got and time.monotonic() < deadline:
            dec.feed(host.read(max(1, host.in_waiting)))
            got = dec.rejected  # a frame of another version: a v1 client reads it
        (nak,) = got
        body = decode_payload(nak.msg_type, nak.payload)
        assert nak.version == 1 and nak.msg_type == MsgType.NAK and nak.seq == 5
        assert body["code"] == ErrorCode.VERSION
        assert not ep.session.open and ep.stats.sessions == 0
