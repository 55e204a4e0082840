"""A second, independent host: written from docs/protocol.md alone, it scans the virtual device.

Nothing of ``cdma_lidar.protocol`` is used by the client: its COBS and CRC follow the
page's text and C snippets, and every layout it packs or parses (frame header, HELLO,
SCAN_START, FRAGMENT, SCAN_END, the COLUMN_RESULT header and channel record) is read
at test time from the page's generated tables. Its columns must equal, field by
field, what the reference host decodes from the same scan.
"""

from __future__ import annotations

import hashlib
import hmac
import re
import secrets
import struct
from pathlib import Path

import numpy as np
import reedsolo
import serial

import cdma_lidar.virtual  # noqa: F401 - registers virtual:// with pyserial
from cdma_lidar.protocol.link import HostLink  # the reference host, for comparison only
from cdma_lidar.protocol.ports import open_port

PAGE = (Path(__file__).resolve().parents[2] / "docs" / "protocol.md").read_text("utf-8")
URL = "virtual://flat-wall?instrument.wavelengths.count=5&instrument.columns=4&seed=2"
_CT = {"u8": "B", "u16": "H", "u32": "I", "u64": "Q", "i8": "b", "i16": "h", "i32": "i",
       "i64": "q"}


# ---- the page's tables ---------------------------------------------------------------------
def _rows(after: str) -> list[list[str]]:
    """Rows of the first table after the heading or sentence ``after``."""
    text = PAGE[PAGE.index(after):]
    lines = text.split("\n| --- ", 1)[1].split("\n")[1:]
    rows = []
    for line in lines:
        if not line.startswith("|"):
            break
        rows.append([c.strip() for c in re.split(r"(?<!\\)\|", line)[1:-1]])
    return rows


def _fmt(section: str) -> tuple[str, list[str]]:
    """struct format and names of a message table of fixed-size integer fields."""
    fmt, names = "<", []
    for row in _rows(section):
        field, ctype = row[1].strip("`"), row[2]
        m = re.fullmatch(r"u8 x (\d+)", ctype)
        fmt += f"{m.group(1)}s" if m else _CT.get(ctype, "")
        if m or ctype in _CT:
            names.append(field)
    return fmt, names


HEADER_FMT = "<" + "".join(_CT[r[2]] for r in _rows("### 2.1 Header"))
HELLO = _fmt("#### HELLO")
SCAN_START = _fmt("#### SCAN_START")
FRAGMENT = _fmt("#### FRAGMENT")
SCAN_END = _fmt("#### SCAN_END")
COLUMN_HEADER = _fmt("Column header (")
TYPES = {re.sub(r"\[(\w+)\].*", r"\1", r[1]): int(r[0], 16) for r in _rows("## 3. Messages")}
VERSION = int(next(r[1] for r in _rows("### 2.4 Constants") if r[0] == "`PROTOCOL_VERSION`"))


def record_dtype(peaks: int) -> np.dtype:
    """The channel record as the page's table says, for P = ``peaks``."""
    fields = []
    for row in _rows("Channel record ("):
        name, ctype = row[1].strip("`"), row[2]
        m = re.fullmatch(r"(\w+?)(?:\[(.+)\])?", ctype)
        base, count = m.group(1), m.group(2)
        dt = np.dtype("<" + _CT[base])
        if count is None:
            fields.append((name, dt))
        else:
            n = peaks - 1 if count == "P-1" else int(count)
            fields.append((name, dt, (n,)))
    return np.dtype(fields)


# ---- CRC-32 and COBS, as section 2 describes them -----------------------------------------------
def crc32(data: bytes) -> int:
    c = 0xFFFFFFFF
    for b in data:
        c ^= b
        for _ in range(8):
            c = (c >> 1) ^ (0xEDB88320 & -(c & 1))
    return c ^ 0xFFFFFFFF


def cobs_encode(data: bytes) -> bytes:
    out, block = bytearray(), bytearray()
    for b in data:
        if b == 0:
            out += bytes([len(block) + 1]) + block
            block.clear()
        else:
            block.append(b)
            if len(block) == 254:
                out += b"\xff" + block
                block.clear()
    return bytes(out + bytes([len(block) + 1]) + block)


def cobs_decode(data: bytes) -> bytes:
    out, i = bytearray(), 0
    while i < len(data):
        code = data[i]
        out += data[i + 1:i + code]
        i += code
        if code != 0xFF and i < len(data):
            out.append(0)
    return bytes(out)


