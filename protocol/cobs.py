"""Consistent Overhead Byte Stuffing (COBS): removes every 0x00 byte from a frame.

Cheshire and Baker (1999). The data is cut at each zero byte into blocks; each block
is sent as one *code* byte (block length + 1) followed by its non-zero bytes, and the
zero itself is implied. A run of 254 non-zero bytes is sent as code 0xFF and implies
no zero. The trailing implied zero of the last block is dropped::

    data     11 22 00 33          ->  encoded  03 11 22 02 33
    data     00                   ->  encoded  01 01
    data     (empty)              ->  encoded  01
    data     254 x non-zero       ->  encoded  FF <254 bytes>

The encoding is never longer than ``n + 1 + n // 254`` bytes and contains no 0x00,
so 0x00 can delimit frames on the wire (see :mod:`cdma_lidar.protocol.framing`).

:func:`encode` and :func:`decode` use the C extension of the ``cobs`` package (a base
dependency, about 2 us for a 4 KB frame); the tests hold it byte for byte to a pure-Python
reference (``tests/protocol/wire_oracle.py``).
"""

from __future__ import annotations

from cobs import cobs as _ccobs

from cdma_lidar.errors import FrameError

__all__ = ["decode", "encode", "max_encoded_len"]


def max_encoded_len(n: int) -> int:
    """Upper bound (bytes) of the COBS encoding of ``n`` data bytes, delimiters excluded."""
    return n + 1 + n // 254


#: COBS-encode bytes (the ``cobs`` package's C extension); byte-identical to the tests' reference.
encode = _ccobs.encode


def decode(enc: bytes) -> bytes:
    """COBS-decode ``enc`` (no delimiters); raises FrameError (only) if malformed."""
    if not enc:
        raise FrameError("COBS: empty input")
    try:
        return _ccobs.decode(enc)
    except _ccobs.DecodeError as exc:
        raise FrameError(f"COBS: {exc}") from None
