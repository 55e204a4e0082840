"""docs/protocol.md is generated from the declarations: it must equal its regenerated form."""

from __future__ import annotations

import inspect
import re

import pytest

from cdma_lidar.protocol import spec
from cdma_lidar.protocol.columns import column_payload_size
from cdma_lidar.protocol.config_keys import CONFIG_KEYS
from cdma_lidar.protocol.framing import FrameDecoder, crc32, encode_frame
from cdma_lidar.protocol.link import HostLink
from cdma_lidar.protocol.messages import (
    MESSAGES,
    SCHEMA_CRC,
    ErrorCode,
    MsgType,
    decode_payload,
)
from cdma_lidar.protocol.requests import (
    DIAG_GARBAGE,
    DIAG_HINTS,
    DIAG_NO_ANSWER,
    DIAG_NOISY,
    DIAG_SILENT,
    DIAG_VERSION,
    DIAG_WRONG_SESSION,
)


def test_committed_spec_page_matches_the_code() -> None:
    assert spec.check(), "docs/protocol.md is stale: run python -m cdma_lidar.protocol.spec"
    assert spec.main(["--check"]) == 0


def test_page_mentions_every_message_key_and_error() -> None:
    text = spec.DOC_PATH.read_text(encoding="utf-8")
    for t in MESSAGES:
        assert f"#### {t.name}" in text
    for k in CONFIG_KEYS:
        assert f"| {k.id} | `{k.name}` |" in text
    for c in ErrorCode:
        assert f"| {int(c)} | `{c.name}` |" in text
    assert f"0x{SCHEMA_CRC:08x}" in text


def test_stale_table_is_detected_and_rewritten(tmp_path) -> None:
    page = tmp_path / "protocol.md"
    text = spec.DOC_PATH.read_text(encoding="utf-8")
    stale = text.replace("| 16 | `peaks` |", "| 16 | `peaks_old` |")
    assert stale != text
    page.write_text(stale, encoding="utf-8")
    assert spec.main(["--check", "--path", str(page)]) == 1
    assert spec.main(["--path", str(page)]) == 0
    assert page.read_text(encoding="utf-8") == text


def test_unknown_section_is_an_error() -> None:
    with pytest.raises(KeyError, match="nope"):
        spec.render("<!-- BEGIN GENERATED: nope -->\n<!-- END GENERATED: nope -->")


def test_example_wire_bytes_in_the_page_decode() -> None:
    text = spec.DOC_PATH.read_text(encoding="utf-8")
    wires = re.findall(r"^wire   ([0-9a-f ]+)$", text, re.M)
    assert len(wires) == 5
    frames = [FrameDecoder().feed(bytes.fromhex(w))[0] for w in wires]
    assert [f.msg_type for f in frames] == [MsgType.STATUS_GET, MsgType.SCAN_START, MsgType.ACK,
                                            MsgType.NAK, MsgType.COLUMN_RESULT]
    col = decode_payload(MsgType.COLUMN_RESULT, frames[-1].payload)
    assert col.column == 3 and col.angle_deg == -1.5 and list(col.peak_lag) == [100, 2041]
    assert all(f.seq == 0x0102 and f.session == 0xA1B2C3D4 for f in frames)


def test_hand_written_numbers_of_the_page_match_the_code() -> None:
    """The prose outside the generated blocks: CRC example, diagnoses, default timing."""
    text = spec.DOC_PATH.read_text(encoding="utf-8")
    head = bytes.fromhex("04 00 00 0a 02 01 00 00 d4 c3 b2 a1")
    assert f"give CRC 0x{crc32(head):08X}" in text
    wire = encode_frame(MsgType.STATUS_GET, b"", 0x0102, 0xA1B2C3D4)
    assert f"COBS-encode to `{wire[1:-1].hex(' ')}`" in text
    for diag in (DIAG_SILENT, DIAG_GARBAGE, DIAG_WRONG_SESSION, DIAG_VERSION, DIAG_NO_ANSWER,
                 DIAG_NOISY):
        assert f"| `{diag}` |" in text
    sig = inspect.signature(HostLink.__init__).parameters
    timeout, retries = sig["timeout_s"].default, sig["retries"].default
    assert f"| {timeout:g} s per try, {retries} retries;" in text
    assert f"(default {10 * (retries + 1)})" in text
    assert f"40 channels, 1 peak: {column_payload_size(40, 1)} bytes" in text


def test_every_diagnosis_has_a_hint_and_a_row_in_the_page() -> None:
    text = spec.DOC_PATH.read_text(encoding="utf-8")
    assert set(DIAG_HINTS) == {DIAG_SILENT, DIAG_GARBAGE, DIAG_WRONG_SESSION, DIAG_VERSION,
                               DIAG_NO_ANSWER, DIAG_NOISY}
    assert all(hint and f"| `{d}` |" in text for d, hint in DIAG_HINTS.items())


def test_the_pages_fragmented_power_set_is_acted_on_by_the_device() -> None:
    """Section 10's POWER_SET in FRAGMENTs, read off the page, sets the power (a request in
    pieces is joined by (type, seq) and acted on once)."""
    import numpy as np
    from protocol_fixtures import SteppedDevice, SyntheticApp, hello_fields

    from cdma_lidar.protocol.messages import encode_payload

    text = spec.DOC_PATH.read_text(encoding="utf-8")
    wires = [bytes.fromhex(h) for h in re.findall(r"^  wire \d  ([0-9a-f ]+)$", text, re.M)]
    assert len(wires) == 2
    app = SyntheticApp(channels=2, columns=120)
    dev = SteppedDevice(app, session_id=0xA1B2C3D4, max_frame=256)
    dev.write(encode_frame(MsgType.HELLO, encode_payload(MsgType.HELLO, hello_fields(1, 256)),
                           0x0101, 0))
    dev.read(4096)
    for w in wires:
        dev.write(w)
    frames = FrameDecoder().feed(dev.read(4096))
    assert [f.msg_type for f in frames] == [MsgType.ACK] and frames[0].seq == 0x0102
    np.testing.assert_array_equal(app.power[0], np.arange(120) * 500)


def test_the_pieces_each_reference_end_keeps_are_what_the_page_says() -> None:
    """Section 6.3: how many messages in pieces the reference device and host hold."""
    from protocol_fixtures import ScriptedPort, SyntheticApp

    from cdma_lidar.protocol.endpoint import DeviceEndpoint, Engine

    text = spec.DOC_PATH.read_text(encoding="utf-8")
    m = re.search(r"reference device keeps the pieces of at most (\d+) requests, the\s+"
                  r"reference host those of (\d+) replies or notices", text)
    assert m is not None
    device = DeviceEndpoint(ScriptedPort(), SyntheticApp(), engine=Engine(threaded=False))
    assert device._pieces.limit == int(m[1])
    assert HostLink(ScriptedPort()).joiner.limit == int(m[2])