class Client:
    def __init__(self, port) -> None:
        self.port, self.buf, self.seq, self.session = port, b"", 7, 0

    def send(self, name: str, payload: bytes) -> None:
        self.seq += 1
        head = struct.pack(HEADER_FMT, VERSION, 0, 0, TYPES[name], self.seq, len(payload),
                           self.session)
        body = head + payload
        self.port.write(b"\x00" + cobs_encode(body + struct.pack("<I", crc32(body))) + b"\x00")

    def chunks(self):
        """The COBS-encoded frames between 0x00 delimiters, as they arrive (section 3)."""
        while True:
            while b"\x00" not in self.buf:
                self.buf += self.port.read(max(1, self.port.in_waiting)) or b""
            chunk, self.buf = self.buf.split(b"\x00", 1)
            if chunk:
                yield chunk

    def frames(self):
        """Decoded frames (type, seq, session, payload); checks the CRC."""
        for chunk in self.chunks():
            body = cobs_decode(chunk)
            assert struct.unpack("<I", body[-4:])[0] == crc32(body[:-4])
            version, _inc, _comp, mtype, seq, plen, session = struct.unpack_from(HEADER_FMT, body)
            assert version == VERSION
            yield mtype, seq, session, body[12:12 + plen]

    def messages(self):
        """Whole messages, FRAGMENTs put together (section 6.3)."""
        parts: dict = {}
        for mtype, seq, session, payload in self.frames():
            if mtype != TYPES["FRAGMENT"]:
                yield mtype, seq, session, payload
                continue
            size = struct.calcsize(FRAGMENT[0])
            f = dict(zip(FRAGMENT[1], struct.unpack_from(FRAGMENT[0], payload), strict=True))
            key = (f["msg_type"], f["seq"], f["frame"], f["column"])
            got = parts.setdefault(key, {})
            got[f["index"]] = payload[size:]
            if len(got) == f["count"]:
                del parts[key]
                yield f["msg_type"], f["seq"], session, b"".join(got[i] for i in range(f["count"]))


def test_a_client_written_from_the_page_scans_the_virtual_device() -> None:
    port = serial.serial_for_url(URL, timeout=0.05)
    client = Client(port)
    msgs = client.messages()
    fields = {"host_max_frame": 96, "flags": 0, "host_nonce": secrets.token_bytes(16),
              "device_nonce": bytes(16), "mac": bytes(32)}  # 96 bytes: INFO comes in pieces
    client.send("HELLO", struct.pack(HELLO[0], *(fields[n] for n in HELLO[1])))
    mtype, _seq, session, _info = next(msgs)
    assert mtype == TYPES["INFO"]
    client.session = session
    client.send("SCAN_START", struct.pack(SCAN_START[0], 9, 0, 4))
    columns = []
    for mtype, _seq, _session, payload in msgs:
        if mtype == TYPES["COLUMN_RESULT"]:
            size = struct.calcsize(COLUMN_HEADER[0])
            head = dict(zip(COLUMN_HEADER[1], struct.unpack_from(COLUMN_HEADER[0], payload),
                            strict=True))
            rec = np.frombuffer(payload, record_dtype(head["peaks"]), head["channels"], size)
            columns.append((head, rec))
        elif mtype == TYPES["SCAN_END"]:
            end = dict(zip(SCAN_END[1], struct.unpack(SCAN_END[0], payload), strict=True))
            assert end["columns"] == 4 and end["reason"] == 0
            break
    port.close()

    with HostLink(open_port(URL), timeout_s=1.0) as link:
        reference = list(link.scan(frame=9, columns=4))
    assert [h["column"] for h, _ in columns] == [0, 1, 2, 3]
    for (head, rec), col in zip(columns, reference, strict=True):
        assert (head["frame"], head["angle_udeg"], head["uid_bits"]) == \
            (col.frame, col.angle_udeg, col.uid_bits)
        assert rec.dtype.names == col.records.dtype.names  # every field the page names
        for name in rec.dtype.names:
            assert np.array_equal(rec[name], col.records[name]), name


# ---- a keyed, signed, FEC-coded session, from sections 2.5 and 5 alone ------------------------
def _mac(key: bytes, *parts: bytes) -> bytes:
    return hmac.new(key, b"".join(parts), hashlib.sha256).digest()


def _whiten(data: bytes) -> bytes:
    return bytes(b ^ ((0x5A + 0x97 * i) & 0xFF) for i, b in enumerate(data))


def _spread(parity: bytes) -> bytes:
    """48 parity bytes as 55 bytes 0x80 | 7 bits (section 2.5), bit by bit."""
    bits = "".join(f"{p:08b}" for p in parity) + "0"
    return bytes(0x80 | int(bits[i:i + 7], 2) for i in range(0, len(bits), 7))


