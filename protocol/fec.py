"""Forward error correction inside the COBS frame: Reed-Solomon RS(255, 239) over GF(2^8).

A frame of a session that negotiated FEC (HELLO flag FEC, docs/protocol.md) is
sent as ``00 | COBS(rs(body)) | 00`` where ``body`` is the plain frame (header,
payload, signature, CRC-32) and ``rs`` cuts it into blocks of 239 bytes (the last
one shorter) and appends 16 parity bytes to each::

    body     b0 ........ b238 | b239 ...... b477 | b478 .. b(d-1)
    coded    [239 data | 16 parity] [239 data | 16 parity] [r data | 16 parity]

The coded bytes are then whitened (:func:`whiten`) before COBS. A block corrects any
8 damaged bytes (a bit error rate of 1e-3 damages about 2 of
255). The code is systematic: a receiver first checks the CRC-32 of the data bytes
alone and decodes only when it fails, so an undamaged frame costs one CRC. The coded
length ``t`` gives the body length ``d`` back: ``t = d + 16 * ceil(d / 239)``.

Code: narrow-sense RS over GF(2^8) with primitive polynomial 0x11D, generator
roots alpha^0 .. alpha^15 (alpha = 2), as ``reedsolo.RSCodec(16, nsize=255)``
builds it (its C extension ``creedsolo`` when installed, same code).
"""

from __future__ import annotations

import logging

import numpy as np

from cdma_lidar.errors import FrameError

__all__ = ["BLOCK", "DATA", "NSYM", "body_len", "coded_len", "decode", "encode", "strip"]

log = logging.getLogger(__name__)

#: Parity bytes per block: corrects 8 damaged bytes per block.
NSYM = 16
#: Bytes of a coded block (data + parity) and of its data.
BLOCK = 255
DATA = BLOCK - NSYM

try:  # pragma: no cover - depends on the installed package
    from creedsolo import ReedSolomonError, RSCodec  # type: ignore[import-not-found]
except ImportError:
    try:
        from reedsolo import ReedSolomonError, RSCodec
    except ImportError:  # pragma: no cover
        RSCodec = None  # type: ignore[assignment,misc]
        ReedSolomonError = Exception  # type: ignore[assignment,misc]

_codec = RSCodec(NSYM, nsize=BLOCK) if RSCodec is not None else None


def _need() -> object:
    if _codec is None:
        raise ImportError("forward error correction needs the reedsolo package: "
                          "pip install reedsolo (or install cdma-lidar with its base "
                          "dependencies)")
    return _codec


def coded_len(d: int) -> int:
    """Coded bytes of a body of ``d`` bytes."""
    return d + NSYM * -(-d // DATA)


def body_len(t: int) -> int:
    """Body bytes of ``t`` coded bytes; -1 when no body codes to that length."""
    blocks = -(-t // BLOCK)
    d = t - NSYM * blocks
    return d if d > DATA * (blocks - 1) else -1


#: Whitening: coded byte i is XORed with ``(WHITE_START + WHITE_STEP * i) mod 256``, so
#: the zero-rich column records give COBS few zero bytes: each is a code byte, which a
#: bit error would make misread the rest of the frame (no code can repair that).
WHITE_START, WHITE_STEP = 0x5A, 0x97
_WHITE = ((WHITE_START + WHITE_STEP * np.arange(1 << 17)) & 0xFF).astype(np.uint8)


def whiten(data: bytes) -> bytes:
    """``data`` XOR the whitening sequence (its own inverse)."""
    if len(data) > _WHITE.size:
        raise FrameError(f"fec: {len(data)} bytes is longer than any frame")
    return (np.frombuffer(data, np.uint8) ^ _WHITE[:len(data)]).tobytes()


def encode(body: bytes) -> bytes:
    """``body`` with 16 parity bytes after every 239 data bytes (and after the rest),
    whitened."""
    return whiten(bytes(_need().encode(body)))  # type: ignore[attr-defined]


def strip(coded: bytes) -> bytes:
    """The data bytes of ``coded`` as they arrived (no correction); b"" if no valid length."""
    if body_len(len(coded)) < 0:
        return b""
    plain = whiten(coded)
    return b"".join(plain[i:i + BLOCK][:-NSYM] for i in range(0, len(plain), BLOCK))


def decode(coded: bytes) -> bytes:
    """Correct ``coded`` and return the body; FrameError (only) when it cannot."""
    if body_len(len(coded)) < 0:
        raise FrameError(f"fec: {len(coded)} bytes is no coded length")
    try:
        return bytes(_need().decode(whiten(coded))[0])  # type: ignore[attr-defined]
    except ReedSolomonError as exc:
        raise FrameError(f"fec: {exc}") from None
