"""Generate the tables of ``docs/protocol.md`` from the declarations in code.

Every table of the spec page sits between ``<!-- BEGIN GENERATED: name -->`` and
``<!-- END GENERATED: name -->``. ``python -m cdma_lidar.protocol.spec`` rewrites them in
place; with ``--check`` it exits 1 when the committed page differs from the code (the
test suite runs the same check).
"""

from __future__ import annotations

import argparse
import re
import sys
from collections.abc import Callable, Sequence
from pathlib import Path

import numpy as np

from cdma_lidar.column_record import RECORD_EXTRA_SIZE, RECORD_FIXED_SIZE, wire_layout
from cdma_lidar.fileio import atomic_write_text
from cdma_lidar.protocol import auth, fec, framing, trust
from cdma_lidar.protocol.columns import (
    COLUMN_HEADER,
    FLAG_CALIBRATION,
    NO_PEAK,
    RECORD_FIELDS,
    ColumnResult,
    column_payload_size,
)
from cdma_lidar.protocol.config_keys import CONFIG_KEYS, CONFIG_OPTIONAL, config_key
from cdma_lidar.protocol.messages import (
    FRAGMENT_HEADER,
    MAX_PIECES,
    MESSAGES,
    SCHEMA_CRC,
    TILT_AUTO,
    ErrorCode,
    MsgKind,
    MsgType,
    encode_payload,
    piece_room,
    split_message,
)
from cdma_lidar.protocol.schema import Field

__all__ = ["DOC_PATH", "SECTIONS", "check", "main", "render"]

DOC_PATH = Path(__file__).resolve().parent.parent / "docs" / "protocol.md"


def _table(head: tuple[str, ...], rows: list[tuple]) -> str:
    return "\n".join("| " + " | ".join(str(c).replace("|", "\\|") for c in r) + " |"
                     for r in [head, ("---",) * len(head), *rows])


def constants_table() -> str:
    """Protocol constants."""
    rows = [
        ("`PROTOCOL_VERSION`", framing.PROTOCOL_VERSION, "header byte 0"),
        ("`HEADER_SIZE`", framing.HEADER_SIZE, "bytes"),
        ("`CRC_SIZE`", framing.CRC_SIZE, "bytes, CRC-32 little-endian after the payload"),
        ("`FRAME_LIMIT`", framing.FRAME_LIMIT,
         "largest max frame size a device may announce (bytes, header + payload + CRC)"),
        ("`MIN_MAX_FRAME`", framing.MIN_MAX_FRAME,
         "smallest max frame a device announces; every request fits (bytes)"),
        ("`MIN_HOST_FRAME`", MESSAGES[MsgType.HELLO].field("host_max_frame").lo,
         "smallest HELLO.host_max_frame (bytes)"),
        ("`SIGNATURE_SIZE`", framing.SIGNATURE_SIZE,
         "bytes between payload and CRC of a signed frame: u64 counter + 16-byte MAC"),
        ("`FRAGMENT_OVERHEAD`", framing.OVERHEAD + FRAGMENT_HEADER,
         "bytes of a FRAGMENT frame besides its data (+ SIGNATURE_SIZE when signed)"),
        ("`MAX_PIECES`", MAX_PIECES, "most FRAGMENTs of one message"),
        ("`COMPAT_RETRANSMIT`", f"0x{framing.COMPAT_RETRANSMIT:02x}",
         "compat flag: frame is a retransmission"),
        ("`INCOMPAT_SIGNED`", f"0x{framing.INCOMPAT_SIGNED:02x}",
         "incompat flag: the frame is signed (signature before the CRC)"),
        ("`INCOMPAT_KNOWN`", f"0x{framing.INCOMPAT_KNOWN:02x}",
         f"incompat flags understood by version {framing.PROTOCOL_VERSION}"),
        ("`CONFIG_OPTIONAL`", f"0x{CONFIG_OPTIONAL:02x}", "key id bit: ignorable if unknown"),
        ("`FLAG_CALIBRATION`", f"0x{FLAG_CALIBRATION:02x}", "COLUMN_RESULT flags bit"),
        ("`TILT_AUTO`", f"{TILT_AUTO} (-2^31)",
         "INFO.tilt_udeg: no mounting tilt given, the host derives it"),
        ("`NO_PEAK`", f"0x{NO_PEAK:08X}",
         "COLUMN_RESULT lag of a peak that was not found (the receiver's lag -1)"),
        ("`SCHEMA_CRC`", f"0x{SCHEMA_CRC:08x}", "CRC-32 of this schema, sent in INFO"),
    ]
    return _table(("name", "value", "meaning"), rows)


