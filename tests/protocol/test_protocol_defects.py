"""Defects a hostile or unlucky peer found in protocol v2, each fixed in v3 (issue 25).

Time-dependent behaviour is driven by injected clocks; no test asserts an elapsed time.
"""

from __future__ import annotations

from protocol_fixtures import RunningDevice, SteppedDevice, SyntheticApp

from cdma_lidar.protocol.framing import encode_frame
from cdma_lidar.protocol.link import HostLink
from cdma_lidar.protocol.messages import MsgType, encode_payload
from cdma_lidar.virtual.line import pipe_pair

KEY = bytes(range(32))


def test_an_unsigned_line_error_in_a_signed_session_is_not_counted() -> None:
    """An injector's LINE_ERROR must not hurry the host: counted only once it verifies."""
    host, dev = pipe_pair()
    with RunningDevice(dev, SyntheticApp(channels=4, columns=8), key=KEY):
        link = HostLink(host, timeout_s=2.0, retries=2, key=KEY)
        link.hello()
        before = (link.line_errors, link.stats.unauthenticated)
        forged = encode_payload(MsgType.LINE_ERROR, {"rx_errors": 7})
        for seq in range(5):
            host.rx.write(encode_frame(MsgType.LINE_ERROR, forged, seq, link.session))
        link.status()  # reads the injected frames on the way
        assert link.line_errors == before[0]
        assert link.stats.unauthenticated >= before[1] + 5
        link.close()


def test_status_counters_run_since_boot_not_since_the_connection() -> None:
    """Two connections to one device (as over TCP): the second sees the first's counts."""
    from cdma_lidar.protocol.endpoint import DeviceCore

    core = DeviceCore(SyntheticApp(channels=4, columns=8))
    first_host, first_dev = pipe_pair()
    with RunningDevice(first_dev, None, core=core):
        link = HostLink(first_host, timeout_s=2.0)
        link.hello()
        list(link.scan(frame=1))
        st1 = link.status()
        link.close()
    second_host, second_dev = pipe_pair()
    with RunningDevice(second_dev, None, core=core):
        link = HostLink(second_host, timeout_s=2.0)
        link.hello()
        st2 = link.status()
        link.close()
    assert st1.columns_sent == 8 and st2.columns_sent == 8
    assert st2.rx_frames > st1.rx_frames and st2.tx_frames > st1.tx_frames
    assert st2.uptime_ms >= st1.uptime_ms


def test_notices_longer_than_a_small_frame_go_out_in_fragments(caplog) -> None:
    """64-byte frames in a signed session: heartbeats and SESSION_LOST still arrive whole."""
    import logging

    from cdma_lidar.protocol.endpoint import DeviceCore, Engine
    from cdma_lidar.protocol.link import SessionLost

    now = [100.0]
    app = SyntheticApp(channels=2, columns=6)
    app.tick = lambda: now.__setitem__(0, now[0] + 0.05)  # 50 ms per column, injected
    core = DeviceCore(app, key=KEY, clock=lambda: now[0], engine=Engine(threaded=False))
    a_port = SteppedDevice(None, core=core, now=now, heartbeat_s=0.01)
    b_port = SteppedDevice(None, core=core, now=now)
    with caplog.at_level(logging.ERROR), a_port, b_port:
        a = HostLink(a_port, timeout_s=1.0, key=KEY, max_frame=64, clock=a_port.clock)
        a.hello()
        assert len(list(a.scan(frame=2))) == 6
        assert a.last_status is not None and a.last_status.frame == 2  # a heartbeat came
        b = HostLink(b_port, timeout_s=1.0, key=KEY, take_over=True, clock=b_port.clock)
        b.hello()
        try:
            a.status()
            raise AssertionError("the taken-over host must hear SESSION_LOST")
        except SessionLost as exc:
            assert "took over" in str(exc)
        b.close()
    assert not [r for r in caplog.records if r.levelno >= logging.ERROR]


class _Stuck(SyntheticApp):
    """Its scan computes column 0 until ``release`` is set (holding the application)."""

    def __init__(self) -> None:
        import threading

        super().__init__(channels=2, columns=4)
        self.release = threading.Event()

    def scan(self, frame: int, first_column: int, columns: int):  # type: ignore[override]
        def gen():
            self.release.wait(120.0)
            yield from super(_Stuck, self).scan(frame, first_column, columns)
        return gen()


