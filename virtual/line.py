"""The simulated line: in-process byte pipes with the port surface, and seeded line faults.

It stands for the cable and UART between a host and a device (the protocol itself
never needs it): ``virtual://`` builds its line from it, and tests put a
:class:`cdma_lidar.protocol.endpoint.DeviceEndpoint` on one end of :func:`pipe_pair`.

A :class:`BytePipe` carries bytes one way between threads. A :class:`PipePort` reads
one pipe and writes another, with the surface a pyserial port shows the protocol
(``read(n)`` waiting up to ``timeout``, ``write``, ``in_waiting``, ``close``);
:func:`pipe_pair` joins a host end and a device end.

Each pipe can misbehave like a bad line, from seeded generators so a run is
repeatable:

* per write (the endpoints write one frame per call), :class:`Faults`: ``drop``,
  ``duplicate``, ``reorder`` (held back and delivered after the next write),
  ``corrupt`` (one bit flipped);
* per bit, :class:`LineNoise`: each bit flipped independently with a probability
  (``Faults.bit_error_rate``, or one LineNoise shared by both directions).

A pipe may also keep a line's pace (``baud``): bytes then reach the reader no faster
than a UART sends them (8N1: 10 bit times per byte, so 921600 baud is 92,160 bytes/s),
and a writer waits while more than ``tx_buffer`` bytes are still on their way, as
``write`` on a serial port blocks when the driver's buffer is full. Without a pace the
pipe is as fast as memory, which measures the code, not the line.
"""

from __future__ import annotations

import random
import threading
import time
from collections import deque
from dataclasses import dataclass

import numpy as np

from cdma_lidar.errors import out_of_range

__all__ = ["BytePipe", "Faults", "LineNoise", "PipePort", "pipe_pair"]

#: Largest bit error rate: beyond one half, flipping is just another code.
MAX_BIT_ERROR_RATE = 0.5
#: Bit times per byte on a UART line with 8 data bits, no parity, 1 stop bit (8N1).
BITS_PER_BYTE = 10
#: Fastest pace a paced pipe takes (baud): beyond this the pace is below the pipe's own cost.
MAX_BAUD = 1_000_000_000
#: Bytes a paced writer may have on their way before ``write`` waits (a driver's buffer).
TX_BUFFER = 1024


@dataclass(frozen=True)
class Faults:
    """Fault probabilities of one direction (each in 0..1; ``bit_error_rate`` in 0..0.5).

    ``drop``, ``duplicate``, ``corrupt`` and ``reorder`` act per write;
    ``bit_error_rate`` is the probability of flipping each bit (see :class:`LineNoise`).
    """

    drop: float = 0.0
    duplicate: float = 0.0
    corrupt: float = 0.0
    reorder: float = 0.0
    bit_error_rate: float = 0.0

    def __post_init__(self) -> None:
        for name in ("drop", "duplicate", "corrupt", "reorder"):
            v = getattr(self, name)
            if not 0.0 <= v <= 1.0:
                raise out_of_range(name, "a probability from 0 to 1", v)
        if not 0.0 <= self.bit_error_rate <= MAX_BIT_ERROR_RATE:
            raise out_of_range("bit_error_rate", "a probability from 0 to 0.5",
                               self.bit_error_rate)

    @property
    def any(self) -> bool:
        """True when some fault can happen."""
        return any((self.drop, self.duplicate, self.corrupt, self.reorder,
                    self.bit_error_rate))


