"""Serve the virtual device on a pty or a TCP socket until interrupted.

``serve_pty`` creates a pseudo-terminal, announces the path of its slave end (open it
like a serial port: ``cdma-lidar scan --port /dev/pts/7``) and runs the device endpoint
on the master end. The server keeps the slave end open itself, so a host may connect,
disconnect and connect again; every connection starts with HELLO.

``serve_tcp`` listens on HOST:PORT (``socket://HOST:PORT`` for the host) and serves
several connections at once in front of one board: one host owns the session (see
docs/protocol.md, Sessions), every HELLO opens a fresh session that starts from the
board's defaults unless the host asks to keep the configuration. With a key every
session is authenticated (challenge-response HELLO) and every frame signed.

Both return 0 on SIGTERM or SIGINT (Ctrl-C), after closing their ports.
"""

from __future__ import annotations

import contextlib
import logging
import os
import signal
import socket
import threading
import time
import tty
from collections.abc import Callable, Iterator
from dataclasses import dataclass

from cdma_lidar.protocol.endpoint import DeviceCore, DeviceEndpoint
from cdma_lidar.protocol.ports import FdPort
from cdma_lidar.scene.model import Scene
from cdma_lidar.virtual.board import VirtualFirmware

__all__ = ["HELLO_DEADLINE_S", "MAX_CONNECTIONS", "Connections", "serve_connections", "serve_pty",
           "serve_tcp"]

log = logging.getLogger(__name__)


@contextlib.contextmanager
def _stop_on_signals() -> Iterator[threading.Event]:
    stop = threading.Event()

    def handler(signum: int, frame: object) -> None:
        stop.set()

    old = {s: signal.signal(s, handler) for s in (signal.SIGTERM, signal.SIGINT)}
    try:
        yield stop
    finally:
        for s, h in old.items():
            signal.signal(s, h)


def serve_pty(scene: Scene, seed: int, announce: Callable[[str], None], *,
              key: bytes | None = None, session_idle_s: float = 10.0) -> int:
    """Serve on a new pty; ``announce`` gets the slave path (one line). Returns 0.

    A serial line codes its frames (FEC) when the host asks; with ``key`` (32 bytes)
    every session is authenticated and signed too (keyed and coded at once)."""

    firmware = VirtualFirmware(scene, seed)
    master, slave = os.openpty()
    tty.setraw(slave)
    path = os.ttyname(slave)
    port = FdPort(master)
    endpoint = DeviceEndpoint(port, firmware, key=key, session_idle_s=session_idle_s)
    with _stop_on_signals() as stop:
        announce(path)
        log.info("virtual device %s (seed %d) on %s", scene.name, seed, path)
        try:
            while not stop.is_set():
                endpoint.serve_forever(stop)
                if not stop.is_set():  # the port failed: keep serving after a short pause
                    stop.wait(0.1)
        finally:
            port.close()
            os.close(slave)
    return 0


#: Connections served at once by the TCP server (one owns the session, the others may
#: read BUSY answers or take over).
MAX_CONNECTIONS = 8
#: A connection without a session for this long (s) is closed: it never said HELLO, or
#: never proved it holds the key, or its session ended. When all MAX_CONNECTIONS are in
#: use, a new connection closes the connection that has been without a session longest,
#: so silent peers can never lock a key holder out.
HELLO_DEADLINE_S = 5.0


@dataclass
class _Conn:
    endpoint: DeviceEndpoint
    stop: threading.Event
    thread: threading.Thread | None = None


