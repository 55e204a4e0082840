"""COBS, CRC and the frame decoder: round trips, and no exception or bad frame from bad bytes."""

from __future__ import annotations

import random

import pytest
import wire_oracle
from hypothesis import given
from hypothesis import strategies as st

from cdma_lidar.errors import FieldError, FrameError
from cdma_lidar.protocol import framing
from cdma_lidar.protocol.framing import Frame, FrameDecoder, crc32, encode_frame

frames_st = st.builds(
    Frame,
    msg_type=st.integers(0, 255),
    seq=st.integers(0, 0xFFFF),
    session=st.integers(0, 0xFFFFFFFF),
    payload=st.binary(max_size=700),
    compat=st.integers(0, 255),
    incompat=st.just(0),
    version=st.just(framing.PROTOCOL_VERSION),
    sig=st.just(b""),
    fec=st.just(False),
    joined=st.just(False),
)


def wire(f: Frame) -> bytes:
    return encode_frame(f.msg_type, f.payload, f.seq, f.session, compat=f.compat)


# ---- COBS ---------------------------------------------------------------------------------------
@pytest.mark.parametrize("n", [0, 1, 253, 254, 255, 507, 508, 509, 1000])
@pytest.mark.parametrize("fill", [0x00, 0x01, 0xFF])
def test_cobs_edge_lengths(n: int, fill: int) -> None:
    data = bytes([fill]) * n
    enc = wire_oracle.cobs_encode_py(data)
    assert 0 not in enc
    assert len(enc) <= framing.cobs_max_len(n)
    assert enc == framing.cobs_encode(data)
    assert wire_oracle.cobs_decode_py(enc) == data == framing.cobs_decode(enc)


@given(st.binary(max_size=2000))
def test_cobs_reference_equals_fast_and_round_trips(data: bytes) -> None:
    enc = wire_oracle.cobs_encode_py(data)
    assert enc == framing.cobs_encode(data)
    assert 0 not in enc
    assert wire_oracle.cobs_decode_py(enc) == data
    assert framing.cobs_decode(enc) == data


def test_cobs_known_vectors() -> None:
    assert wire_oracle.cobs_encode_py(b"") == b"\x01"
    assert wire_oracle.cobs_encode_py(b"\x00") == b"\x01\x01"
    assert wire_oracle.cobs_encode_py(b"\x11\x22\x00\x33") == b"\x03\x11\x22\x02\x33"
    assert wire_oracle.cobs_encode_py(bytes(range(1, 255))) == b"\xff" + bytes(range(1, 255))


@pytest.mark.parametrize("bad", [b"", b"\x00", b"\x05\x01\x02", b"\x03\x01\x00"])
def test_cobs_decode_rejects_malformed(bad: bytes) -> None:
    with pytest.raises(FrameError):
        wire_oracle.cobs_decode_py(bad)
    with pytest.raises(FrameError):
        framing.cobs_decode(bad)


def test_crc_check_value() -> None:
    assert crc32(b"123456789") == 0xCBF43926


# ---- frames ------------------------------------------------------------------------------------
@given(frames_st)
def test_frame_round_trip(f: Frame) -> None:
    w = wire(f)
    assert w[0] == 0 and w[-1] == 0 and 0 not in w[1:-1]
    dec = FrameDecoder()
    assert dec.feed(w) == [f]
    assert dec.stats.frames == 1 and dec.stats.errors == 0


@pytest.mark.parametrize(("kw", "name"), [
    ({"msg_type": 256}, "frame.msg_type"), ({"seq": -1}, "frame.seq"),
    ({"session": 2**32}, "frame.session"), ({"compat": 300}, "frame.compat"),
])
def test_encode_frame_names_bad_header_field(kw: dict, name: str) -> None:
    args = {"msg_type": 1, "seq": 0, "session": 1} | kw
    with pytest.raises(FieldError, match=name) as exc:
        encode_frame(args["msg_type"], b"", args["seq"], args["session"],
                     compat=kw.get("compat", 0))
    assert exc.value.field == name


def test_encode_frame_refuses_payload_over_max_frame() -> None:
    encode_frame(1, bytes(512 - framing.OVERHEAD), 0, 1, max_frame=512)
    with pytest.raises(FieldError, match="payload"):
        encode_frame(1, bytes(512 - framing.OVERHEAD + 1), 0, 1, max_frame=512)


@given(st.lists(frames_st, max_size=6), st.lists(st.integers(0, 10_000), max_size=8))
def test_decoder_chunked_equals_whole(frames: list[Frame], cuts: list[int]) -> None:
    stream = b"".join(wire(f) for f in frames)
    points = sorted({min(c, len(stream)) for c in cuts})
    dec = FrameDecoder()
    got = []
    prev = 0
    for p in [*points, len(stream)]:
        got += dec.feed(stream[prev:p])
        prev = p
    assert got == frames
    assert dec.buffered == 0


