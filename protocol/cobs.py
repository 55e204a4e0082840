"""Consistent Overhead Byte Stuffing (COBS, Cheshire and Baker 1999): no 0x00 in a frame.

The data is cut at each zero byte into blocks, each sent as one *code* byte (block
length + 1) and its non-zero bytes, the zero implied; a run of 254 non-zero bytes is
code 0xFF and implies no zero; the last block's implied zero is dropped::

    data     11 22 00 33          ->  encoded  03 11 22 02 33
    data     00                   ->  encoded  01 01
    data     (empty)              ->  encoded  01
    data     254 x non-zero       ->  encoded  FF <254 bytes>

The encoding has no 0x00 (it delimits frames, :mod:`cdma_lidar.protocol.framing`). The
``cobs`` package's C extension does the work; the tests hold it byte for byte to a
pure-Python reference (``tests/protocol/wire_oracle.py``).
"""

from __future__ import annotations

from cobs import cobs as _ccobs

from cdma_lidar.errors import FrameError

__all__ = ["decode", "encode", "max_encoded_len"]

#: COBS-encode bytes (no delimiters).
encode = _ccobs.encode


def max_encoded_len(n: int) -> int:
    """Upper bound (bytes) of the COBS encoding of ``n`` data bytes, delimiters excluded."""
    return n + 1 + n // 254


def decode(enc: bytes) -> bytes:
    """COBS-decode ``enc`` (no delimiters); raises FrameError (only) if malformed."""
    if not enc:
        raise FrameError("COBS: empty input")
    try:
        return _ccobs.decode(enc)
    except _ccobs.DecodeError as exc:
        raise FrameError(f"COBS: {exc}") from None
