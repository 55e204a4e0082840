"""Serve the virtual device on a pty or a TCP socket until interrupted.

``serve_pty`` creates a pseudo-terminal, announces the path of its slave end (open it
like a serial port: ``cdma-lidar scan --port /dev/pts/7``) and runs the device endpoint
on the master end. The server keeps the slave end open itself, so a host may connect,
disconnect and connect again; every connection starts with HELLO.

``serve_tcp`` listens on HOST:PORT (``socket://HOST:PORT`` for the host) and serves one
connection at a time; the virtual board (configuration, power matrix) persists across
connections, each connection gets a new session id.

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

from cdma_lidar.protocol.endpoint import DeviceEndpoint
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


def serve_pty(scene: Scene, seed: int, announce: Callable[[str], None]) -> int:
    """Serve on a new pty; ``announce`` gets the slave path (one line). Returns 0."""

    firmware = VirtualFirmware(scene, seed)
    master, slave = os.openpty()
    tty.setraw(slave)
    path = os.ttyname(slave)
    port = FdPort(master)
    endpoint = DeviceEndpoint(port, firmware)
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


def serve_tcp(scene: Scene, seed: int, host: str, port_no: int,
              announce: Callable[[str], None]) -> int:
    """Serve on a TCP socket, one connection at a time; announces ``socket://HOST:PORT``."""

    firmware = VirtualFirmware(scene, seed)
    server = socket.create_server((host, port_no), reuse_port=False)
    server.settimeout(0.2)
    bound_host, bound_port = server.getsockname()[:2]
    with _stop_on_signals() as stop:
        announce(f"socket://{bound_host}:{bound_port}")
        log.info("virtual device %s (seed %d) on tcp %s:%d", scene.name, seed, bound_host,
                 bound_port)
        try:
            while not stop.is_set():
                try:
                    conn, peer = server.accept()
                except TimeoutError:
                    continue
                log.info("host connected from %s:%d", *peer[:2])
                conn.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
                sp = FdPort(conn.detach())  # the port owns and closes the descriptor
                try:
                    DeviceEndpoint(sp, firmware).serve_forever(stop)
                finally:
                    sp.close()
                log.info("host disconnected")
        finally:
            server.close()
    return 0
