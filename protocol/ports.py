"""Ports onto the operating system: pyserial URLs, TCP, and raw file descriptors.

A port needs only ``read(n)`` waiting at most ``timeout`` s, ``write(data)``,
``in_waiting`` (bytes ready) and ``close()``. :func:`open_port` opens any pyserial URL
(device path, pty, ``socket://``, ``loop://``, or a scheme an imported package registered,
such as ``virtual://``); :class:`FdPort` wraps a file descriptor (a pty master, an accepted
socket). The simulated in-process line is :mod:`cdma_lidar.virtual.line`.
"""

from __future__ import annotations

import fcntl
import os
import select
import struct
import termios
import time
from typing import Any

import serial
from serial.urlhandler.protocol_socket import Serial as SocketSerial

from cdma_lidar.errors import ConfigError, LinkError

__all__ = ["DEFAULT_BAUD", "FdPort", "TcpPort", "byte_time_s", "default_fec", "open_port",
           "port_name"]

#: Serial line rate the protocol uses unless told otherwise (bit/s, 8N1); USB CDC ignores it.
DEFAULT_BAUD = 921600


def _bytes_ready(fd: int) -> int:
    """FIONREAD: bytes readable on ``fd`` without blocking (pty, pipe or socket)."""
    return struct.unpack("i", fcntl.ioctl(fd, termios.FIONREAD, b"\0\0\0\0"))[0]


def port_name(port: Any) -> str:
    """What a port calls itself (its URL or path), for messages and logs; else its type."""
    return str(getattr(port, "name", None) or type(port).__name__)  # pyserial: = portstr


def default_fec(port: Any) -> bool:
    """Whether frames on ``port`` are Reed-Solomon coded by default: yes on a serial line
    (a device path such as ``/dev/ttyUSB0``, a pty, ``virtual://``), no where bytes arrive
    intact (``socket://``, USB ``/dev/ttyACM*``) and elsewhere (``loop://``, pipes)."""
    name = port_name(port)
    return (name.startswith("/dev/") and "ttyACM" not in name) or \
        name.lower().startswith("virtual://")


def byte_time_s(port: Any) -> float:
    """Seconds one byte takes on ``port``'s line (8N1: 10 bit times), 0 when unknown: a
    serial line's ``baudrate``, ``line_baud`` (``virtual://``), a paced pipe's ``tx.baud``."""
    baud = getattr(port, "line_baud", None) or getattr(getattr(port, "tx", None), "baud", None)
    if baud is None and default_fec(port) and not port_name(port).startswith("virtual://"):
        baud = getattr(port, "baudrate", None)
    return 10.0 / baud if isinstance(baud, int | float) and baud > 0 else 0.0


def open_port(url: str, baudrate: int = DEFAULT_BAUD, timeout: float = 0.05, **kw: Any) -> Any:
    """Open any pyserial URL (``socket://`` as a :class:`TcpPort`); LinkError with a
    one-line hint when it cannot (naming the scheme when no handler is registered)."""
    try:
        if url.lower().startswith("socket://"):
            return TcpPort(url, baudrate=baudrate, timeout=timeout, **kw)
        return serial.serial_for_url(url, baudrate=baudrate, timeout=timeout, **kw)
    except (serial.SerialException, OSError, ValueError) as exc:
        scheme = url.split("://", 1)[0] if "://" in url else ""
        if isinstance(exc.__cause__ or exc, ConfigError):  # a setting: the error names it
            raise LinkError(f"cannot open port {url!r}: {exc}") from None
        if scheme and "invalid URL" in str(exc):
            hint = (f"unknown URL scheme {scheme!r}: no handler is registered for "
                    f"{scheme}://; use a device path or socket://, or import the package "
                    "that provides the scheme first")
        elif "://" in url:
            hint = "check the URL and that its server or handler is available"
        else:
            hint = "check the device is plugged in and the path is right (ls /dev/tty*)"
        raise LinkError(f"cannot open port {url!r}: {exc}; {hint}") from None


class TcpPort(SocketSerial):
    """``socket://HOST:PORT`` with a true ``in_waiting`` (bytes, from FIONREAD): pyserial's
    says 1 whenever anything is readable, so reads of ``in_waiting`` bytes got one byte
    per call (about 80 columns/s instead of thousands)."""

    @property
    def in_waiting(self) -> int:
        if not self.is_open:
            raise serial.PortNotOpenError()
        return _bytes_ready(self._socket.fileno())


class FdPort:
    """The port surface over a file descriptor (a pty master from ``os.openpty``, a socket:
    pass ``sock.detach()``), put in non-blocking mode, owned and closed by the port.
    ``timeout``: longest wait of one read (s, None: forever); ``write_timeout``: see
    :meth:`write`."""

    def __init__(self, fd: int, timeout: float | None = 0.05,
                 write_timeout: float = 5.0) -> None:
        self.fd, self.timeout, self.write_timeout = fd, timeout, write_timeout
        os.set_blocking(fd, False)
        self._closed = False

    @property
    def in_waiting(self) -> int:
        return _bytes_ready(self.fd)

    def read(self, n: int = 1) -> bytes:
        """Up to ``n`` bytes, fewer when ``timeout`` expires; OSError at end of file (as
        pyserial), so a caller never spins on a descriptor readable but empty."""
        out = bytearray()
        deadline = None if self.timeout is None else time.monotonic() + self.timeout
        while len(out) < n:
            left = None if deadline is None else max(0.0, deadline - time.monotonic())
            if not select.select([self.fd], [], [], left)[0]:
                break
            try:
                chunk = os.read(self.fd, n - len(out))
            except BlockingIOError:
                continue
            if not chunk:
                raise OSError(f"fd {self.fd}: end of file (the other side closed)")
            out += chunk
        return bytes(out)

    def write(self, data: bytes) -> int:
        """Write all of ``data``, waiting while the buffer is full; OSError when no byte
        went for ``write_timeout`` s: a peer that stopped reading must not hold the device
        (and every other host) up."""
        view = memoryview(data)
        while view:
            try:
                view = view[os.write(self.fd, view):]
            except BlockingIOError:
                if not select.select([], [self.fd], [], self.write_timeout)[1]:
                    raise OSError(f"fd {self.fd}: no byte written for {self.write_timeout:g} "
                                  "s (the other side does not read)") from None
        return len(data)

    def close(self) -> None:
        """Close the descriptor (once)."""
        if not self._closed:
            self._closed = True
            os.close(self.fd)
