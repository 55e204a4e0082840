"""In-process byte pipes and port adapters for the virtual device, with line bit errors.

A :class:`BytePipe` carries bytes one way between threads; :class:`PipePort` gives the
device endpoint the port surface it needs (``read(n)`` with ``timeout``, ``write``,
``in_waiting``). :class:`LineNoise` flips bits at a given rate so tests can prove the link
loses nothing. :class:`SocketPort` wraps a connected TCP socket the same way.
"""

from __future__ import annotations

import select
import socket
import threading
import time

import numpy as np

from cdma_lidar.errors import out_of_range

__all__ = ["BytePipe", "LineNoise", "PipePort", "SocketPort"]


class BytePipe:
    """One-way, thread-safe byte buffer; ``read`` waits up to a timeout for ``n`` bytes."""

    def __init__(self) -> None:
        self._buf = bytearray()
        self._cv = threading.Condition()
        self.closed = False

    def write(self, data: bytes) -> None:
        with self._cv:
            self._buf += data
            self._cv.notify_all()

    def available(self) -> int:
        with self._cv:
            return len(self._buf)

    def read(self, n: int, timeout: float | None) -> bytes:
        """Up to ``n`` bytes: returns when ``n`` arrived, at the timeout, or when closed.

        ``timeout`` None blocks until ``n`` bytes; 0 returns what is there.
        """
        deadline = None if timeout is None else time.monotonic() + timeout
        with self._cv:
            while len(self._buf) < n and not self.closed:
                left = None if deadline is None else deadline - time.monotonic()
                if left is not None and left <= 0:
                    break
                self._cv.wait(left)
            out = bytes(self._buf[:n])
            del self._buf[:n]
            return out

    def clear(self) -> None:
        with self._cv:
            self._buf.clear()

    def close(self) -> None:
        with self._cv:
            self.closed = True
            self._cv.notify_all()


class LineNoise:
    """Flips each bit independently with probability ``rate`` (seeded, reproducible)."""

    def __init__(self, rate: float, seed: int = 0) -> None:
        if not (isinstance(rate, int | float) and 0.0 <= rate <= 0.5):
            raise out_of_range("line_error_rate", "a probability from 0 to 0.5", rate)
        self.rate = float(rate)
        self._rng = np.random.default_rng([seed, 0x11E])
        self._lock = threading.Lock()
        self.flipped = 0

    def __call__(self, data: bytes) -> bytes:
        if self.rate == 0.0 or not data:
            return data
        with self._lock:
            nbits = 8 * len(data)
            count = int(self._rng.binomial(nbits, self.rate))
            if count == 0:
                return data
            pos = self._rng.choice(nbits, size=count, replace=False)
        arr = np.frombuffer(data, dtype=np.uint8).copy()
        np.bitwise_xor.at(arr, pos // 8, (1 << (pos % 8)).astype(np.uint8))
        self.flipped += count
        return arr.tobytes()


class PipePort:
    """Port surface over two pipes: reads ``rx``, writes ``tx`` through ``noise``."""

    def __init__(self, rx: BytePipe, tx: BytePipe, noise: LineNoise | None = None,
                 timeout: float | None = 0.01) -> None:
        self.rx, self.tx, self.noise = rx, tx, noise
        self.timeout = timeout

    @property
    def in_waiting(self) -> int:
        if self.rx.closed and not self.rx.available():
            raise OSError("virtual line closed")
        return self.rx.available()

    def read(self, n: int = 1) -> bytes:
        if self.rx.closed and not self.rx.available():
            raise OSError("virtual line closed")
        return self.rx.read(n, self.timeout)

    def write(self, data: bytes) -> int:
        if self.tx.closed:
            raise OSError("virtual line closed")
        self.tx.write(self.noise(bytes(data)) if self.noise else bytes(data))
        return len(data)


class SocketPort:
    """Port surface over a connected TCP socket; raises OSError when the peer has gone."""

    def __init__(self, sock: socket.socket, timeout: float | None = 0.01) -> None:
        self.sock = sock
        self.timeout = timeout
        self._buf = bytearray()
        sock.setblocking(False)

    def _fill(self, wait: float | None) -> None:
        r, _, _ = select.select([self.sock], [], [], wait)
        if r:
            try:
                chunk = self.sock.recv(65536)
            except BlockingIOError:
                return
            if not chunk:
                raise OSError("peer closed the connection")
            self._buf += chunk

    @property
    def in_waiting(self) -> int:
        self._fill(0)
        return len(self._buf)

    def read(self, n: int = 1) -> bytes:
        deadline = None if self.timeout is None else time.monotonic() + self.timeout
        while len(self._buf) < n:
            left = None if deadline is None else deadline - time.monotonic()
            if left is not None and left <= 0:
                break
            self._fill(left)
        out = bytes(self._buf[:n])
        del self._buf[:n]
        return out

    def write(self, data: bytes) -> int:
        view = memoryview(bytes(data))
        while view:
            try:
                k = self.sock.send(view)
            except BlockingIOError:
                select.select([], [self.sock], [], 1.0)
                continue
            view = view[k:]
        return len(data)

    def close(self) -> None:
        self.sock.close()
