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
builds it. Encoding and syndromes are table-driven numpy (the code is linear over
GF(2^8); a test checks them against ``reedsolo``); locating and correcting the errors
of a damaged block is ``reedsolo``'s.
"""

from __future__ import annotations

import numpy as np
import reedsolo

from cdma_lidar.errors import FrameError

__all__ = ["BLOCK", "DATA", "NSYM", "body_len", "coded_len", "decode", "encode", "encode_reference",
           "strip", "whiten"]

#: Parity bytes per block: corrects 8 damaged bytes per block.
NSYM = 16
#: Bytes of a coded block (data + parity) and of its data.
BLOCK = 255
DATA = BLOCK - NSYM

_codec = reedsolo.RSCodec(NSYM, nsize=BLOCK)


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


def _gf_tables() -> tuple[np.ndarray, np.ndarray]:
    """(MUL, U): GF(2^8) products (reedsolo's tables, poly 0x11D) and the parity of each
    unit message.

    ``U[e]`` is the remainder of ``x^(NSYM + e)`` modulo the generator
    ``g(x) = prod_{i<16} (x - 2^i)``, highest degree first: the parity of a message whose
    only non-zero byte is a 1, ``e`` bytes before its end. The code is linear over
    GF(2^8), so a message's parity is the XOR of ``m_i * U[e_i]``.
    """
    exp = np.frombuffer(bytes(reedsolo.gf_exp[:255]), np.uint8).astype(np.int64)
    log_ = np.frombuffer(bytes(reedsolo.gf_log), np.uint8).astype(np.int64)
    mul = exp[(log_[:, None] + log_[None, :]) % 255].astype(np.uint8)
    mul[0, :] = mul[:, 0] = 0
    low = np.frombuffer(bytes(reedsolo.rs_generator_poly(NSYM)[1:]), np.uint8)  # g = x^16 + low
    u = np.zeros((DATA, NSYM), np.uint8)
    u[0] = low
    for e in range(1, DATA):  # x * U[e-1] mod g
        u[e] = np.append(u[e - 1, 1:], 0).astype(np.uint8) ^ mul[u[e - 1, 0], low]
    return mul, u


_MUL, _UNIT = _gf_tables()


def _powers() -> np.ndarray:
    """``[p, j] = (2^j)^(BLOCK - 1 - p)``: byte p of a block times it, XORed over p, is
    syndrome j (the block polynomial at the root 2^j)."""
    a = np.ones((BLOCK, NSYM), np.uint8)
    roots = np.ones(NSYM, np.uint8)
    for j in range(1, NSYM):
        roots[j] = _MUL[roots[j - 1], 2]
    for p in range(BLOCK - 2, -1, -1):
        a[p] = _MUL[a[p + 1], roots]
    return a


_POWERS = _powers()
#: Parity contribution rows by position in a full block (position 0 is e = DATA - 1).
_UNIT_BY_POS = _UNIT[::-1].copy()


def _blocks(data: np.ndarray, width: int) -> np.ndarray:
    """``data`` (uint8) cut into rows of ``width`` bytes, the last one right-aligned after
    zeros: leading zeros change neither a block's parity nor its syndromes."""
    nb = -(-data.size // width)
    rows = np.zeros((nb, width), np.uint8)
    full = (nb - 1) * width
    rows[:nb - 1] = data[:full].reshape(nb - 1, width)
    rows[nb - 1, width - (data.size - full):] = data[full:]
    return rows


def _data(plain: bytes) -> bytes:
    """The data bytes of unwhitened coded bytes (each block's parity dropped)."""
    return b"".join(plain[i:i + BLOCK][:-NSYM] for i in range(0, len(plain), BLOCK))


def encode(body: bytes) -> bytes:
    """``body`` with 16 parity bytes after every 239 data bytes (and after the rest),
    whitened. Table-driven (the code is linear): byte-identical to ``reedsolo``'s
    encoder, which a test checks."""
    if not body:
        return b""
    data = np.frombuffer(body, np.uint8)
    blocks = _blocks(data, DATA)
    parity = np.bitwise_xor.reduce(_MUL[blocks[:, :, None], _UNIT_BY_POS[None, :, :]], axis=1)
    full = (len(blocks) - 1) * DATA
    out = np.concatenate([np.hstack([blocks[:-1], parity[:-1]]).ravel(), data[full:],
                          parity[-1]])
    return whiten(out.tobytes())


def encode_reference(body: bytes) -> bytes:
    """:func:`encode` by ``reedsolo`` (the reference the fast encoder is tested against)."""
    return whiten(bytes(_codec.encode(body)))


def strip(coded: bytes) -> bytes:
    """The data bytes of ``coded`` as they arrived (no correction); b"" if no valid length."""
    return _data(whiten(coded)) if body_len(len(coded)) >= 0 else b""


def decode(coded: bytes) -> bytes:
    """Correct ``coded`` and return the body; FrameError (only) when it cannot.

    The syndromes of every block are computed at once (tables); a block whose
    syndromes show damage goes through ``reedsolo``'s Berlekamp-Massey, Chien search
    and Forney steps with those syndromes. A block with more than 8 damaged bytes
    fails there, or is miscorrected and then fails the frame's CRC."""
    if body_len(len(coded)) < 0:
        raise FrameError(f"fec: {len(coded)} bytes is no coded length")
    plain = np.frombuffer(whiten(coded), np.uint8).copy()
    if not plain.size:
        return b""
    # Syndrome j of a block: the block polynomial at the root 2^j (all zero: a codeword).
    syn = np.bitwise_xor.reduce(_MUL[_blocks(plain, BLOCK)[:, :, None], _POWERS[None, :, :]],
                                axis=1)
    for b in np.flatnonzero(syn.any(axis=1)):
        block = plain[b * BLOCK:(b + 1) * BLOCK]
        synd = [0, *syn[b].tolist()]  # reedsolo's layout
        try:
            loc = reedsolo.rs_find_error_locator(synd, NSYM)
            pos = reedsolo.rs_find_errors(loc[::-1], block.size, 2)
            fixed = reedsolo.rs_correct_errata(bytearray(block.tobytes()), synd, pos, 0, 2)
        except (reedsolo.ReedSolomonError, ValueError, IndexError, ZeroDivisionError) as exc:
            raise FrameError(f"fec: block {b}: {exc}") from None
        block[:] = np.frombuffer(bytes(fixed), np.uint8)
    return _data(plain.tobytes())
