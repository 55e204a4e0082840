"""Reed-Solomon FEC inside the COBS frame, reproducible line noise, and the 1e-3 target."""

from __future__ import annotations

import numpy as np
import pytest
import reedsolo
from hypothesis import given, settings
from hypothesis import strategies as st

from cdma_lidar.errors import FrameError
from cdma_lidar.protocol import fec
from cdma_lidar.protocol.framing import FrameDecoder, encode_frame
from cdma_lidar.virtual.line import LineNoise

stuffed = st.binary(min_size=1, max_size=2000).map(lambda b: b.replace(b"\x00", b"\x07"))


@given(stuffed)
def test_coded_bytes_round_trip_hold_no_zero_and_their_length_gives_the_stuffed_length(
        data: bytes) -> None:
    coded = fec.encode(data)
    assert len(coded) == fec.coded_len(len(data)) and 0 not in coded
    assert fec.body_len(len(coded)) == len(data)
    assert fec.plausible(coded)
    assert fec.strip(coded) == data == fec.decode(coded)


def _encode_reference(stuffed: bytes) -> bytes:
    """fec.encode with reedsolo's encoder (the reference it is tested against)."""
    codec = reedsolo.RSCodec(fec.NSYM, nsize=fec.BLOCK)
    out = []
    for i in range(0, len(stuffed), fec.DATA):
        block = bytes(codec.encode(stuffed[i:i + fec.DATA]))
        parity = np.frombuffer(block[-fec.NSYM:], np.uint8)[None, :]
        out.append(block[:-fec.NSYM] + fec._spread(parity).tobytes())
    return b"".join(out)


@given(stuffed)
def test_table_driven_encoder_equals_reedsolo(data: bytes) -> None:
    assert fec.encode(data) == _encode_reference(data)


def test_the_code_does_not_follow_reedsolos_tables_after_import() -> None:
    """reedsolo's GF tables are process-global: an init_tables of another polynomial
    after import (the lazily built encoder tables included) does not change the code."""
    want = fec.encode(bytes(range(1, 256)) * 2)
    fec._by_byte.cache_clear()
    reedsolo.init_tables(0x187)
    try:
        assert fec.encode(bytes(range(1, 256)) * 2) == want
    finally:
        reedsolo.init_tables(0x11D)
        fec._by_byte.cache_clear()


@settings(max_examples=300)
@given(st.lists(st.tuples(st.integers(0, fec.BLOCK - 1), st.integers(1, 255)), max_size=30,
                unique_by=lambda e: e[0]))
def test_the_error_locator_is_reedsolos(errors: list[tuple[int, int]]) -> None:
    """The table-driven Berlekamp-Massey gives reedsolo's locator for any error pattern
    (value Y at exponent e: S_j = sum Y 2^(e j)), and refuses the same ones (> 24)."""
    syn = [0] * fec.NSYM
    for e, y in errors:
        for j in range(fec.NSYM):
            syn[j] ^= reedsolo.gf_mul(y, reedsolo.gf_pow(2, e * j % 255))

    def locator(find):  # the locator, or the error it raised
        try:
            return find()
        except reedsolo.ReedSolomonError as exc:
            return type(exc)
    assert locator(lambda: fec._locator(syn)) == \
        locator(lambda: reedsolo.rs_find_error_locator([0, *syn], fec.NSYM))


@settings(max_examples=50)
@given(st.binary(min_size=1, max_size=1200), st.integers(0, 2**32 - 1))
def test_twelve_damaged_bytes_per_block_are_corrected(data: bytes, seed: int) -> None:
    """Twelve damaged wire bytes per block (a spread byte damages up to two parity
    symbols: at most 24, as many as a block corrects)."""
    data = data.replace(b"\x00", b"\x01")
    coded = bytearray(fec.encode(data))
    rng = np.random.default_rng(seed)
    for start in range(0, len(coded), fec.WIRE_BLOCK):
        block = min(fec.WIRE_BLOCK, len(coded) - start)
        for i in rng.choice(block, size=min(12, block), replace=False):
            coded[start + int(i)] ^= int(rng.integers(1, 256))
    assert fec.decode(bytes(coded)) == data