@given(st.binary(max_size=3000))
def test_decoder_never_raises_on_garbage(data: bytes) -> None:
    dec = FrameDecoder()
    for f in dec.feed(data):
        # Whatever random bytes pass must be internally consistent frames.
        assert isinstance(f, Frame)
    assert dec.stats.bytes == len(data)


def _mutate(w: bytes, rng: random.Random, how: str) -> bytes:
    b = bytearray(w[1:-1])
    if how == "flip":
        for _ in range(rng.randint(1, 4)):
            pos = rng.randrange(len(b))
            b[pos] ^= 1 << rng.randrange(8)
    elif how == "truncate":
        del b[rng.randrange(len(b)):]
    elif how == "insert":
        b.insert(rng.randrange(len(b) + 1), rng.randrange(1, 256))
    elif how == "delete":
        del b[rng.randrange(len(b))]
    elif how == "swap" and len(b) > 1:
        i = rng.randrange(len(b) - 1)
        b[i], b[i + 1] = b[i + 1], b[i]
    return b"\x00" + bytes(b) + b"\x00"


@given(frames_st, frames_st, st.binary(max_size=300), st.integers(0, 2**32 - 1),
       st.sampled_from(["flip", "truncate", "insert", "delete", "swap"]))
def test_corrupted_frame_never_accepted_and_decoder_resyncs(
        victim: Frame, good: Frame, garbage: bytes, seed: int, how: str) -> None:
    bad = _mutate(wire(victim), random.Random(seed), how)
    dec = FrameDecoder()
    got = dec.feed(garbage + bad + wire(good))
    # Resync: the frame after the damage always comes through.
    assert got[-1] == good
    # Nothing else is accepted, unless the "mutation" left the bytes unchanged.
    assert got[:-1] == ([victim] if bad == wire(victim) else [])
    if bad != wire(victim):
        assert dec.stats.errors >= 1


def test_decoder_counts_each_error_kind() -> None:
    dec = FrameDecoder(max_frame=512)
    good = encode_frame(0x80, b"\x05", 7, 9)
    body = framing.cobs_decode(good[1:-1])
    bad_crc = bytearray(body)
    bad_crc[-1] ^= 0xFF
    bad_len = framing.HEADER.pack(1, 0, 0, 0x80, 7, 5, 9) + b"\x05"
    bad_len += crc32(bad_len).to_bytes(4, "little")
    v2 = framing.HEADER.pack(framing.PROTOCOL_VERSION + 1, 0, 0, 0x01, 7, 0, 9)
    v2 += crc32(v2).to_bytes(4, "little")
    inc = framing.HEADER.pack(framing.PROTOCOL_VERSION, 0x02, 0, 0x01, 8, 0, 9)
    inc += crc32(inc).to_bytes(4, "little")
    stream = b"".join([
        b"\x00\x00\x00",                                   # empty chunks: ignored
        b"\x00\x05\x01\x00",                               # COBS overrun
        b"\x00" + framing.cobs_encode(b"\x01\x02\x03") + b"\x00",  # short
        b"\x00" + framing.cobs_encode(bytes(bad_crc)) + b"\x00",   # CRC
        b"\x00" + framing.cobs_encode(bad_len) + b"\x00",          # length
        b"\x00" + bytes([7]) * 2000 + b"\x00",             # oversize
        b"\x00" + framing.cobs_encode(v2) + b"\x00",               # version
        b"\x00" + framing.cobs_encode(inc) + b"\x00",              # incompat
        good,
    ])
    got = dec.feed(stream)
    assert got == [Frame(0x80, 7, 9, b"\x05")]
    s = dec.stats
    assert (s.cobs, s.short, s.crc, s.length, s.oversize, s.version, s.incompat) == \
        (1, 1, 1, 1, 1, 1, 1)
    v = framing.PROTOCOL_VERSION
    assert [(f.version, f.incompat, f.seq) for f in dec.rejected] == [(v + 1, 0, 7), (v, 2, 8)]


def test_decoder_bounds_memory_on_endless_garbage() -> None:
    dec = FrameDecoder(max_frame=1024)
    for _ in range(50):
        dec.feed(b"\x55" * 997)
        assert dec.buffered <= framing.cobs_max_len(1024)
    assert dec.stats.oversize == 1  # one endless chunk counts once
    good = encode_frame(0xC1, b"abc", 1, 2)
    assert dec.feed(good) == [Frame(0xC1, 1, 2, b"abc")]


def test_decoder_max_frame_is_checked() -> None:
    with pytest.raises(ValueError, match="max_frame"):
        FrameDecoder(max_frame=100)
