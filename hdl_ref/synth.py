"""Resource use of the reference RTL from yosys.

Run as ``python -m cdma_lidar.hdl_ref.synth [--write-doc]``.

Synthesises each design of :data:`DESIGNS` with three yosys flows:

* ``generic``: ``synth -flatten`` up to the ``fine`` step, then the rest of
  ``synth`` without ``memory_map`` (so RAMs stay RAMs and are reported as
  memory bits, not as flip-flops), down to yosys's internal gate library;
* ``ice40``: ``synth_ice40`` (Lattice iCE40: 4-input LUTs, SB_RAM40_4K 4 kbit
  block RAMs, no multipliers);
* ``xc7``: ``synth_xilinx -family xc7 -noiopad`` (Xilinx 7-series: 6-input LUTs,
  RAMB36E1/RAMB18E1 block RAMs, DSP48E1).

and prints Markdown tables. With ``--write-doc`` it replaces the section
between ``<!-- synth:begin -->`` and ``<!-- synth:end -->`` in ``docs/hdl.md``
(written atomically), so the figures in the documentation are never typed by
hand. Needs ``yosys`` on PATH (Debian package ``yosys``; figures in the doc are
from the version the table names). Resource counts only: yosys does not place
and route, so no clock-frequency figure is claimed.
"""

from __future__ import annotations

import argparse
import json
import logging
import re
import shutil
import subprocess
import sys
import tempfile
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path

from cdma_lidar.errors import ConfigError
from cdma_lidar.fileio import atomic_write_text
from cdma_lidar.hdl_ref.cosim import RTL_DIR

__all__ = [
    "DESIGNS", "FLOWS", "Design", "main", "markdown", "synthesise", "table_row", "update_doc",
    "yosys_version",
]

log = logging.getLogger(__name__)

DOC_PATH = Path(__file__).resolve().parent.parent / "docs" / "hdl.md"
BEGIN, END = "<!-- synth:begin -->", "<!-- synth:end -->"


@dataclass(frozen=True)
class Design:
    """One synthesis run: top module, its sources and parameter overrides."""

    name: str
    top: str
    sources: tuple[str, ...]
    params: Mapping[str, int]
    note: str


RX_SOURCES = ("lfsr_fib.v", "sdp_ram.v", "rx_chain.v")
DESIGNS: tuple[Design, ...] = (
    Design("lfsr_fib m<=11", "lfsr_fib", ("lfsr_fib.v",), {"MAX_DEG": 11},
           "one LFSR, run-time polynomial"),
    Design("gold_gen m<=11", "gold_gen", ("lfsr_fib.v", "gold_gen.v"),
           {"MAX_DEG": 11, "MAX_UID": 8}, "two LFSRs, UID polarity up to 8 periods"),
    Design("rx_chain small", "rx_chain", RX_SOURCES,
           {"MAX_DEG": 7, "MAX_S": 4, "MAX_UID": 1, "MAX_R": 4, "MAX_G": 32, "MAX_P": 1,
            "NGHOST": 1, "ADC_W": 12, "OUT_W": 16},
           "m<=7, S<=4, no UID, R<=4, 32 lags, 1 peak, 1 ghost window, 12-bit ADC, 16-bit out"),
    Design("rx_chain paper", "rx_chain", RX_SOURCES,
           {"MAX_DEG": 11, "MAX_S": 4, "MAX_UID": 3, "MAX_R": 16, "MAX_G": 64, "MAX_P": 2,
            "NGHOST": 2, "ADC_W": 12, "OUT_W": 32},
           "m<=11, S<=4, 3-bit UID, R<=16, 64 lags, 2 peaks, 2 ghost windows, 12-bit ADC, "
           "32-bit out"),
)

FLOWS: dict[str, str] = {
    "generic": ("synth -flatten -top {top} -run begin:fine; "
                "tee -q -o {mem} dump t:$mem_v2; "
                "opt -fast -full; opt -full; techmap; opt -fast; abc -fast; opt -fast"),
    "ice40": "synth_ice40 -top {top}",
    "xc7": "synth_xilinx -family xc7 -noiopad -top {top}",
}


def _yosys() -> str:
    exe = shutil.which("yosys")
    if exe is None:
        raise FileNotFoundError("yosys not found on PATH (Debian: apt-get install yosys)")
    return exe


def yosys_version() -> str:
    """``yosys -V`` output, e.g. ``Yosys 0.23 (git sha1 7ce5011c24b)``."""
    return subprocess.run([_yosys(), "-V"], capture_output=True, text=True,
                          check=True).stdout.strip()


def _memory_bits(dump: str) -> tuple[int, int]:
    """(memories, bits) from an RTLIL dump of the $mem_v2 cells."""
    sizes = [int(v) for v in re.findall(r"parameter \\SIZE (\d+)", dump)]
    widths = [int(v) for v in re.findall(r"parameter \\WIDTH (\d+)", dump)]
    if len(sizes) != len(widths):
        raise ConfigError("cannot read memory sizes from the yosys dump", field="dump")
    return len(sizes), sum(s * w for s, w in zip(sizes, widths, strict=True))