def _decode_reference(coded: bytes) -> bytes | None:
    """fec.decode with reedsolo's decoder, block by block; None where it cannot."""
    codec = reedsolo.RSCodec(fec.NSYM, nsize=fec.BLOCK)
    data, spread, pad = fec._cut(coded)
    data = [*data[:-1], data[-1, pad:]]  # the last block without the zeros before it
    try:
        return b"".join(bytes(codec.decode(d.tobytes() + p.tobytes())[0])
                        for d, p in zip(data, fec._unspread(spread), strict=True))
    except reedsolo.ReedSolomonError:
        return None


@settings(max_examples=120)
@given(st.sampled_from([1, 30, fec.DATA - 1, fec.DATA, fec.DATA + 1, 2 * fec.DATA + 150]),
       st.sampled_from([0, 1, 24, 25, 26, 40, fec.WIRE_BLOCK]), st.booleans(),
       st.integers(0, 2**32 - 1))
def test_damage_at_the_edges_is_decoded_as_reedsolo_decodes_it(
        n: int, errors: int, last: bool, seed: int) -> None:
    """0, 1, 24 (as many as a block corrects), 25, 26, 40 damaged wire bytes or all of
    one block (the last, often short, or the first; the other end block gets 5): the
    table-driven decoder corrects exactly what reedsolo's decoder corrects and fails
    (FrameError) where it fails."""
    rng = np.random.default_rng(seed)
    data = bytes(rng.integers(1, 256, n, dtype=np.uint8))
    coded = bytearray(fec.encode(data))
    end = (len(coded) - 1) // fec.WIRE_BLOCK * fec.WIRE_BLOCK  # the last block's start
    for start, k in ((end, errors), (0, 5)) if last else ((0, errors), (end, 5)):
        block = min(fec.WIRE_BLOCK, len(coded) - start)
        for i in rng.choice(block, size=min(k, block), replace=False):
            coded[start + int(i)] ^= int(rng.integers(1, 128))  # a spread byte keeps bit 7
        if not end:
            break  # one block
    want = _decode_reference(bytes(coded))
    try:
        got = fec.decode(bytes(coded))
    except FrameError:
        got = None
    assert got == want
    if errors <= 7:  # a damaged spread byte damages at most two parity symbols
        assert got == data


def test_a_short_block_is_not_corrected_at_positions_it_does_not_have() -> None:
    """A 78-symbol block (30 data bytes) with 25 errors whose syndromes are those of 24
    errors, one at a position (degree 83) only a full block has: the decoder refuses it,
    as reedsolo does, instead of "correcting" 23 symbols and returning wrong bytes. The
    25 errors are 25 of the 49 symbols of a weight-49 codeword (solved over GF(2^8))
    whose 49th symbol sits at degree 83."""
    gmul, gpow = reedsolo.gf_mul, reedsolo.gf_pow
    rng = np.random.default_rng(5)
    data = bytes(rng.integers(1, 256, 30, dtype=np.uint8))
    n, pad = 30 + fec.NSYM, 30 + fec.NSYM + 5  # the block's symbols; the degree beyond it
    (d,), spread, pad = fec._cut(fec.encode(data))
    sym = list(d[pad:].tobytes() + fec._unspread(spread)[0].tobytes())  # degrees n-1 .. 0
    degrees = [int(e) for e in rng.choice(n, fec.NSYM, replace=False)]
    # Solve sum_e c_e 2^(j e) = 2^(j pad), j < 48: c plus 1 at degree pad is a codeword.
    a = [[gpow(2, j * e % 255) for e in degrees] + [gpow(2, j * pad % 255)]
         for j in range(fec.NSYM)]
    for col in range(fec.NSYM):  # Gauss-Jordan over GF(2^8)
        piv = next(r for r in range(col, fec.NSYM) if a[r][col])
        a[col], a[piv] = a[piv], a[col]
        inv = reedsolo.gf_inverse(a[col][col])
        a[col] = [gmul(v, inv) for v in a[col]]
        for r in range(fec.NSYM):
            if r != col and a[r][col]:
                f = a[r][col]
                a[r] = [v ^ gmul(f, w) for v, w in zip(a[r], a[col], strict=True)]
    for e, row in list(zip(degrees, a, strict=True))[:25]:
        sym[n - 1 - e] ^= row[-1]
    parity = np.frombuffer(bytes(sym[-fec.NSYM:]), np.uint8)[None, :]
    coded = bytes(sym[:-fec.NSYM]) + fec._spread(parity).tobytes()
    assert _decode_reference(coded) is None
    with pytest.raises(FrameError, match="23 error positions for a locator of degree 24"):
        fec.decode(coded)


