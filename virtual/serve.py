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
import tty
from collections.abc import Callable, Iterator

from cdma_lidar.protocol.endpoint import DeviceCore, DeviceEndpoint
from cdma_lidar.protocol.ports import FdPort
from cdma_lidar.scene.model import Scene
from cdma_lidar.virtual.board import VirtualFirmware

__all__ = ["serve_pty", "serve_tcp"]

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
              session_idle_s: float = 10.0) -> int:
    """Serve on a new pty; ``announce`` gets the slave path (one line). Returns 0."""

    firmware = VirtualFirmware(scene, seed)
    master, slave = os.openpty()
    tty.setraw(slave)
    path = os.ttyname(slave)
    port = FdPort(master)
    endpoint = DeviceEndpoint(port, firmware, session_idle_s=session_idle_s)
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
#: read BUSY answers or take over); more are closed at once.
MAX_CONNECTIONS = 8


def serve_tcp(scene: Scene, seed: int, host: str, port_no: int,
              announce: Callable[[str], None], *, key: bytes | None = None,
              session_idle_s: float = 10.0) -> int:
    """Serve on a TCP socket; announces ``socket://HOST:PORT``.

    Several connections are served at once (up to :data:`MAX_CONNECTIONS`), each by
    its own endpoint in front of one shared board: one host owns the session, another
    host's HELLO is answered BUSY (naming the owner's age and idle time) unless it
    takes over or the session expired. With ``key`` (32 bytes) every session is
    authenticated and every frame signed; without one the caller must bind loopback.
    """

    firmware = VirtualFirmware(scene, seed)
    core = DeviceCore(firmware, key=key, session_idle_s=session_idle_s)
    server = socket.create_server((host, port_no), reuse_port=False)
    server.settimeout(0.2)
    bound_host, bound_port = server.getsockname()[:2]
    threads: list[threading.Thread] = []
    with _stop_on_signals() as stop:
        announce(f"socket://{bound_host}:{bound_port}")
        log.info("virtual device %s (seed %d) on tcp %s:%d%s", scene.name, seed, bound_host,
                 bound_port, ", frames signed" if key else ", NO access control")
        try:
            while not stop.is_set():
                try:
                    conn, peer = server.accept()
                except TimeoutError:
                    continue
                threads = [t for t in threads if t.is_alive()]
                if len(threads) >= MAX_CONNECTIONS:
                    log.warning("refused %s:%d: %d connections already", *peer[:2],
                                MAX_CONNECTIONS)
                    conn.close()
                    continue
                log.info("host connected from %s:%d", *peer[:2])
                conn.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
                t = threading.Thread(target=_serve_connection, args=(conn, core, stop, peer),
                                     name=f"cdma-lidar-tcp-{peer[1]}", daemon=True)
                t.start()
                threads.append(t)
        finally:
            server.close()
            for t in threads:
                t.join(timeout=2.0)
    return 0


def _serve_connection(conn: socket.socket, core: DeviceCore, stop: threading.Event,
                      peer: tuple) -> None:
    sp = FdPort(conn.detach())  # the port owns and closes the descriptor
    try:
        DeviceEndpoint(sp, core=core).serve_forever(stop)
    finally:
        sp.close()
    log.info("host %s:%d disconnected", *peer[:2])