def _rs_encode(stuffed: bytes) -> bytes:
    rs = reedsolo.RSCodec(48, nsize=255)
    out = b""
    for i in range(0, len(stuffed), 207):
        block = bytes(rs.encode(stuffed[i:i + 207]))
        out += block[:-48] + _spread(block[-48:])
    return out


def _rs_data(coded: bytes) -> bytes:
    """The data bytes of an undamaged coded chunk (the pipe does not damage them)."""
    return b"".join(coded[i:i + 262][:-55] for i in range(0, len(coded), 262))


class SignedClient(Client):
    """Signs (section 5) and codes (section 2.5) what it sends; reads coded frames."""

    def __init__(self, port) -> None:
        super().__init__(port)
        self.k_dev = self.k_host = b""
        self.counter = self.last_in = 0
        self.keys = None  # session id -> (k_to_device, k_to_host), once HELLO has its MAC

    def send(self, name: str, payload: bytes) -> None:
        self.seq += 1
        head = struct.pack(HEADER_FMT, VERSION, 1 if self.k_dev else 0, 0, TYPES[name], self.seq,
                           len(payload), self.session)
        body = head + payload
        if self.k_dev:
            self.counter += 1
            c = struct.pack("<Q", self.counter)
            body += c + _mac(self.k_dev, body, c)[:16]
        body += struct.pack("<I", crc32(body))
        self.port.write(b"\x00" + _rs_encode(cobs_encode(_whiten(body))) + b"\x00")

    def frames(self):
        for chunk in self.chunks():
            body = cobs_decode(chunk)
            if len(body) < 16 or struct.unpack("<I", body[-4:])[0] != crc32(body[:-4]):
                body = _whiten(cobs_decode(_rs_data(chunk)))  # coded (section 2.5)
            assert struct.unpack("<I", body[-4:])[0] == crc32(body[:-4])
            _v, incompat, _c, mtype, seq, plen, session = struct.unpack_from(HEADER_FMT, body)
            payload = body[12:12 + plen]
            if self.keys is not None and incompat & 1 and not self.k_host:
                # The signed INFO (or its first piece) names the session the keys are for.
                self.k_dev, self.k_host = self.keys(session)
            if self.k_host:  # every frame of the session signed, counters rising
                assert incompat & 1
                sig = body[12 + plen:-4]
                assert sig[8:] == _mac(self.k_host, body[:12 + plen], sig[:8])[:16]
                counter = struct.unpack("<Q", sig[:8])[0]
                assert counter > self.last_in
                self.last_in = counter
            yield mtype, seq, session, payload


def test_a_client_from_the_page_opens_a_keyed_fec_session() -> None:
    """HELLO, CHALLENGE, HELLO with the MAC, signed INFO in pieces, a signed STATUS: all coded."""
    from protocol_fixtures import RunningDevice, SyntheticApp  # the device under test

    from cdma_lidar.virtual.line import pipe_pair

    key = bytes(range(32))
    host, dev = pipe_pair()
    with RunningDevice(dev, SyntheticApp(channels=40, columns=2), key=key):
        client = SignedClient(host)
        msgs = client.messages()
        nonce = secrets.token_bytes(16)
        fields = {"host_max_frame": 256, "flags": 4, "host_nonce": nonce,
                  "device_nonce": bytes(16), "mac": bytes(32)}
        client.send("HELLO", struct.pack(HELLO[0], *(fields[n] for n in HELLO[1])))
        mtype, _seq, _session, dn = next(msgs)
        assert mtype == TYPES["CHALLENGE"]
        fields["device_nonce"] = dn
        fields["mac"] = _mac(key, b"cdma-lidar hello", dn, nonce, struct.pack("<BH", 4, 256))
        client.keys = lambda s: tuple(_mac(key, b"cdma-lidar to " + who, nonce, dn,
                                           struct.pack("<I", s)) for who in (b"device", b"host"))
        client.send("HELLO", struct.pack(HELLO[0], *(fields[n] for n in HELLO[1])))
        mtype, _seq, session, payload = next(msgs)
        assert mtype == TYPES["INFO"] and client.last_in > 1  # signed pieces: 256-byte frames
        info_fmt = _fmt("#### INFO")
        info = dict(zip(info_fmt[1], struct.unpack_from(info_fmt[0], payload), strict=True))
        assert info["session_id"] == session and info["auth"] == 1
        assert info["device_mac"] == _mac(key, b"cdma-lidar device", nonce, dn,
                                          struct.pack("<I", session))
        client.session = session
        client.send("STATUS_GET", b"")
        mtype, _seq, _session, _payload = next(msgs)
        assert mtype == TYPES["STATUS"]