def test_a_second_host_hears_busy_while_the_application_computes() -> None:
    """HELLO is refused from the polling thread: it never waits for a column."""
    import pytest

    from cdma_lidar.errors import DeviceError
    from cdma_lidar.protocol.endpoint import DeviceCore
    from cdma_lidar.protocol.messages import ErrorCode

    app = _Stuck()
    core = DeviceCore(app)
    a_host, a_dev = pipe_pair()
    b_host, b_dev = pipe_pair()
    try:
        with RunningDevice(a_dev, None, core=core), RunningDevice(b_dev, None, core=core):
            a = HostLink(a_host, timeout_s=2.0)
            a.hello()
            a.request(MsgType.SCAN_START, {"frame": 1, "first_column": 0, "columns": 4})
            b = HostLink(b_host, timeout_s=2.0, retries=0)
            with pytest.raises(DeviceError) as exc:
                b.hello()
            assert exc.value.code == ErrorCode.BUSY
            app.release.set()
    finally:
        app.release.set()


def test_busy_comes_from_the_scan_state_while_the_application_computes() -> None:
    """CONFIG_SET, SCAN_START and CALIBRATE during a scan are refused BUSY by the polling
    thread (issue 42.3): none waits for the column the application is computing."""
    import pytest

    from cdma_lidar.errors import DeviceError
    from cdma_lidar.protocol.messages import ErrorCode

    app = _Stuck()
    host, dev = pipe_pair()
    try:
        with RunningDevice(dev, app):
            link = HostLink(host, timeout_s=2.0, retries=0)
            link.hello()
            link.request(MsgType.SCAN_START, {"frame": 1, "first_column": 0, "columns": 4})
            for req, fields in ((MsgType.CONFIG_SET, {"items": []}),
                                (MsgType.SCAN_START, {"frame": 2, "first_column": 0,
                                                      "columns": 1}),
                                (MsgType.CALIBRATE, {"frame": 3, "shots": 1})):
                with pytest.raises(DeviceError) as exc:
                    link.request(req, fields)
                assert exc.value.code == ErrorCode.BUSY, req
            assert not app.release.is_set()  # all answered while the column was stuck
    finally:
        app.release.set()


def test_failed_authentication_backs_off_per_peer_and_logs_once(caplog) -> None:
    """20 wrong MACs at one instant: one is checked, one WARNING; later the key holder gets in."""
    import logging

    import pytest

    from cdma_lidar.errors import DeviceError
    from cdma_lidar.protocol.endpoint import DeviceCore
    from cdma_lidar.protocol.messages import ErrorCode

    now = [100.0]
    core = DeviceCore(SyntheticApp(channels=2, columns=4), key=KEY, clock=lambda: now[0])
    host, dev = pipe_pair()
    with caplog.at_level(logging.WARNING, logger="cdma_lidar.protocol"), \
            RunningDevice(dev, None, core=core) as ep:
        guesser = HostLink(host, timeout_s=2.0, key=bytes(32))
        for _ in range(20):
            with pytest.raises(DeviceError) as exc:
                guesser.hello()
            assert exc.value.code == ErrorCode.AUTH_FAILED
        assert ep.stats.auth_rejected == 1 and ep.stats.auth_throttled == 19
        now[0] += 0.2  # past the first back-off (0.1 s)
        holder = HostLink(host, timeout_s=1.0, key=KEY)
        assert holder.hello().auth == 1
    warnings = [r for r in caplog.records if r.levelno == logging.WARNING]
    assert len(warnings) == 1, [r.getMessage() for r in warnings]


class _Ep:
    """What Connections reads of an endpoint: its session."""

    def __init__(self, since: float, session: bool = False) -> None:
        from types import SimpleNamespace

        self.session = SimpleNamespace(sessionless_since=since, open=session, peer="peer")


def test_silent_connections_are_closed_after_the_hello_deadline_and_make_room() -> None:
    import threading

    from cdma_lidar.virtual.serve import HELLO_DEADLINE_S, Connections, _Conn

    now = [0.0]
    conns = Connections(limit=3, clock=lambda: now[0])
    owner = _Conn(_Ep(0.0, session=True), threading.Event())  # type: ignore[arg-type]
    silent = [_Conn(_Ep(t), threading.Event()) for t in (1.0, 2.0)]  # type: ignore[arg-type]
    for c in (owner, *silent):
        assert conns.admit(c)
    # Full: a newcomer closes the longest-silent connection, never the session's owner.
    newcomer = _Conn(_Ep(3.0), threading.Event())  # type: ignore[arg-type]
    now[0] = 3.0
    assert conns.admit(newcomer)
    assert silent[0].stop.is_set() and not owner.stop.is_set()
    # The deadline closes the rest.
    now[0] = 2.0 + HELLO_DEADLINE_S
    conns.sweep()
    assert silent[1].stop.is_set() and not newcomer.stop.is_set()
    now[0] = 3.0 + HELLO_DEADLINE_S
    conns.sweep()
    assert newcomer.stop.is_set() and conns.items == [owner]
    # Only sessions fill the server for good.
    full = Connections(limit=1, clock=lambda: now[0])
    assert full.admit(owner)
    assert not full.admit(_Conn(_Ep(now[0]), threading.Event()))  # type: ignore[arg-type]