def synthesise(design: Design, flow: str) -> dict[str, int]:
    """Run one flow on one design; return the cell counts by type (plus memory figures)."""
    if flow not in FLOWS:
        raise ConfigError(f"flow must be one of {', '.join(FLOWS)}, not {flow!r}", field="flow")
    with tempfile.TemporaryDirectory(prefix="hdl_synth_") as tmp:
        mem = Path(tmp) / "mem.txt"
        stat = Path(tmp) / "stat.json"
        chparam = " ".join(f"-set {k} {v}" for k, v in design.params.items())
        script = "; ".join([
            "read_verilog -defer " + " ".join(str(RTL_DIR / s) for s in design.sources),
            f"chparam {chparam} {design.top}" if chparam else "",
            FLOWS[flow].format(top=design.top, mem=mem),
            f"tee -q -o {stat} stat -json",
        ])
        proc = subprocess.run([_yosys(), "-q", "-p", script], capture_output=True, text=True,
                              check=False)
        if proc.returncode != 0 or not stat.exists():
            raise RuntimeError(f"yosys failed on {design.name} / {flow}:\n{proc.stderr[-2000:]}")
        cells = dict(json.loads(stat.read_text())["design"]["num_cells_by_type"])
        if flow == "generic":
            cells.pop("$mem_v2", None)
            n_mem, bits = _memory_bits(mem.read_text() if mem.exists() else "")
            cells["memories"] = n_mem
            cells["memory bits"] = bits
    return cells


def _sum(cells: Mapping[str, int], pattern: str) -> int:
    return sum(v for k, v in cells.items() if re.fullmatch(pattern, k))


COLUMNS: dict[str, list[tuple[str, str]]] = {
    "generic": [("gates", r"\$_(?!.*DFF).*_"), ("flip-flops", r"\$_.*DFF.*_"),
                ("memories", "memories"), ("memory bits", "memory bits")],
    "ice40": [("SB_LUT4", "SB_LUT4"), ("SB_CARRY", "SB_CARRY"), ("flip-flops", "SB_DFF.*"),
              ("SB_RAM40_4K", "SB_RAM40_4K"), ("SB_MAC16", "SB_MAC16")],
    "xc7": [("LUTs", r"LUT\d"), ("flip-flops", r"FD[CPRS]E?"), ("CARRY4", "CARRY4"),
            ("MUXF7/F8", "MUXF[78]"), ("LUTRAM", r"RAM\d+[XM].*"), ("RAMB36E1", "RAMB36E1"),
            ("RAMB18E1", "RAMB18E1"), ("DSP48E1", "DSP48E1")],
}


def markdown(results: Mapping[tuple[str, str], Mapping[str, int]], version: str) -> str:
    """Markdown tables (one per flow) of the synthesis results."""
    lines = [f"Produced by `python -m cdma_lidar.hdl_ref.synth --write-doc` with {version}.", ""]
    lines.append("| design | parameters |")
    lines.append("|---|---|")
    for d in DESIGNS:
        params = ", ".join(f"{k}={v}" for k, v in d.params.items())
        lines.append(f"| {d.name} | {params} ({d.note}) |")
    for flow in FLOWS:
        cols = COLUMNS[flow]
        lines += ["", f"**{flow}** (`{FLOWS[flow].split(';')[0].format(top='<top>')}`)", ""]
        lines.append("| design | " + " | ".join(c for c, _ in cols) + " |")
        lines.append("|---" * (len(cols) + 1) + "|")
        lines += [table_row(d, flow, results[(d.name, flow)]) for d in DESIGNS]
    return "\n".join(lines) + "\n"


def table_row(design: Design, flow: str, cells: Mapping[str, int]) -> str:
    """One Markdown table row: the design's name and the flow's resource columns."""
    return f"| {design.name} | " + " | ".join(str(_sum(cells, p)) for _, p in COLUMNS[flow]) \
        + " |"


def update_doc(text: str, table: str) -> str:
    """``text`` with the section between the synth markers replaced by ``table``."""
    start, end = text.find(BEGIN), text.find(END)
    if start < 0 or end < start:
        raise ConfigError(f"docs/hdl.md must contain {BEGIN} ... {END}", field="docs/hdl.md")
    return text[:start + len(BEGIN)] + "\n" + table + text[end:]


def main(argv: list[str] | None = None) -> int:
    """Synthesise every design with every flow; print (or write into docs/hdl.md) the tables."""
    parser = argparse.ArgumentParser(prog="python -m cdma_lidar.hdl_ref.synth", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--write-doc", action="store_true",
                        help=f"replace the synthesis section of {DOC_PATH}")
    args = parser.parse_args(argv)
    try:
        version = yosys_version()
    except FileNotFoundError as exc:
        sys.stderr.write(f"{exc}\n")
        return 2
    results = {}
    for d in DESIGNS:
        for flow in FLOWS:
            log.info("synthesising %s with %s", d.name, flow)
            results[(d.name, flow)] = synthesise(d, flow)
    table = markdown(results, version)
    if args.write_doc:
        atomic_write_text(DOC_PATH, update_doc(DOC_PATH.read_text(), table))
    else:
        sys.stdout.write(table)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
