"""End to end through the kernel: a real pty pair, and a TCP socket (socket://)."""

from __future__ import annotations

import itertools
import os
import socket
import threading
import time
import tty

import numpy as np
import pytest
from protocol_fixtures import RunningDevice, SyntheticApp, expected_column

from cdma_lidar.errors import LinkTimeout
from cdma_lidar.protocol.link import HostLink
from cdma_lidar.protocol.ports import FdPort, open_port
from cdma_lidar.protocol.requests import DIAG_SILENT

pytestmark = pytest.mark.skipif(not hasattr(os, "openpty"), reason="needs a pty")


@pytest.fixture
def pty_pair():
    master, slave = os.openpty()
    tty.setraw(slave)
    path = os.ttyname(slave)
    yield FdPort(master), path
    os.close(slave)


def test_handshake_configure_scan_over_pty(pty_pair) -> None:
    device_port, path = pty_pair
    app = SyntheticApp(channels=40, columns=50)
    with RunningDevice(device_port, app, heartbeat_s=0.05):
        port = open_port(path, baudrate=921600, timeout=0.02)
        with HostLink(port, timeout_s=2.0, retries=3) as link:
            link.min_timeout_s = 2.0  # real threads: no retry unless 2 s pass
            info = link.hello()
            assert info.channels == 40 and info.serial == "SYN-0001"
            link.set_config(peaks=2, uid_bits=2, rounding="convergent")
            assert link.get_config("peaks", "rounding") == {"peaks": 2, "rounding": "convergent"}
            link.set_power(np.full((40, 50), 0.25))
            assert (app.power == 16384).all()
            cols = list(link.scan())
            assert [c.column for c in cols] == list(range(50))
            assert all(c == expected_column(c.frame, c.column, 40, 2, 2) for c in cols)
            assert link.decoder.stats.errors == 0 and link.stats.retries == 0
            assert link.status().columns_sent == 50
    device_port.close()


def test_pty_without_device_is_diagnosed_silent(pty_pair) -> None:
    _, path = pty_pair
    port = open_port(path, timeout=0.01)
    clock = itertools.count(0.0, 0.1).__next__  # timeouts on an injected clock: 0.1 s a look
    with HostLink(port, timeout_s=0.5, retries=1, clock=clock) as link, \
            pytest.raises(LinkTimeout) as exc:
        link.hello()
    assert exc.value.diagnosis == DIAG_SILENT
    assert path in str(exc.value)


def test_handshake_and_scan_over_tcp_with_a_true_in_waiting() -> None:
    """socket:// through open_port: in_waiting counts bytes (pyserial's says 0 or 1)."""
    server = socket.create_server(("127.0.0.1", 0))
    host_addr, port_no = server.getsockname()[:2]
    box: dict = {}

    def accept() -> None:
        conn, _ = server.accept()
        box["conn"] = conn

    t = threading.Thread(target=accept, daemon=True)
    t.start()
    port = open_port(f"socket://{host_addr}:{port_no}", timeout=0.02)
    t.join(5.0)
    conn = box["conn"]
    conn.sendall(b"\x55" * 300)
    deadline = time.monotonic() + 5.0
    while port.in_waiting < 300 and time.monotonic() < deadline:
        time.sleep(0.005)
    assert port.in_waiting == 300  # one read takes them all
    assert port.read(300) == b"\x55" * 300
    app = SyntheticApp(channels=40, columns=200)
    dev_port = FdPort(conn.fileno())
    try:
        with RunningDevice(dev_port, app, heartbeat_s=0.05), \
                HostLink(port, timeout_s=2.0, retries=3) as link:
            link.min_timeout_s = 2.0  # real threads: no retry unless 2 s pass
            assert link.hello().channels == 40
            cols = list(link.scan())
            assert [c.column for c in cols] == list(range(200))
            assert all(c == expected_column(c.frame, c.column, 40, 1, 1) for c in cols)
            assert link.stats.retries == 0
    finally:
        conn.close()
        server.close()


def test_the_cli_device_on_a_pty_with_a_key_file_speaks_keyed_and_coded(tmp_path) -> None:
    """``cdma-lidar device --pty --key-file``: a serial line whose sessions are signed and
    Reed-Solomon coded at once (issue 42.6)."""
    import subprocess
    import sys

    from cdma_lidar.protocol.auth import load_or_create_key

    key_file = tmp_path / "device.key"
    key, _ = load_or_create_key(key_file)
    proc = subprocess.Popen(
        [sys.executable, "-m", "cdma_lidar.cli", "device", "--scene",
         "flat-wall?instrument.wavelengths.count=4&instrument.columns=2", "--pty",
         "--key-file", str(key_file)], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        path = proc.stdout.readline().strip()
        assert path.startswith("/dev/"), proc.stderr.read() if proc.poll() is not None else path
        with HostLink(open_port(path, timeout=0.02), timeout_s=2.0, key=key) as link:
            assert link.hello().auth == 1 and link.coded
            assert len(list(link.scan())) == 2
    finally:
        proc.terminate()
        proc.wait(10)