def ranges_table() -> str:
    """Every request field: wire range (else MALFORMED), device rule, code (CONFIG keys'
    ranges: :func:`config_table`)."""
    rows = []
    for t, m in MESSAGES.items():
        if m.kind is not MsgKind.REQUEST:
            continue
        for f in m.fields:
            rule, code = m.rules.get(f.name, ("", None))
            rows.append((t.name, f"`{f.name}`", f.range_text or "any", rule or "none",
                         f"`{code.name}`" if code is not None else ""))
    return _table(("message", "field", "wire range (outside: `MALFORMED`)",
                   "device check", "NAK code"), rows)


def messages_table() -> str:
    """Overview of every message type."""
    return _table(("type", "name", "kind", "direction", "reply", "purpose"), [
        (f"0x{int(t):02X}", f"[{t.name}](#{t.name.lower()})", m.kind.value,
         "host → device" if m.kind is MsgKind.REQUEST else "device → host",
         m.reply.name if m.reply else "", m.doc) for t, m in MESSAGES.items()])


def _fields_table(fields: Sequence[Field], offsets: list | None = None) -> str:
    """Field rows; offsets summed from the sizes unless given."""
    rows: list[tuple] = []
    off: int | str = 0
    for k, f in enumerate(fields):
        rows.append((off if offsets is None else offsets[k], f"`{f.name}`", f.ctype, f.unit,
                     f.range_text, f.doc))
        off = off + f.size if isinstance(off, int) and f.size else "var"
    return _table(("offset", "field", "type", "unit", "range", "meaning"), rows)


def message_fields() -> str:
    """One field table per message (COLUMN_RESULT: see its own section)."""
    parts = []
    for t, m in MESSAGES.items():
        parts.append(f"#### {t.name}\n\n`0x{int(t):02X}`, {m.kind.value}. {m.doc}\n")
        if t == MsgType.COLUMN_RESULT:
            parts.append("Layout: see [COLUMN_RESULT layout](#column_result-layout).\n")
        elif not m.fields:
            parts.append("Empty payload (`payload_len` = 0).\n")
        else:
            parts.append(_fields_table(m.fields) + "\n")
    return "\n".join(parts).rstrip()


def column_table() -> str:
    """COLUMN_RESULT header and per-channel record (offsets of the record in terms of P)."""
    head = _fields_table(COLUMN_HEADER.fields)
    rec = _fields_table(RECORD_FIELDS, [
        f"{at.offset} + {at.offset_per_extra}(P-1)" if at.offset_per_extra else at.offset
        for at in wire_layout()])
    return (f"Column header ({COLUMN_HEADER.sizeof()} bytes):\n\n{head}\n\n"
            f"Channel record (`{RECORD_FIXED_SIZE} + {RECORD_EXTRA_SIZE} (P-1)` bytes, K of "
            f"them, channel 0 first):\n\n{rec}")


def column_size() -> str:
    """The payload size sentence of COLUMN_RESULT (derived from the record declaration)."""
    return (f"`{COLUMN_HEADER.sizeof()} + K ({RECORD_FIXED_SIZE} + {RECORD_EXTRA_SIZE} "
            f"(P-1))` bytes (40 channels, 1 peak: {column_payload_size(40, 1)} bytes; 40 "
            f"channels, 8 peaks: {column_payload_size(40, 8)} bytes)")


def config_table() -> str:
    """CONFIG keys."""
    return _table(("key", "name", "value type", "unit", "wire range (else MALFORMED)",
                   "device range (else OUT_OF_RANGE)", "read-only", "meaning"),
                  [(k.id, f"`{k.name}`", k.ctype, k.unit,
                    "any that parses" if k.lo is None else f"{k.lo}..{k.hi}", k.allowed,
                    "yes" if k.read_only else "", k.doc) for k in CONFIG_KEYS])