def test_a_piece_of_a_coded_frame_is_not_plausible() -> None:
    coded = fec.encode(fec.whiten(bytes(1020)).replace(b"\x00", b"\x01"))
    assert fec.plausible(coded)
    assert not fec.plausible(coded[:600]) and not fec.plausible(coded[100:])


def test_whitening_leaves_few_zero_bytes_for_cobs() -> None:
    """A zero-rich body (column records) whitens to about one zero in 256: few bytes of
    the coded frame are one bit error away from 0x00."""
    assert fec.whiten(bytes(4000)).count(0) < 4000 / 100


@given(st.binary(max_size=600), st.booleans())
def test_a_decoder_with_fec_reads_coded_and_plain_frames(payload: bytes, coded: bool) -> None:
    wire = encode_frame(0x81, payload, 7, 9, coded=coded)
    (frame,) = FrameDecoder(fec=True).feed(wire)
    assert (frame.payload, frame.fec) == (payload, coded)
    assert FrameDecoder().feed(wire) == ([] if coded else [frame._replace(fec=False)])


@pytest.mark.parametrize("zeros", [(300,), (40, 300, 700, 1100)])
def test_bytes_damaged_into_delimiters_are_rejoined(zeros: tuple[int, ...]) -> None:
    payload = bytes(range(1, 200)) * 6
    wire = bytearray(encode_frame(0x81, payload, 7, 9, coded=True))
    for at in zeros:
        wire[at] = 0  # the line turned a byte into 0x00: the frame arrives in pieces
    dec = FrameDecoder(fec=True)
    (frame,) = dec.feed(bytes(wire))
    assert frame.payload == payload and dec.stats.rejoined == 1


@pytest.mark.parametrize("where", ["first", "last"])
def test_a_delimiter_damaged_into_a_byte_costs_no_frame(where: str) -> None:
    one = encode_frame(0x81, bytes(900), 7, 9, coded=True)
    assert one.endswith(b"\x00\x00")  # a coded frame ends with two delimiters
    wire = bytearray(one * 2)
    at = len(one) - 2 if where == "last" else len(one)
    wire[at] = 0x10  # the first frame's first trailing delimiter, or the next's leading one
    dec = FrameDecoder(fec=True)
    assert [f.payload for f in dec.feed(bytes(wire))] == [bytes(900)] * 2


@pytest.mark.parametrize("ber", [1e-3, 3e-3])
def test_a_coded_frame_of_any_size_survives_the_line(ber: float) -> None:
    """Delivery no longer falls with size: 5 frames each of 200 B to 60 kB, seeded (each
    frame alone: nothing after it ends it but its own delimiters)."""
    for size in (200, 4000, 60000):
        for seed in range(5):
            payload = bytes(np.random.default_rng(seed).integers(0, 4, size, dtype=np.uint8))
            wire = encode_frame(0x81, payload, 7, 9, coded=True)
            got = FrameDecoder(fec=True).feed(LineNoise(ber, [size, seed])(wire))
            assert [f.payload for f in got] == [payload], (size, seed)


