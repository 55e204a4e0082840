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
dependency, about 2 us for a 4 KB frame); the pure-Python reference :func:`encode_py` /
:func:`decode_py` is tested against it byte for byte.
"""

from __future__ import annotations

from cobs import cobs as _ccobs

from cdma_lidar.errors import FrameError

__all__ = ["decode", "decode_py", "encode", "encode_py", "max_encoded_len"]


def max_encoded_len(n: int) -> int:
    """Upper bound (bytes) of the COBS encoding of ``n`` data bytes, delimiters excluded."""
    return n + 1 + n // 254


def encode_py(data: bytes) -> bytes:
    """COBS-encode ``data`` (reference implementation; output has no 0x00 byte)."""
    out = bytearray()
    segments = bytes(data).split(b"\x00")
    last = len(segments) - 1
    for k, seg in enumerate(segments):
        # Full 254-byte blocks first: code 0xFF, no implied zero.
        full = len(seg) // 254
        for b in range(full):
            out.append(0xFF)
            out += seg[254 * b:254 * (b + 1)]
        rest = seg[254 * full:]
        # The remainder block (code len+1) implies the zero that ended the segment. The
        # last segment has no such zero, so after full blocks it needs no block at all.
        if k < last or not (full and not rest):
            out.append(len(rest) + 1)
            out += rest
    return bytes(out)


def decode_py(enc: bytes) -> bytes:
    """Decode one COBS block sequence (no delimiters); raises FrameError if malformed."""
    enc = bytes(enc)
    out = bytearray()
    i, n = 0, len(enc)
    if n == 0:
        raise FrameError("COBS: empty input")
    while i < n:
        code = enc[i]
        if code == 0:
            raise FrameError(f"COBS: zero byte at offset {i}")
        end = i + code
        if end > n:
            raise FrameError(f"COBS: block at offset {i} runs past the end")
        block = enc[i + 1:end]
        if 0 in block:
            raise FrameError(f"COBS: zero byte inside block at offset {i}")
        out += block
        i = end
        if code != 0xFF and i < n:
            out.append(0)
    return bytes(out)


#: COBS-encode bytes (the ``cobs`` package's C extension); byte-identical to :func:`encode_py`.
encode = _ccobs.encode


def decode(enc: bytes) -> bytes:
    """COBS-decode ``enc`` (no delimiters); raises FrameError (only) if malformed."""
    if not enc:
        raise FrameError("COBS: empty input")
    try:
        return _ccobs.decode(enc)
    except _ccobs.DecodeError as exc:
        raise FrameError(f"COBS: {exc}") from None