def info_ranges_table() -> str:
    """Physical range of each INFO field with a unit (what a host checks, section 8)."""
    return _table(("INFO field", "allowed (inclusive)", "unit"),
                  [(f"`{name}`", f"{lo}..{hi}", unit) for name, (lo, hi, unit)
                   in trust.INFO_RANGES.items()])


def errors_table() -> str:
    """NAK error codes."""
    return _table(("code", "name", "meaning"),
                  [(int(c), f"`{c.name}`", c.doc) for c in ErrorCode])


def examples() -> str:
    """Hex dumps of complete frames (seq 0x0102, session 0xA1B2C3D4)."""
    cases = [
        ("STATUS_GET request, seq 0x0102, session 0xA1B2C3D4", MsgType.STATUS_GET, {}),
        ("SCAN_START frame 7, columns 0..99", MsgType.SCAN_START,
         {"frame": 7, "first_column": 0, "columns": 100}),
        ("ACK of a SCAN_START", MsgType.ACK, {"request_type": int(MsgType.SCAN_START)}),
        ("NAK of a CONFIG_SET: OUT_OF_RANGE, field `peaks`", MsgType.NAK,
         {"request_type": int(MsgType.CONFIG_SET), "code": 4, "field": "peaks",
          "detail": ""}),
        ("COLUMN_RESULT of frame 7, column 3, 2 channels, P = 1, n = 2, angle -1.5 deg",
         MsgType.COLUMN_RESULT, ColumnResult.from_arrays(
             7, 3, -1.5, peak_lag=[100, 2041], peak=[52000, -300], neighbours=[[20, 19],
                                                                                [-7, 2]],
             noise_count=[120, 120], noise_sum=[-35, 16], noise_sumsq=[9100, 8800],
             uid_signs=[[1, -1], [1, 0]], uid_observed=[2, 0], uid_match=[True, False],
             saturated=[False, False],
             timestamp_us=1_000_000)),
    ]
    out = []
    for title, t, f in cases:
        wire = framing.encode_frame(int(t), encode_payload(t, f), 0x0102, 0xA1B2C3D4)
        body = framing.cobs_decode(wire[1:-1])  # header, payload, CRC (little-endian)
        crc = body[-framing.CRC_SIZE:]
        out.append(f"{title}:\n\n```text\nframe  {body[:-framing.CRC_SIZE].hex(' ')} | crc "
                   f"{int.from_bytes(crc, 'little'):08x} (LE {crc.hex(' ')})\nwire   "
                   f"{wire.hex(' ')}\n```")
    return "\n\n".join(out)