def _device(*args: str):
    import subprocess
    import sys

    proc = subprocess.Popen(
        [sys.executable, "-m", "cdma_lidar.cli", "device", "--scene",
         "flat-wall?instrument.wavelengths.count=4&instrument.columns=2", *args],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    return proc, proc.stdout.readline().strip()


def test_eight_silent_peers_cannot_lock_a_key_holder_out(tmp_path) -> None:
    import socket
    import urllib.parse

    from cdma_lidar.host.connection import connect
    from cdma_lidar.protocol.auth import load_or_create_key

    key_file = tmp_path / "device.key"
    load_or_create_key(key_file)
    proc, url = _device("--tcp", "127.0.0.1:0", "--key-file", str(key_file))
    silent = []
    try:
        where = urllib.parse.urlsplit(url)
        silent = [socket.create_connection((where.hostname, where.port)) for _ in range(8)]
        with connect(url, timeout_s=2.0, key_file=str(key_file)) as dev:
            assert dev.info.auth == 1
    finally:
        for s in silent:
            s.close()
        proc.terminate()
        proc.wait(10)


def test_insecure_tcp_on_the_ipv6_loopback_is_accepted() -> None:
    from cdma_lidar.host.connection import connect

    proc, url = _device("--tcp", "[::1]:0", "--insecure")
    try:
        assert url.startswith("socket://[::1]:"), (url, proc.stderr.read() if not url else "")
        with connect(url, timeout_s=2.0) as dev:
            assert dev.info.channels == 4
    finally:
        proc.terminate()
        proc.wait(10)


def test_a_scan_that_never_progresses_fails_with_what_was_delivered() -> None:
    """Heartbeats and STATUS say "scanning" while column 0 never comes: ScanStalled."""
    import pytest

    from cdma_lidar.errors import LinkError
    from cdma_lidar.protocol.link import ScanStalled

    calls = [0]

    def clock() -> float:  # 50 ms per reading; bounded, so a scan that never ends fails
        calls[0] += 1
        if calls[0] > 200_000:
            raise RuntimeError("the host waited forever")
        return calls[0] * 0.05

    # The host's waits run on its own clock, 50 ms a reading: 20 s of it pass in well
    # under the app's 120 s, and a device thread held up for seconds by a loaded machine
    # still answers STATUS within the (retries + 1) x 5 s the host gives it.
    app = _Stuck()
    host, dev = pipe_pair()
    try:
        with RunningDevice(dev, app, heartbeat_s=0.01):  # frequent: fast, not needed
            link = HostLink(host, timeout_s=5.0, progress_timeout_s=20.0, clock=clock)
            link.hello()
            with pytest.raises(ScanStalled) as exc:
                list(link.scan(frame=4))
            assert isinstance(exc.value, LinkError)
            assert exc.value.frame == 4 and exc.value.next_column == 0
            assert "no progress for 20 s" in str(exc.value)
    finally:
        app.release.set()


class _Slow(_Stuck):
    """Computes column 0 for ``stated_s`` of the HOST's clock, and says so in STATUS."""

    def __init__(self, stated_s: float) -> None:
        super().__init__()
        self.stated_s = stated_s

    def column_time_s(self) -> float:
        return self.stated_s


def _slow_scan(app: _Slow, release_at_s: float) -> tuple[list[int], str]:
    """Scan 4 columns on a 0.2 s-a-reading host clock that releases the app's column 0
    once it passes ``release_at_s``: the columns delivered, and the error if any. The
    clock stands still at 1 s until the host has heard a heartbeat (the device's thread
    may be slow to send one on a loaded machine)."""
    from cdma_lidar.errors import LinkError

    calls, links = [0], []
    step = 0.2  # s per reading

    def clock() -> float:
        if calls[0] * step < 1.0 or (links and links[0].last_status is not None):
            calls[0] += 1
        if calls[0] > 200_000:
            raise RuntimeError("the host waited forever")
        if calls[0] * step >= release_at_s:
            app.release.set()
        return calls[0] * step

    got: list[int] = []
    host, dev = pipe_pair()
    try:
        # timeout 20 s: 100 readings of silence before a reply counts as lost
        with RunningDevice(dev, app, heartbeat_s=0.01):
            link = HostLink(host, timeout_s=20.0, progress_timeout_s=20.0, clock=clock)
            links.append(link)
            link.hello()
            try:
                got.extend(c.column for c in link.scan(frame=4))
            except LinkError as exc:
                return got, str(exc)
    finally:
        app.release.set()
    return got, ""


def test_a_column_that_takes_minutes_is_waited_for_when_the_device_says_so() -> None:
    """The device states 60 s a column: 3 minutes of the host's clock pass before
    column 0, far beyond the 20 s floor, and the scan completes."""
    got, err = _slow_scan(_Slow(60.0), release_at_s=180.0)
    assert (got, err) == ([0, 1, 2, 3], "")


def test_a_device_that_overruns_its_own_column_time_is_caught() -> None:
    """Stated 10 s: the limit is 20 + 3 x 10 = 50 s of no progress, then ScanStalled."""
    got, err = _slow_scan(_Slow(10.0), release_at_s=1e9)
    assert got == [] and "no progress for 50 s" in err, err


def test_the_no_progress_limit_is_the_floor_plus_three_stated_column_times() -> None:
    from cdma_lidar.protocol.link import patience_s
    from cdma_lidar.protocol.messages import Status

    assert patience_s(10.0, None) == 10.0
    assert patience_s(10.0, Status()) == 10.0
    assert patience_s(10.0, Status(column_time_ms=250_000)) == 760.0


def test_an_early_scan_end_is_a_link_error_carrying_the_delivered_columns() -> None:
    """host/scan.py saves a partial file on any LinkError: an early end must be one."""
    import pytest

    from cdma_lidar.errors import LinkError
    from cdma_lidar.protocol.link import StreamEnded
    from cdma_lidar.protocol.messages import ScanEndReason

    app = SyntheticApp(channels=2, columns=8)
    app.fail_at = 3
    host, dev = pipe_pair()
    got = []
    with RunningDevice(dev, app):
        link = HostLink(host, timeout_s=2.0)
        link.hello()
        with pytest.raises(StreamEnded) as exc:
            got.extend(c.column for c in link.scan(frame=5))
    assert isinstance(exc.value, LinkError) and got == [0, 1, 2]
    assert (exc.value.frame, exc.value.next_column, exc.value.reason) == \
        (5, 3, ScanEndReason.ERROR)


def test_a_column_too_large_for_the_session_ends_the_scan_not_the_device(caplog) -> None:
    """The application yields columns of 8 peaks after SCAN_START was accepted at 1: the
    first needs more than MAX_PIECES fragments of 256 bytes, so the scan ends with SCAN_END
    reason 2 (nothing of it sent, nothing counted) and the device answers on."""
    import logging

    import pytest

    from cdma_lidar.protocol.link import StreamEnded
    from cdma_lidar.protocol.messages import ScanEndReason

    class Grows(SyntheticApp):
        def scan(self, frame: int, first_column: int, columns: int):  # type: ignore[override]
            self.config["peaks"] = 8  # behind set_config's back: SCAN_START checked 1
            return super().scan(frame, first_column, columns)

    dev = SteppedDevice(Grows(channels=1000, columns=4), max_frame=256)
    with dev, caplog.at_level(logging.ERROR, logger="cdma_lidar.protocol"):
        link = HostLink(dev, timeout_s=1.0, max_frame=256, clock=dev.clock)
        link.hello()
        with pytest.raises(StreamEnded) as exc:
            list(link.scan(frame=3))
        assert (exc.value.frame, exc.value.next_column, exc.value.reason) == \
            (3, 0, ScanEndReason.ERROR)
        st = link.status()
        assert st.state_name == "idle" and st.columns_sent == 0
    assert "frame 3" in caplog.text


def test_line_error_counts_rejected_chunks_since_boot_as_status_does() -> None:
    """LINE_ERROR.rx_errors is the device's count since boot (docs/protocol.md), the same
    number STATUS gives, however many connections the damage came over."""
    from cdma_lidar.protocol.endpoint import DeviceCore
    from cdma_lidar.protocol.messages import Status, decode_payload

    core = DeviceCore(SyntheticApp(channels=2, columns=4))
    first = SteppedDevice(None, core=core)
    second = SteppedDevice(None, core=core, now=first.now)
    first.write(b"\x00\x05garbage\x00" * 3)  # three damaged chunks on the first connection
    first.read(4096)
    link = HostLink(second, timeout_s=1.0, clock=second.clock)
    link.hello()
    second.write(b"\x00\x07junk\x00")  # one more, on the second connection
    heard = [f for f in link.decoder.feed(second.read(4096)) if f.msg_type == MsgType.LINE_ERROR]
    (notice,) = heard
    st = Status(**link.request(MsgType.STATUS_GET, {}))
    assert decode_payload(MsgType.LINE_ERROR, notice.payload)["rx_errors"] == 4 == st.rx_errors
