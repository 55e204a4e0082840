"""Ports onto the operating system: pyserial URLs, TCP, and raw file descriptors.

The protocol needs only a small port surface: ``read(n)`` that waits at most
``timeout`` seconds, ``write(data)``, ``in_waiting`` (bytes ready) and ``close()``.
:func:`open_port` gives one for any pyserial URL (a device path, a pty, ``socket://``,
``loop://``, or a scheme some imported package registered with pyserial, such as the
virtual device's); :class:`FdPort` gives one around a file descriptor (a pty master,
an accepted TCP socket). The simulated in-process line is :mod:`cdma_lidar.virtual.line`.
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

from cdma_lidar.errors import LinkError

__all__ = ["DEFAULT_BAUD", "FdPort", "TcpPort", "byte_time_s", "default_fec", "open_port",
           "port_name"]


def _bytes_ready(fd: int) -> int:
    """FIONREAD: bytes readable on ``fd`` without blocking (pty, pipe or socket)."""
    buf = fcntl.ioctl(fd, termios.FIONREAD, b"\0\0\0\0")
    return struct.unpack("i", buf)[0]


#: Serial line rate the protocol uses unless told otherwise (bit/s, 8N1); USB CDC ignores it.
DEFAULT_BAUD = 921600


def port_name(port: Any) -> str:
    """What a port calls itself (its URL or path), for messages and logs; else its type."""
    return str(getattr(port, "portstr", None) or getattr(port, "name", None)
               or type(port).__name__)


def default_fec(port: Any) -> bool:
    """Whether frames on ``port`` are Reed-Solomon coded by default: yes on a serial line
    (a device path such as ``/dev/ttyUSB0`` or a pty, and ``virtual://``, which stands for
    one), no where the transport delivers intact bytes (TCP ``socket://``, USB bulk
    ``/dev/ttyACM*``) and on anything else (``loop://``, in-process pipes: the caller
    says)."""
    if isinstance(port, TcpPort):
        return False
    name = port_name(port)
    return (name.startswith("/dev/") and "ttyACM" not in name) or \
        name.lower().startswith("virtual://")


def byte_time_s(port: Any) -> float:
    """Seconds one byte takes on ``port``'s line (8N1: 10 bit times), 0 when unknown: a
    serial line's ``baudrate``, a port's ``line_baud`` (``virtual://``), a paced pipe's
    ``tx.baud``; nothing for TCP and unpaced pipes."""
    baud = getattr(port, "line_baud", None) or getattr(getattr(port, "tx", None), "baud", None)
    if baud is None and default_fec(port) and not port_name(port).startswith("virtual://"):
        baud = getattr(port, "baudrate", None)
    return 10.0 / baud if isinstance(baud, int | float) and baud > 0 else 0.0


def open_port(url: str, baudrate: int = DEFAULT_BAUD, timeout: float = 0.05, **kw: Any) -> Any:
    """Open any pyserial URL (device path, pty, ``socket://``, ``loop://``, registered schemes).

    ``socket://`` opens a :class:`TcpPort`. Raises LinkError with a one-line hint when
    the port does not exist or cannot be opened, or when no handler is registered
    for the URL's scheme (the message names the scheme).
    """
    try:
        if url.lower().startswith("socket://"):
            return TcpPort(url, baudrate=baudrate, timeout=timeout, **kw)
        return serial.serial_for_url(url, baudrate=baudrate, timeout=timeout, **kw)
    except (serial.SerialException, OSError, ValueError) as exc:
        scheme = url.split("://", 1)[0] if "://" in url else ""
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
    """``socket://HOST:PORT`` as pyserial opens it, with a true ``in_waiting`` (bytes).

    pyserial's handler reports 1 whenever anything is readable, so a reader that asks
    for ``in_waiting`` bytes gets one byte per call: about 80 columns/s instead of
    thousands. FIONREAD on the socket gives the real count.
    """

    @property
    def in_waiting(self) -> int:
        """Bytes ready to read."""
        if not self.is_open:
            raise serial.PortNotOpenError()
        return _bytes_ready(self._socket.fileno())


class FdPort:
    """Minimal port over a file descriptor (a pty master from ``os.openpty``, a socket).

    Same surface as a pyserial port as far as the protocol uses it: ``read(n)``
    blocks until ``n`` bytes or ``timeout`` seconds, ``write``, ``in_waiting``,
    ``timeout``, ``close``. The fd is put in non-blocking mode; the port owns it and
    closes it in :meth:`close` (for a socket, pass ``sock.detach()``).
    """

    def __init__(self, fd: int, timeout: float | None = 0.05,
                 write_timeout: float = 5.0) -> None:
        self.fd = fd
        self.timeout = timeout
        self.write_timeout = write_timeout
        os.set_blocking(fd, False)
        self._closed = False

    @property
    def in_waiting(self) -> int:
        """Bytes ready to read without blocking."""
        return _bytes_ready(self.fd)

    def read(self, n: int = 1) -> bytes:
        """Up to ``n`` bytes; returns early with fewer when ``timeout`` expires.

        Raises OSError at end of file, like pyserial, so a caller never spins on a
        descriptor that is always readable but empty.
        """
        out = bytearray()
        deadline = None if self.timeout is None else time.monotonic() + self.timeout
        while len(out) < n:
            left = None if deadline is None else max(0.0, deadline - time.monotonic())
            r, _, _ = select.select([self.fd], [], [], left)
            if not r:
                break
            try:
                chunk = os.read(self.fd, n - len(out))
            except BlockingIOError:
                continue
            if not chunk:  # end of file: readable but nothing to read
                raise OSError(f"fd {self.fd}: end of file (the other side closed)")
            out += chunk
        return bytes(out)

    def write(self, data: bytes) -> int:
        """Write all of ``data``, waiting while the pty or socket buffer is full.

        Raises OSError when no byte could be written for ``write_timeout`` seconds: a
        peer that stopped reading must not hold the device (and every other host) up.
        """
        view = memoryview(data)
        while view:
            try:
                k = os.write(self.fd, view)
            except BlockingIOError:
                _, w, _ = select.select([], [self.fd], [], self.write_timeout)
                if not w:
                    raise OSError(f"fd {self.fd}: no byte written for {self.write_timeout:g} "
                                  "s (the other side does not read)") from None
                continue
            view = view[k:]
        return len(data)

    def close(self) -> None:
        """Close the descriptor (once)."""
        if not self._closed:
            self._closed = True
            os.close(self.fd)
