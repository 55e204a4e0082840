"""In-process byte pipe with the pyserial surface, and optional line faults.

:func:`pipe_pair` joins a host end and a device end in memory, e.g. to run a
:class:`cdma_lidar.protocol.endpoint.DeviceEndpoint` in a thread behind a ``virtual://`` URL
handler or in tests. Each direction can misbehave like a bad line, from a seeded
generator so a run is repeatable:

* per write (the endpoints write one frame per call): ``drop``, ``duplicate``,
  ``reorder`` (held back and delivered after the next write), ``corrupt`` (one bit
  flipped);
* per byte: ``bit_error_rate`` (each byte has one bit flipped with this probability).
"""

from __future__ import annotations

import random
import threading
from dataclasses import dataclass

from cdma_lidar.errors import out_of_range

__all__ = ["Faults", "PipePort", "pipe_pair"]


@dataclass(frozen=True)
class Faults:
    """Fault probabilities of one direction (each in 0..1)."""

    drop: float = 0.0
    duplicate: float = 0.0
    corrupt: float = 0.0
    reorder: float = 0.0
    bit_error_rate: float = 0.0

    def __post_init__(self) -> None:
        for name in ("drop", "duplicate", "corrupt", "reorder", "bit_error_rate"):
            v = getattr(self, name)
            if not 0.0 <= v <= 1.0:
                raise out_of_range(name, "a probability from 0 to 1", v)

    @property
    def any(self) -> bool:
        """True when some fault can happen."""
        return any((self.drop, self.duplicate, self.corrupt, self.reorder,
                    self.bit_error_rate))


class _Pipe:
    """One direction: a locked byte buffer with fault injection on write."""

    def __init__(self, faults: Faults | None, seed: int) -> None:
        self.buf = bytearray()
        self.cond = threading.Condition()
        self.faults = faults or Faults()
        self.rng = random.Random(seed)
        self.held: bytes | None = None
        self.closed = False

    def _mangle(self, data: bytes) -> list[bytes]:
        f, r = self.faults, self.rng
        if r.random() < f.drop:
            out: list[bytes] = []
        else:
            b = bytearray(data)
            if b and r.random() < f.corrupt:
                b[r.randrange(len(b))] ^= 1 << r.randrange(8)
            if b and f.bit_error_rate:
                k = 0
                while True:  # geometric gaps between corrupted bytes
                    k += int(r.expovariate(f.bit_error_rate)) if f.bit_error_rate < 1 else 0
                    if k >= len(b):
                        break
                    b[k] ^= 1 << r.randrange(8)
                    k += 1
            out = [bytes(b)]
            if r.random() < f.duplicate:
                out.append(bytes(b))
        if out and self.held is None and r.random() < f.reorder:
            self.held = out.pop(0)
        elif self.held is not None:
            out.append(self.held)
            self.held = None
        return out

    def push(self, data: bytes) -> None:
        with self.cond:
            if self.closed:
                raise OSError("pipe closed")
            for d in self._mangle(data) if self.faults.any else [bytes(data)]:
                self.buf += d
            self.cond.notify_all()


class PipePort:
    """One end of a :func:`pipe_pair`: ``read``, ``write``, ``in_waiting``, ``timeout``.

    ``read(n)`` follows pyserial: it waits until ``n`` bytes or ``timeout`` seconds
    (None: forever), then returns what it has. ``max_read`` caps the bytes returned
    per call, to exercise callers against partial reads.
    """

    def __init__(self, rx: _Pipe, tx: _Pipe, name: str, max_read: int | None = None) -> None:
        self._rx, self._tx = rx, tx
        self.timeout: float | None = 0.05
        self.max_read = max_read
        self.name = name
        self.is_open = True

    @property
    def in_waiting(self) -> int:
        """Bytes ready to read."""
        if self._rx.closed and not self._rx.buf:
            raise OSError("pipe closed")
        return len(self._rx.buf)

    def read(self, n: int = 1) -> bytes:
        """Up to ``n`` bytes (fewer when the timeout expires or ``max_read`` is set)."""
        want = min(n, self.max_read or n)
        rx = self._rx
        with rx.cond:
            rx.cond.wait_for(lambda: len(rx.buf) >= want or rx.closed, self.timeout)
            if rx.closed and not rx.buf:
                raise OSError("pipe closed")
            data = bytes(rx.buf[:want])
            del rx.buf[:want]
            return data

    def write(self, data: bytes) -> int:
        """Send ``data`` to the other end (through the faults of this direction)."""
        self._tx.push(data)
        return len(data)

    def flush(self) -> None:
        """Nothing to flush."""

    def close(self) -> None:
        """Close both directions; the peer's next read or write raises OSError."""
        self.is_open = False
        for p in (self._rx, self._tx):
            with p.cond:
                p.closed = True
                p.cond.notify_all()


def pipe_pair(to_device: Faults | None = None, to_host: Faults | None = None, seed: int = 0,
              max_read: int | None = None) -> tuple[PipePort, PipePort]:
    """(host end, device end) of an in-memory link, with optional faults per direction."""
    down = _Pipe(to_device, seed)
    up = _Pipe(to_host, seed + 1)
    return (PipePort(up, down, "pipe://host", max_read),
            PipePort(down, up, "pipe://device", max_read))