class LineNoise:
    """Flips each bit of one direction's byte stream independently with probability ``rate``.

    Which bits flip depends only on their position in the stream and on ``seed``: the
    gaps between flipped bits are drawn in order from a seeded generator (geometric,
    mean ``1 / rate`` bits), so the same seed damages the same bit positions however
    the stream is cut into writes and whatever the other direction does (a line is
    two LineNoise, one per direction). ``flipped`` counts the bits flipped so far.
    """

    def __init__(self, rate: float, seed: int | list[int] = 0) -> None:
        if not (isinstance(rate, int | float) and 0.0 <= rate <= MAX_BIT_ERROR_RATE):
            raise out_of_range("line_error_rate", "a probability from 0 to 0.5", rate)
        self.rate = float(rate)
        self._rng = np.random.default_rng([*np.atleast_1d(seed).tolist(), 0x11E])
        self._lock = threading.Lock()
        self._pos = 0  # bits of the stream so far
        self._next = self._gap() - 1 if self.rate else 0  # bit position of the next flip
        self.flipped = 0

    def _gap(self) -> int:
        return int(self._rng.geometric(self.rate))

    def __call__(self, data: bytes) -> bytes:
        """``data`` with its bit errors (the same object when none)."""
        if self.rate == 0.0 or not data:
            return data
        with self._lock:
            start, end = self._pos, self._pos + 8 * len(data)
            pos = []
            while self._next < end:
                pos.append(self._next - start)
                self._next += self._gap()
            self._pos = end
        if not pos:
            return data
        at = np.asarray(pos)
        arr = np.frombuffer(data, dtype=np.uint8).copy()
        np.bitwise_xor.at(arr, at // 8, (1 << (at % 8)).astype(np.uint8))
        self.flipped += len(pos)
        return arr.tobytes()


class BytePipe:
    """One direction of a line: a thread-safe byte buffer, faults applied on write.

    Args:
        faults: what this direction does to each write (default: nothing).
        seed: seed of the per-write faults and of the bit errors of ``faults``.
        noise: bit errors shared with other pipes (the virtual device's line); by
            default a :class:`LineNoise` of ``faults.bit_error_rate`` when that is set.

    ``faults`` may be replaced while the pipe is in use; the bit errors stay.
    """

    def __init__(self, faults: Faults | None = None, seed: int = 0,
                 noise: LineNoise | None = None, baud: int | None = None,
                 tx_buffer: int = TX_BUFFER) -> None:
        if baud is not None and not (isinstance(baud, int) and 1 <= baud <= MAX_BAUD):
            raise out_of_range("baud", f"an integer from 1 to {MAX_BAUD} bit/s", baud)
        if not (isinstance(tx_buffer, int) and tx_buffer >= 1):
            raise out_of_range("tx_buffer", "an integer of at least 1 byte", tx_buffer)
        self._buf = bytearray()
        self._cv = threading.Condition()
        self.closed = False
        self.faults = faults or Faults()
        self.noise = noise if noise is not None or not self.faults.bit_error_rate else \
            LineNoise(self.faults.bit_error_rate, seed)
        self._rng = random.Random(seed)
        self._held: bytes | None = None
        self.baud = baud
        self.tx_buffer = tx_buffer
        self._byte_s = 0.0 if baud is None else BITS_PER_BYTE / baud  # s per byte
        self._flight: deque[tuple[float, bytes]] = deque()  # (arrival time, bytes) on the line
        self._in_flight = 0  # bytes in _flight
        self._line_free = 0.0  # monotonic time the last byte on the line arrives

    def _impair(self, data: bytes) -> list[bytes]:
        """What reaches the buffer of one write of ``data``."""
        f, r = self.faults, self._rng
        if not f.any:
            return [self.noise(data) if self.noise is not None else data]
        if r.random() < f.drop:
            out: list[bytes] = []
        else:
            b = bytearray(data)
            if b and r.random() < f.corrupt:
                b[r.randrange(len(b))] ^= 1 << r.randrange(8)
            one = self.noise(bytes(b)) if self.noise is not None else bytes(b)
            out = [one]
            if r.random() < f.duplicate:
                out.append(one)
        if out and self._held is None and r.random() < f.reorder:
            self._held = out.pop(0)
        elif self._held is not None:
            out.append(self._held)
            self._held = None
        return out

    def write(self, data: bytes) -> None:
        """Append ``data`` (through the faults); raises OSError once the pipe is closed.

        On a paced pipe the bytes arrive after their time on the line, and ``write``
        first waits while more than ``tx_buffer`` bytes are on their way.
        """
        data = bytes(data)
        with self._cv:
            if self.closed:
                raise OSError("pipe closed")
            chunks = self._impair(data)
            if not self._byte_s:
                for chunk in chunks:
                    self._buf += chunk
                self._cv.notify_all()
                return
            while self._in_flight and self._in_flight + len(data) > self.tx_buffer:
                self._arrive()
                if self.closed:
                    raise OSError("pipe closed")
                if self._flight:
                    self._cv.wait(max(0.0, self._flight[0][0] - time.monotonic()))
            for chunk in chunks:  # a duplicate costs line time too
                start = max(time.monotonic(), self._line_free)
                self._line_free = start + len(chunk) * self._byte_s
                self._flight.append((self._line_free, chunk))
                self._in_flight += len(chunk)
            self._cv.notify_all()

    def _arrive(self) -> None:
        """Move the bytes whose time on the line is over into the read buffer (lock held)."""
        now = time.monotonic()
        while self._flight and self._flight[0][0] <= now:
            _, chunk = self._flight.popleft()
            self._in_flight -= len(chunk)
            self._buf += chunk
            self._cv.notify_all()

    def available(self) -> int:
        """Bytes ready to read."""
        with self._cv:
            self._arrive()
            return len(self._buf)

    def read(self, n: int, timeout: float | None) -> bytes:
        """Up to ``n`` bytes: returns when ``n`` arrived, at the timeout (s), or when closed.

        ``timeout`` None blocks until ``n`` bytes; 0 returns what is there.
        """
        deadline = None if timeout is None else time.monotonic() + timeout
        with self._cv:
            self._arrive()
            while len(self._buf) < n and not self.closed:
                now = time.monotonic()
                left = None if deadline is None else deadline - now
                if left is not None and left <= 0:
                    break
                if self._flight:  # wake when the next chunk is due
                    due = self._flight[0][0] - now
                    left = due if left is None else min(left, due)
                self._cv.wait(max(0.0, left) if left is not None else None)
                self._arrive()
            out = bytes(self._buf[:n])
            del self._buf[:n]
            return out

    def clear(self) -> None:
        """Drop what is buffered (and what is still on the line)."""
        with self._cv:
            self._buf.clear()
            self._flight.clear()
            self._in_flight = 0

    def close(self) -> None:
        """Close: readers return what is left, then the port above raises OSError."""
        with self._cv:
            self.closed = True
            self._cv.notify_all()


class PipePort:
    """Port surface over two pipes: reads ``rx``, writes ``tx``.

    ``read(n)`` follows pyserial: it waits until ``n`` bytes or ``timeout`` seconds
    (None: forever), then returns what it has. ``max_read`` caps the bytes returned
    per call, to exercise callers against partial reads. Reading a closed, drained
    pipe or writing a closed one raises OSError, as a vanished serial port does.
    """

    def __init__(self, rx: BytePipe, tx: BytePipe, name: str = "pipe",
                 max_read: int | None = None, timeout: float | None = 0.05) -> None:
        self.rx, self.tx = rx, tx
        self.name = name
        self.max_read = max_read
        self.timeout = timeout
        self.is_open = True

    @property
    def in_waiting(self) -> int:
        """Bytes ready to read."""
        n = self.rx.available()
        if not n and self.rx.closed:
            raise OSError("pipe closed")
        return n

    def read(self, n: int = 1) -> bytes:
        """Up to ``n`` bytes (fewer when the timeout expires or ``max_read`` is set)."""
        data = self.rx.read(min(n, self.max_read or n), self.timeout)
        if not data and self.rx.closed:
            raise OSError("pipe closed")
        return data

    def write(self, data: bytes) -> int:
        """Send ``data`` to the other end (through the faults of this direction)."""
        self.tx.write(data)
        return len(data)

    def flush(self) -> None:
        """Nothing to flush."""

    def close(self) -> None:
        """Close both directions; the peer's next read or write raises OSError."""
        self.is_open = False
        self.rx.close()
        self.tx.close()


def pipe_pair(to_device: Faults | None = None, to_host: Faults | None = None, seed: int = 0,
              max_read: int | None = None, baud: int | None = None
              ) -> tuple[PipePort, PipePort]:
    """(host end, device end) of an in-memory link, with optional faults per direction and
    an optional UART pace ``baud`` (bit/s, 8N1) both ways."""
    down = BytePipe(to_device, seed, baud=baud)
    up = BytePipe(to_host, seed + 1, baud=baud)
    return (PipePort(up, down, "pipe://host", max_read),
            PipePort(down, up, "pipe://device", max_read))