@given(st.lists(st.binary(max_size=300), max_size=8), st.integers(0, 1000))
def test_line_noise_depends_on_stream_position_only(writes: list[bytes], seed: int) -> None:
    """The same seed flips the same bits however the stream is cut into writes."""
    whole = LineNoise(0.01, [seed, 0])(b"".join(writes))
    cut = LineNoise(0.01, [seed, 0])
    assert b"".join(cut(w) for w in writes) == whole


def test_line_noise_rate_is_the_bit_error_rate() -> None:
    noise = LineNoise(1e-3, 4)
    noise(bytes(500_000))
    assert noise.flipped == pytest.approx(4000, rel=0.1)


# ---- the target: 100 short scans at a bit error rate of 1e-3, byte for byte ------------------
SHORT = "virtual://flat-wall?seed=3&instrument.columns=16"


def _scan(url: str, frames: int = 1) -> list[bytes]:
    """The columns of ``frames`` frames of ``url``, each after a whole power matrix
    (near-far control's POWER_SET, a different one every frame)."""
    import cdma_lidar.virtual  # noqa: F401 - registers virtual://
    from cdma_lidar.protocol.columns import encode_column
    from cdma_lidar.protocol.link import HostLink
    from cdma_lidar.protocol.ports import open_port

    with HostLink(open_port(url), timeout_s=2.0) as link:
        info = link.hello()
        assert link.coded  # virtual:// is a serial line: FEC by default
        cols = []
        for f in range(frames):
            power = np.random.default_rng(f).integers(4_000, 16_000,
                                                      (info.channels, info.column_count))
            link.set_power(power)
            cols += [encode_column(c) for c in link.scan(frame=7 + f)]
        return cols


def test_one_hundred_short_scans_at_1e3_give_the_clean_cloud() -> None:
    clean = _scan(SHORT)
    assert len(clean) == 16
    bad = [seed for seed in range(100)
           if _scan(f"{SHORT}&line_error_rate=0.001&line_seed={seed}") != clean]
    assert bad == []


def test_short_scans_with_near_far_power_at_3e3_give_the_clean_cloud() -> None:
    """The fast suite's version of the paper-scene1 test below: 5 line seeds, 2 frames."""
    clean = _scan(SHORT, frames=2)
    bad = [seed for seed in range(5)
           if _scan(f"{SHORT}&line_error_rate=0.003&line_seed={seed}", frames=2) != clean]
    assert bad == []


@pytest.mark.slow
@pytest.mark.parametrize("ber", [1e-3, 3e-3])
def test_ten_paper_scene_scans_with_near_far_power_give_the_clean_cloud(ber: float) -> None:
    """paper-scene1, a 40 x 160 power matrix before each of 2 frames, line seeds 0..9."""
    base = "virtual://paper-scene1?seed=3"
    clean = _scan(base, frames=2)
    bad = [seed for seed in range(10)
           if _scan(f"{base}&line_error_rate={ber:g}&line_seed={seed}", frames=2) != clean]
    assert bad == []


def test_a_frame_split_after_a_stray_chunk_is_still_joined() -> None:
    """A damaged boundary leaves one byte between delimiters; the next frame, split by a
    byte damaged into 0x00, is joined without that stray chunk."""
    one = encode_frame(0x81, bytes(range(1, 200)) * 6, 7, 9, coded=True)
    wire = bytearray(one * 2)
    wire[len(one) - 1] = 0x33  # the first frame's second delimiter: a chunk of its own
    wire[len(one) + 300] = 0  # the second frame split in two
    dec = FrameDecoder(fec=True)
    assert [f.payload for f in dec.feed(bytes(wire))] == [bytes(range(1, 200)) * 6] * 2
