"""The C snippets of docs/protocol.md compile and agree with the Python codec byte for byte.

A firmware engineer copies them from the page; this test copies them the same way,
builds them with the system C compiler and runs them over seeded vectors: every
COBS edge length, random frames, malformed chunks and the page's example frames.
"""

from __future__ import annotations

import random
import re
import shutil
import subprocess

import pytest
import wire_oracle

from cdma_lidar.errors import FrameError
from cdma_lidar.protocol import spec
from cdma_lidar.protocol.framing import crc32, encode_frame

CC = shutil.which("cc") or shutil.which("gcc") or shutil.which("clang")
pytestmark = pytest.mark.skipif(CC is None, reason="needs a C compiler")

HARNESS = r"""
#include <stdint.h>
#include <stddef.h>
#include <stdio.h>
#include <string.h>

%s

static uint8_t in[70000], out[70000];

static size_t unhex(const char *s, uint8_t *dst) {
    size_t n = 0;
    unsigned v;
    while (sscanf(s, "%%2x", &v) == 1) { dst[n++] = (uint8_t)v; s += 2; }
    return n;
}

static void hex(const uint8_t *p, size_t n) {
    for (size_t i = 0; i < n; i++) printf("%%02x", p[i]);
}

/* Each input line: "E <hex>" encode, "D <hex>" decode a chunk, "C <hex>" crc32. */
int main(void) {
    static char line[300000];
    while (fgets(line, sizeof line, stdin)) {
        line[strcspn(line, "\n")] = 0;
        size_t n = unhex(line + 2, in);
        if (line[0] == 'E') { hex(out, cobs_encode(in, n, out)); }
        else if (line[0] == 'D') {
            long m = cobs_decode(in, n, out, sizeof out);
            if (m < 0) printf("bad"); else hex(out, (size_t)m);
        } else { printf("%%08x", (unsigned)crc32(in, n)); }
        printf("\n");
    }
    return 0;
}
"""


@pytest.fixture(scope="module")
def c_codec(tmp_path_factory) -> str:
    text = spec.DOC_PATH.read_text(encoding="utf-8")
    snippets = re.findall(r"```c\n(.*?)```", text, re.S)
    assert len(snippets) == 2, "expected the COBS and the CRC-32 snippets"
    assert "cobs_encode" in snippets[0] and "cobs_decode" in snippets[0]
    assert "crc32" in snippets[1]
    d = tmp_path_factory.mktemp("cref")
    src, exe = d / "cref.c", d / "cref"
    src.write_text(HARNESS % "\n".join(snippets), encoding="utf-8")
    subprocess.run([CC, "-std=c99", "-O1", "-Wall", "-Wextra", "-Werror", "-o", str(exe),
                    str(src)], check=True, capture_output=True, timeout=60)
    return str(exe)


def _run(exe: str, lines: list[str]) -> list[str]:
    res = subprocess.run([exe], input="\n".join(lines) + "\n", capture_output=True, text=True,
                         check=True, timeout=60)
    return res.stdout.splitlines()


def _py_decode(chunk: bytes) -> str:
    try:
        return wire_oracle.cobs_decode_py(chunk).hex()
    except FrameError:
        return "bad"


def test_c_crc32_matches_and_has_the_stated_check_value(c_codec: str) -> None:
    rng = random.Random(5)
    data = [b"123456789", b"", *(rng.randbytes(rng.randrange(1, 3000)) for _ in range(50))]
    got = _run(c_codec, ["C " + d.hex() for d in data])
    assert got[0] == "cbf43926"
    assert got == [f"{crc32(d):08x}" for d in data]


def test_c_cobs_matches_the_python_codec(c_codec: str) -> None:
    rng = random.Random(6)
    data: list[bytes] = []
    for n in (0, 1, 253, 254, 255, 507, 508, 509, 1000):
        data += [bytes([f]) * n for f in (0x00, 0x01, 0xFF)]
    for _ in range(200):  # zero-rich and zero-poor data, lengths across block boundaries
        n = rng.randrange(0, 1200)
        p = rng.choice([0.0, 0.01, 0.3])
        data.append(bytes(0 if rng.random() < p else rng.randrange(1, 256) for _ in range(n)))
    enc = _run(c_codec, ["E " + d.hex() for d in data])
    assert enc == [wire_oracle.cobs_encode_py(d).hex() for d in data]
    dec = _run(c_codec, ["D " + e for e in enc])
    assert dec == [d.hex() for d in data]


def test_c_cobs_decoder_rejects_what_python_rejects(c_codec: str) -> None:
    rng = random.Random(7)
    chunks = [b"\x05\x01\x02", b"\x03\x01\x00", b"\x02", b"\xff" + b"\x01" * 10]
    for _ in range(300):  # damaged encodings: flipped, cut or zero-injected bytes
        e = bytearray(wire_oracle.cobs_encode_py(rng.randbytes(rng.randrange(1, 600))))
        how = rng.randrange(3)
        if how == 0:
            e[rng.randrange(len(e))] ^= 1 << rng.randrange(8)
        elif how == 1:
            del e[rng.randrange(1, len(e) + 1):]
        else:
            e[rng.randrange(len(e))] = 0
        chunks.append(bytes(e) or b"\x07")
    got = _run(c_codec, ["D " + c.hex() for c in chunks])
    assert got == [_py_decode(c) for c in chunks]
    assert got.count("bad") >= 50


def test_c_reads_the_example_frames_of_the_page(c_codec: str) -> None:
    """Decode each example's wire bytes in C, then check its CRC in C: as a device would."""
    text = spec.DOC_PATH.read_text(encoding="utf-8")
    wires = [bytes.fromhex(w) for w in re.findall(r"^wire   ([0-9a-f ]+)$", text, re.M)]
    wires.append(encode_frame(0x0A, b"", 0xFFFF, 0xFFFFFFFF))
    frames = _run(c_codec, ["D " + w[1:-1].hex() for w in wires])
    assert "bad" not in frames
    bodies = [bytes.fromhex(f) for f in frames]
    crcs = _run(c_codec, ["C " + b[:-4].hex() for b in bodies])
    assert crcs == [f"{int.from_bytes(b[-4:], 'little'):08x}" for b in bodies]
