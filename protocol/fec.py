"""Forward error correction around the COBS frame: Reed-Solomon RS(255, 207) over GF(2^8).

docs/protocol.md section 2.5 is the contract. A frame of a FEC session is sent as
``00 | rs(COBS(whiten(body))) | 00 00``; ``rs`` follows every 207 stuffed bytes (the last
block shorter) with the block's 48 parity bytes, highest degree first, spread 7 bits a byte
over 55 bytes ``0x80 | g`` that are never 0x00: ``[207 data | 55] ... [r data | 55]``, of
``n + 55 * ceil(n / 207)`` bytes for ``n`` stuffed bytes. Code: primitive polynomial 0x11D,
generator roots 2^0 .. 2^47, as ``reedsolo.RSCodec(48, nsize=255)`` builds it. Encoding,
syndromes, the Chien search and Forney's formula are table-driven numpy (tests hold them
to ``reedsolo``); the error locator is Berlekamp-Massey on log tables.
"""

from __future__ import annotations

import functools

import numpy as np
import reedsolo

from cdma_lidar.errors import FrameError

__all__ = ["BLOCK", "DATA", "NSYM", "SPREAD", "WIRE_BLOCK", "body_len", "coded_len", "decode",
           "encode", "plausible", "strip", "whiten"]

#: Parity bytes per block: corrects 24 damaged symbols per block.
NSYM = 48
#: Symbols of a code block (data + parity) and of its data.
BLOCK, DATA = 255, 255 - NSYM
#: Bytes that carry one block's parity on the wire (7 bits each, high bit set), and of a
#: full block on the wire.
SPREAD = -(-8 * NSYM // 7)
WIRE_BLOCK = DATA + SPREAD

# reedsolo's GF(2^8) tables for the polynomial 0x11D, read below at import: they are
# process-global, and any later init_tables (a RSCodec of other parameters) changes them.
reedsolo.init_tables(0x11D)


def coded_len(d: int) -> int:
    """Coded bytes of ``d`` stuffed (COBS) bytes."""
    return d + SPREAD * -(-d // DATA)


def body_len(t: int) -> int:
    """Stuffed bytes (at least 1) of ``t`` coded bytes; -1 when nothing codes to it."""
    blocks = -(-t // WIRE_BLOCK)
    d = t - SPREAD * blocks
    return d if d > max(0, DATA * (blocks - 1)) else -1


#: Whitening: body byte i is XORed with ``(WHITE_START + WHITE_STEP * i) mod 256``.
WHITE_START, WHITE_STEP = 0x5A, 0x97


def whiten(data: bytes) -> bytes:
    """``data`` XOR the whitening sequence (its own inverse): zero-rich column records come
    out with few bytes one bit error away from 0x00 (which would split the frame)."""
    white = (WHITE_START + WHITE_STEP * np.arange(len(data))).astype(np.uint8)  # mod 256
    return (np.frombuffer(data, np.uint8) ^ white).tobytes()


_EXP = np.array(reedsolo.gf_exp[:255], np.uint8)  # 2^i, poly 0x11D
_LOG = np.array(reedsolo.gf_log[:256], np.int16)  # narrow: the Chien search holds
# (blocks, 25, 255) of them (7 MB, not 27, for 64 kB with every block damaged)
_EXP_LIST, _LOG_LIST = _EXP.tolist(), _LOG.tolist()
#: GF(2^8) products: ``_MUL[a, b] = a * b`` (``_GMUL[a][b]`` as lists, for scalars).
_MUL = _EXP[(_LOG[:, None] + _LOG[None, :]) % 255]
_MUL[0, :] = _MUL[:, 0] = 0
_GMUL = _MUL.tolist()
_LOW = np.frombuffer(bytes(reedsolo.rs_generator_poly(NSYM)[1:]), np.uint8)  # g = x^48 + low


@functools.cache
def _by_byte() -> tuple[np.ndarray, np.ndarray]:
    """Syndrome and parity rows of each byte position ``p`` of a block times every byte
    value, ``[p, v] = v * row p`` (3.1 and 2.5 MB, built at first use): a block's syndromes
    or parity are the XOR of one row per byte (a tenth of the time of gathering products).
    Syndrome row p: ``(2^j)^(BLOCK - 1 - p)``, j < 48; parity row p (of a data byte):
    ``x^(BLOCK - 1 - p) mod g(x)``, ``g = prod_{i<48} (x - 2^i)``, highest degree first."""
    powers = _EXP[(np.arange(NSYM) * (BLOCK - 1 - np.arange(BLOCK))[:, None]) % 255]
    unit = np.zeros((DATA, NSYM), np.uint8)
    unit[-1] = _LOW  # x^48 mod g
    for p in range(DATA - 2, -1, -1):  # x times row p+1, mod g
        unit[p] = np.append(unit[p + 1, 1:], 0).astype(np.uint8) ^ _MUL[unit[p + 1, 0], _LOW]
    v = np.arange(256)[None, :, None]
    return _MUL[v, powers[:, None, :]], _MUL[v, unit[:, None, :]]


def _blocks(data: bytes, width: int) -> tuple[np.ndarray, int]:
    """(``data`` cut into rows of ``width`` bytes, ``pad``): the last row is right-aligned
    after ``pad`` zeros, which change neither a block's parity nor its syndromes."""
    nb = -(-len(data) // width)
    pad, cut = nb * width - len(data), (nb - 1) * width
    return np.frombuffer(data[:cut] + bytes(pad) + data[cut:], np.uint8).reshape(nb, width), pad


def _unblock(rows: np.ndarray, pad: int) -> bytes:
    """The bytes of ``rows`` without the ``pad`` zeros :func:`_blocks` put before the last."""
    return rows[:-1].tobytes() + rows[-1, pad:].tobytes()


def _spread(parity: np.ndarray) -> np.ndarray:
    """(blocks, NSYM) parity bytes -> (blocks, SPREAD) bytes ``0x80 | 7 bits``."""
    bits = np.unpackbits(parity, axis=1)
    bits = np.pad(bits, ((0, 0), (0, 7 * SPREAD - bits.shape[1])))
    groups = np.packbits(bits.reshape(len(parity), SPREAD, 7), axis=2)[:, :, 0] >> 1
    return groups | np.uint8(0x80)


def _unspread(spread: np.ndarray) -> np.ndarray:
    """(blocks, SPREAD) wire bytes -> (blocks, NSYM) parity bytes (high bits ignored)."""
    bits = np.unpackbits((spread << 1)[:, :, None], axis=2)[:, :, :7]
    return np.packbits(bits.reshape(len(spread), 7 * SPREAD)[:, :8 * NSYM], axis=1)


def _cut(coded: bytes) -> tuple[np.ndarray, np.ndarray, int]:
    """(data, spread parity, pad) of coded bytes, one block a row: (blocks, DATA) data
    bytes, the last block's right-aligned after ``pad`` zeros, and (blocks, SPREAD) spread
    parity; FrameError when nothing codes to their length."""
    if body_len(len(coded)) < 0:
        raise FrameError(f"fec: {len(coded)} bytes is no coded length")
    rows, pad = _blocks(coded, WIRE_BLOCK)
    return rows[:, :DATA], rows[:, DATA:], pad


def encode(stuffed: bytes) -> bytes:
    """``stuffed`` (COBS bytes) with 55 spread parity bytes after every 207 (and after the
    rest); no byte is 0x00 when ``stuffed`` has none. Byte-identical to ``reedsolo``."""
    if not stuffed:
        return b""
    blocks, pad = _blocks(stuffed, DATA)
    parity = np.bitwise_xor.reduce(_by_byte()[1][np.arange(DATA), blocks], axis=1)
    return _unblock(np.hstack([blocks, _spread(parity)]), pad)


def plausible(coded: bytes) -> bool:
    """``coded`` has a coded length and every block's spread parity has at most 4 bytes
    without their high bit: the bytes are where a coded frame puts them (a piece of a
    frame, or one a byte longer or shorter, fails this at once, without decoding)."""
    return body_len(len(coded)) > 0 and bool(((_cut(coded)[1] < 0x80).sum(axis=1) <= 4).all())


def strip(coded: bytes) -> bytes:
    """The data bytes of ``coded`` as they arrived (no correction); FrameError as _cut."""
    data, _, pad = _cut(coded)
    return _unblock(data, pad)


def _locator(syn: list[int]) -> list[int]:
    """The error locator Lambda (highest degree first, no leading zero) of syndromes
    ``S_0 .. S_47``: Berlekamp-Massey in tables, a third of the cost of ``reedsolo``'s
    ``rs_find_error_locator`` (a test holds the two equal). ReedSolomonError above 24."""
    c, b, big_l, m, last = [1], [1], 0, 1, 1  # Lambda, previous Lambda, L, shift, its d
    for n, d in enumerate(syn):
        for i in range(1, min(big_l, len(c) - 1) + 1):
            d ^= _GMUL[c[i]][syn[n - i]]
        if d:
            q = _EXP_LIST[(_LOG_LIST[d] - _LOG_LIST[last]) % 255]  # d / last
            new = c + [0] * max(0, len(b) + m - len(c))
            for i, bi in enumerate(b):
                new[i + m] ^= _GMUL[bi][q]
            if 2 * big_l <= n:
                big_l, b, last, m = n + 1 - big_l, c, d, 0
            c = new
        m += 1
    loc = c[:big_l + 1][::-1]
    while loc and loc[0] == 0:
        loc = loc[1:]
    if len(loc) - 1 > NSYM // 2:
        raise reedsolo.ReedSolomonError("Too many errors to correct")
    return loc


def _correct(rows: np.ndarray, bad: list[int], syn: np.ndarray, last: int) -> None:
    """Correct the blocks ``bad`` of ``rows`` (one block a row, the last one ``last``
    symbols long, right-aligned after zeros) in place from their syndromes ``syn``: the
    roots of every locator at once (Chien search in tables: Lambda(2^-e) for every e),
    the error values by Forney (first consecutive root 1: ``Y = X Omega(1/X) /
    Lambda'(1/X)``). ReedSolomonError naming a block with more than 24 damaged symbols
    (roots not as many as its locator's degree)."""
    lams = [_locator(syn[b].tolist())[::-1] for b in bad]  # Lambda, lowest degree first
    width = max(map(len, lams))
    lam = np.array([coef + [0] * (width - len(coef)) for coef in lams], np.uint8)
    powers = (np.arange(width)[:, None] * np.arange(BLOCK)).astype(np.int16)  # i * e
    terms = np.where(lam[:, :, None] > 0, _EXP[(_LOG[lam][:, :, None] - powers) % 255], 0)
    found = np.bitwise_xor.reduce(terms, axis=1) == 0
    for k, b in enumerate(bad):
        s_b, coef, deg = syn[b].tolist(), lams[k], len(lams[k]) - 1
        roots = np.flatnonzero(found[k, :last if b == len(rows) - 1 else BLOCK]).tolist()
        if deg == 0 or len(roots) != deg:
            raise reedsolo.ReedSolomonError(f"block {b}: {len(roots)} error positions for a "
                                            f"locator of degree {deg}")
        omega = [0] * deg  # S(x) Lambda(x) mod x^deg, lowest degree first
        for i in range(deg):
            for j in range(i + 1):
                omega[i] ^= _GMUL[s_b[i - j]][coef[j]]
        for r in roots:
            xinv = _EXP_LIST[(255 - r) % 255]  # 1/X, X = 2^r
            num = den = 0
            for c in reversed(omega):  # Horner: Omega(1/X)
                num = _GMUL[num][xinv] ^ c
            for c in reversed(coef[1::2]):  # Lambda'(1/X): the odd terms, one degree down
                den = _GMUL[den][_GMUL[xinv][xinv]] ^ c
            if den == 0:
                raise reedsolo.ReedSolomonError(f"block {b}: Forney: zero derivative")
            y = _GMUL[_EXP_LIST[r]][_GMUL[num][_EXP_LIST[(255 - _LOG_LIST[den]) % 255]]]
            rows[b, BLOCK - 1 - r] ^= y


def decode(coded: bytes) -> bytes:
    """Correct ``coded`` and return the stuffed (COBS) bytes; FrameError (only) when it
    cannot. A block with more than 24 damaged symbols fails in :func:`_correct`, or is
    miscorrected and then fails the frame's CRC."""
    data, spread, pad = _cut(coded)
    rows = np.hstack([data, _unspread(spread)])
    # Syndrome j of a block: the block polynomial at the root 2^j (all zero: a codeword).
    syn = np.bitwise_xor.reduce(_by_byte()[0][np.arange(BLOCK), rows], axis=1)
    if (bad := np.flatnonzero(syn.any(axis=1)).tolist()):
        try:
            _correct(rows, bad, syn, BLOCK - pad)
        except (reedsolo.ReedSolomonError, ValueError, IndexError, ZeroDivisionError) as exc:
            raise FrameError(f"fec: {exc}") from None
    return _unblock(rows[:, :DATA], pad)