def vectors() -> str:
    """Test vectors of access control and FEC, computed by the code that runs the link."""
    key = bytes(range(32))
    host_nonce, device_nonce = bytes(range(0x10, 0x20)), bytes(range(0x20, 0x30))
    session, flags, host_max = 0xA1B2C3D4, 0x04, 4096
    to_dev, to_host = auth.session_macs(key, host_nonce, device_nonce, session)
    payload = encode_payload(MsgType.STATUS_GET, {})
    signed = framing.encode_frame(int(MsgType.STATUS_GET), payload, 0x0102, session,
                                  signer=to_dev)
    sent = framing.decode_frame(framing.cobs_decode(signed[1:-1]))
    ack = encode_payload(MsgType.ACK, {"request_type": int(MsgType.SCAN_START)})
    coded = framing.encode_frame(int(MsgType.ACK), ack, 0x0102, session, coded=True)
    # A request longer than the frame: POWER_SET of 1 x 120 at max frame 256, in pieces.
    power = encode_payload(MsgType.POWER_SET, {
        "channel_start": 0, "column_start": 0, "channels": 1, "columns": 120,
        "power": np.arange(120, dtype=np.uint16) * 500})
    room = piece_room(256, False)
    pieces = [framing.encode_frame(int(MsgType.FRAGMENT), p, 0x0102, session)
              for p in split_message(MsgType.POWER_SET, power, room, 0x0102)]
    nak = encode_payload(MsgType.NAK, {"request_type": int(MsgType.STATUS_GET),
                                       "code": int(ErrorCode.WRONG_SESSION), "field": "session",
                                       "detail": ""})
    ended = framing.encode_frame(int(MsgType.NAK), nak, 0x0102, session,
                                 signer=auth.FrameMac(to_host.key, counter=6))
    lines = [
        f"key (the key file's 64 hex digits, decoded: the key is these 32 bytes)\n"
        f"             {key.hex()}",
        f"host_nonce   {host_nonce.hex()}",
        f"device_nonce {device_nonce.hex()}",
        f"session_id   0x{session:08X}, HELLO flags 0x{flags:02X}, host_max_frame {host_max}",
        f"HELLO mac    {auth.hello_mac(key, device_nonce, host_nonce, flags, host_max).hex()}",
        f"INFO device_mac {auth.device_mac(key, host_nonce, device_nonce, session).hex()}",
        f"key to device {to_dev.key.hex()}",
        f"key to host   {to_host.key.hex()}",
        f"STATUS_GET seq 0x0102, signed host -> device, counter 1:\n"
        f"  header  {sent.signed_bytes().hex(' ')}\n"
        f"  sig     {sent.sig.hex(' ')}\n"
        f"  wire    {signed.hex(' ')}",
        f"ACK of SCAN_START, seq 0x0102, FEC-coded (whitened, COBS, then RS parity spread):\n"
        f"  wire    {coded.hex(' ')}",
        f"whitening bytes 0..7: {fec.whiten(bytes(8)).hex(' ')}",
        f"POWER_SET of 1 x 120 (values 0, 500, 1000, ...), seq 0x0102, max frame 256: "
        f"{len(power)} payload bytes in {len(pieces)} FRAGMENTs of at most {room} data bytes:\n"
        + "\n".join(f"  wire {k}  {w.hex(' ')}" for k, w in enumerate(pieces)),
        "NAK WRONG_SESSION to a STATUS_GET of the session above after it ended, signed with\n"
        "that session's key to the host, counter 7:\n"
        f"  wire    {ended.hex(' ')}",
        "poly_u (32, 22, 2, 1), i.e. x^32 + x^22 + x^2 + x + 1, on the wire: "
        f"{config_key('poly_u').encode((32, 22, 2, 1)).hex(' ')} (mask 0x80200003)",
    ]
    return "```text\n" + "\n".join(lines) + "\n```"


#: Generated sections by marker name.
SECTIONS: dict[str, Callable[[], str]] = {
    "constants": constants_table,
    "header": lambda: _fields_table(framing.HEADER_FIELDS.fields),
    "messages": messages_table,
    "fields": message_fields,
    "column": column_table,
    "column_size": column_size,
    "config": config_table,
    "errors": errors_table,
    "info_ranges": info_ranges_table,
    "ranges": ranges_table,
    "examples": examples,
    "vectors": vectors,
}

_BLOCK = re.compile(r"(<!-- BEGIN GENERATED: (\w+) -->\n)(.*?)(<!-- END GENERATED: \2 -->)",
                    re.S)


def render(text: str) -> str:
    """``text`` with every generated block replaced by its current content."""
    def sub(m: re.Match) -> str:
        name = m.group(2)
        if name not in SECTIONS:
            raise KeyError(f"unknown generated section {name!r} in docs/protocol.md")
        return f"{m.group(1)}{SECTIONS[name]()}\n{m.group(4)}"

    return _BLOCK.sub(sub, text)


def check(path: Path = DOC_PATH) -> bool:
    """True when the page at ``path`` equals its regenerated form."""
    text = path.read_text(encoding="utf-8")
    return render(text) == text


def main(argv: list[str] | None = None) -> int:
    """Regenerate (or with --check, verify) the tables of docs/protocol.md."""
    ap = argparse.ArgumentParser(prog="python -m cdma_lidar.protocol.spec",
                                 description=__doc__.split("\n")[0])
    ap.add_argument("--check", action="store_true", help="exit 1 if the page is stale")
    ap.add_argument("--path", type=Path, default=DOC_PATH)
    args = ap.parse_args(argv)
    text = args.path.read_text(encoding="utf-8")
    if (new := render(text)) != text:
        if args.check:
            sys.stderr.write(f"{args.path} is stale: run python -m cdma_lidar.protocol.spec\n")
            return 1
        atomic_write_text(args.path, new)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
