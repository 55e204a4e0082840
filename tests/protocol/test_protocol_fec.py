"""Reed-Solomon FEC inside the COBS frame, reproducible line noise, and the 1e-3 target."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from cdma_lidar.protocol import fec
from cdma_lidar.protocol.framing import FrameDecoder, encode_frame
from cdma_lidar.virtual.line import LineNoise


@given(st.binary(max_size=2000))
def test_coded_body_round_trips_and_its_length_gives_the_body_length(body: bytes) -> None:
    coded = fec.encode(body)
    assert len(coded) == fec.coded_len(len(body))
    assert fec.body_len(len(coded)) == len(body)
    assert fec.strip(coded) == body == fec.decode(coded)


@given(st.binary(max_size=2000))
def test_table_driven_encoder_equals_reedsolo(body: bytes) -> None:
    assert fec.encode(body) == fec.encode_reference(body)


@settings(max_examples=50)
@given(st.binary(min_size=1, max_size=1200), st.integers(0, 2**32 - 1))
def test_eight_damaged_bytes_per_block_are_corrected(body: bytes, seed: int) -> None:
    coded = bytearray(fec.encode(body))
    rng = np.random.default_rng(seed)
    for start in range(0, len(coded), fec.BLOCK):
        block = min(fec.BLOCK, len(coded) - start)
        for i in rng.choice(block, size=min(8, block), replace=False):
            coded[start + int(i)] ^= int(rng.integers(1, 256))
    assert fec.decode(bytes(coded)) == body


def test_whitening_leaves_few_zero_bytes_for_cobs() -> None:
    """A zero-rich body (column records) codes to about one zero in 256: few COBS code
    bytes for a bit error to hit."""
    coded = fec.encode(bytes(4000))
    assert coded.count(0) < len(coded) / 100


@given(st.binary(max_size=600), st.booleans())
def test_a_decoder_with_fec_reads_coded_and_plain_frames(payload: bytes, coded: bool) -> None:
    wire = encode_frame(0x81, payload, 7, 9, coded=coded)
    (frame,) = FrameDecoder(fec=True).feed(wire)
    assert (frame.payload, frame.fec) == (payload, coded)
    assert FrameDecoder().feed(wire) == ([] if coded else [frame._replace(fec=False)])


def test_a_byte_damaged_into_a_delimiter_is_rejoined() -> None:
    payload = bytes(range(1, 200)) * 3
    wire = bytearray(encode_frame(0x81, payload, 7, 9, coded=True))
    wire[300] = 0  # the line turned one byte into 0x00: two damaged chunks
    dec = FrameDecoder(fec=True)
    (frame,) = dec.feed(bytes(wire))
    assert frame.payload == payload and dec.stats.rejoined == 1


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


def _scan(url: str) -> list[bytes]:
    import cdma_lidar.virtual  # noqa: F401 - registers virtual://
    from cdma_lidar.protocol.columns import encode_column
    from cdma_lidar.protocol.link import HostLink
    from cdma_lidar.protocol.ports import open_port

    with HostLink(open_port(url), timeout_s=0.5) as link:
        link.hello()
        assert link.coded  # virtual:// is a serial line: FEC by default
        return [encode_column(c) for c in link.scan(frame=7)]


def test_one_hundred_short_scans_at_1e3_give_the_clean_cloud() -> None:
    clean = _scan(SHORT)
    assert len(clean) == 16
    bad = [seed for seed in range(100)
           if _scan(f"{SHORT}&line_error_rate=0.001&line_seed={seed}") != clean]
    assert bad == []


@pytest.mark.slow
def test_ten_paper_scene_scans_at_1e3_give_the_clean_cloud() -> None:
    base = "virtual://paper-scene1?seed=3"
    clean = _scan(base)
    bad = [seed for seed in range(10)
           if _scan(f"{base}&line_error_rate=0.001&line_seed={seed}") != clean]
    assert bad == []