class Connections:
    """The TCP server's connections, at most ``limit``, none sessionless for long.

    Args:
        limit: connections served at once.
        hello_deadline_s: a connection without a session this long is closed (s).
        clock: monotonic clock (s), the endpoints' clock; replaceable in tests.
    """

    def __init__(self, limit: int = MAX_CONNECTIONS, hello_deadline_s: float = HELLO_DEADLINE_S,
                 clock: Callable[[], float] = time.monotonic) -> None:
        self.limit, self.hello_deadline_s, self.clock = limit, hello_deadline_s, clock
        self.items: list[_Conn] = []

    def sweep(self) -> list[_Conn]:
        """Forget finished connections; close (stop) those sessionless past the deadline."""
        now = self.clock()
        dropped = [c for c in self.items if c.stop.is_set() or
                   (c.thread is not None and not c.thread.is_alive()) or
                   (not c.endpoint.session.open and
                    now - c.endpoint.session.sessionless_since >= self.hello_deadline_s)]
        for c in dropped:
            if not c.stop.is_set():
                log.info("closing %s: no session for %g s", c.endpoint.session.peer,
                         self.hello_deadline_s)
                c.stop.set()
            self.items.remove(c)
        return dropped

    def admit(self, conn: _Conn) -> bool:
        """Add ``conn``, closing the longest-sessionless connection if all are in use.

        False (``conn`` not added) only when every connection holds a session.
        """
        self.sweep()
        if len(self.items) >= self.limit:
            idle = [c for c in self.items if not c.endpoint.session.open]
            if not idle:
                return False
            oldest = min(idle, key=lambda c: c.endpoint.session.sessionless_since)
            log.info("closing %s to make room: no session", oldest.endpoint.session.peer)
            oldest.stop.set()
            self.items.remove(oldest)
        self.items.append(conn)
        return True


def serve_tcp(scene: Scene, seed: int, host: str, port_no: int,
              announce: Callable[[str], None], *, key: bytes | None = None,
              session_idle_s: float = 10.0) -> int:
    """Serve on a TCP socket; announces ``socket://HOST:PORT`` (``[::1]`` for IPv6).

    Several connections are served at once (see :class:`Connections`), each by its own
    endpoint in front of one shared board: one host owns the session, another host's
    HELLO is answered BUSY (naming the owner's age and idle time) unless it takes over
    or the session expired. With ``key`` (32 bytes) every session is authenticated and
    every frame signed; without one the caller must bind loopback.
    """

    firmware = VirtualFirmware(scene, seed)
    core = DeviceCore(firmware, key=key, session_idle_s=session_idle_s)
    server = socket.create_server((host, port_no), reuse_port=False,
                                  family=socket.AF_INET6 if ":" in host else socket.AF_INET)
    bound_host, bound_port = server.getsockname()[:2]
    shown = f"[{bound_host}]" if ":" in bound_host else bound_host
    with _stop_on_signals() as stop:
        announce(f"socket://{shown}:{bound_port}")
        log.info("virtual device %s (seed %d) on tcp %s:%d%s", scene.name, seed, shown,
                 bound_port, ", frames signed" if key else ", NO access control")
        serve_connections(server, core, stop)
    return 0


def serve_connections(server: socket.socket, core: DeviceCore, stop: threading.Event,
                      conns: Connections | None = None) -> None:
    """Accept connections on ``server`` until ``stop``; serve each in a thread (its
    loop) in front of ``core`` (and its engine). Closes ``server`` and waits for the
    connections' threads when done."""
    conns = conns or Connections(clock=core.clock)
    server.settimeout(0.2)
    try:
        while not stop.is_set():
            conns.sweep()
            try:
                sock, peer = server.accept()
            except TimeoutError:
                continue
            sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            port = FdPort(sock.detach())  # the port owns and closes the descriptor
            conn = _Conn(DeviceEndpoint(port, core=core, peer=str(peer[0]), fec=False),
                         threading.Event())
            if not conns.admit(conn):
                log.warning("refused %s:%d: %d connections hold sessions", *peer[:2],
                            conns.limit)
                port.close()
                continue
            log.info("host connected from %s:%d", *peer[:2])
            conn.thread = threading.Thread(target=_serve_connection, args=(conn, peer),
                                           name=f"cdma-lidar-tcp-{peer[1]}", daemon=True)
            conn.thread.start()
    finally:
        server.close()
        for c in conns.items:
            c.stop.set()
        for c in conns.items:
            if c.thread is not None:
                c.thread.join(timeout=2.0)
        core.engine.close()


def _serve_connection(conn: _Conn, peer: tuple) -> None:
    try:
        conn.endpoint.serve_forever(conn.stop)
    finally:
        conn.endpoint.port.close()
    log.info("host %s:%d disconnected", *peer[:2])
