"""The receive chain from the ADC pins (``rx_adc_top``): R_MIN and the fixed-rate ADC bench.

``rx_adc_top`` (``hdl_ref/rtl/rx_adc_top.v``) puts ``adc_rx`` (one sample per ADC
clock, packed P_IN to a word, carried into the fabric clock by an asynchronous FIFO)
in front of an unchanged ``rx_top``, and refuses at ``start`` a configuration that
``rx_top`` cannot process as fast as a fixed-rate ADC delivers it. :func:`r_min` is the
Python side of that bound, the Verilog side is ``r_min_rom.v``; the tests check that
both give the same number for every degree and ``samples_per_chip`` of a sweep of
builds. A valid/ready source that can wait (``rx_top`` alone, the RTL engine) is not
bound by it: ``rx_top`` applies back-pressure and stays exact at any R.

:func:`run_adc_bench` plays ``cdma-lidar hdl vectors`` files through the fixed-rate ADC
bench (two unrelated clocks) and returns its verdict line. Its stimulus and checks are one
delay-free module, ``hdl_ref/tb/rx_adc_top_vectors_check.v``; the clocks come from
Verilog delays under Icarus (``rx_adc_top_vectors_tb.v``, seconds to build: the small
builds) or from a picosecond loop in C++ under Verilator without ``--timing``
(``rx_adc_top_vectors_main.cpp``; built once per vector geometry, a minute or more, and
cached under ``$XDG_CACHE_HOME/cdma-lidar/adc-bench/``: the paper build, whose 640 lanes
take Icarus hours).
"""

from __future__ import annotations

import hashlib
import subprocess
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from cdma_lidar.checks import check_int
from cdma_lidar.errors import out_of_range
from cdma_lidar.hdl_ref import engine
from cdma_lidar.hdl_ref.cosim import (
    TOP_FILES,
    TopParams,
    default_rtl_dir,
    top_ports,
    top_timing,
)

__all__ = ["ADC_SOURCES", "CHECK", "GEARING_MODELS", "MAIN", "PIN_SOURCES", "SIMULATORS",
           "TB", "adc_ports", "r_min", "run_adc_bench"]

#: the sources of ``rx_adc_top`` (rx_top's and the three of the ADC side)
ADC_SOURCES = (*TOP_FILES, "adc_rx.v", "r_min_rom.v", "rx_adc_top.v")
#: ... and with ``PINS = 1``, the DDR pin front end (its primitives: :data:`GEARING_MODELS`)
PIN_SOURCES = (*ADC_SOURCES, "adc_pins.v")
TB = Path(__file__).resolve().parent / "tb" / "rx_adc_top_vectors_tb.v"
#: our behavioural models of the ECP5's IDDRX2F, ECLKSYNCB and CLKDIVF (simulation only)
GEARING_MODELS = TB.with_name("ecp5_gearing_models.v")
#: the bench's stimulus and checks (no delays), and the Verilator bench's C++ clocks
CHECK = TB.with_name("rx_adc_top_vectors_check.v")
MAIN = TB.with_name("rx_adc_top_vectors_main.cpp")
SIMULATORS = ("icarus", "verilator")


def r_min(params: TopParams, degree: int, spc: int) -> int:
    """The smallest averages R with which ``rx_top`` keeps up with a fixed-rate source.

    Real time holds when ``process + 1 <= column_clocks`` (:func:`cosim.top_timing
    <cdma_lidar.hdl_ref.cosim.top_timing>`, clocks); ``process`` is taken at the build's
    largest gate and peak count and one UID period, the worst case (more gate lags or
    peaks add clocks; more periods add samples faster than clocks), so every
    configuration of the build at this degree and ``spc`` (samples per chip) with
    ``R >= r_min`` keeps up. Returns ``params.max_r + 1`` when no R of the build does,
    or when the build cannot run the degree and ``spc`` at all (degree outside
    3..max_deg, ``spc`` outside 1..max_s or not a multiple of P_IN, or K L > N - 2).
    """
    n_chips = (1 << degree) - 1
    p_in = params.samples_per_clock
    if (not 3 <= degree <= params.max_deg or not 1 <= spc <= params.max_s or spc % p_in
            or params.channels * params.lanes > n_chips - 2):
        return params.max_r + 1
    worst = {"cfg_degree": degree, "cfg_spc": spc, "cfg_uid_bits": 1, "cfg_averages": 1,
             "cfg_gate_len": params.max_g, "cfg_peaks": params.max_p}
    clocks_per_r = top_timing(worst, params)["column_clocks"]      # N S / P_IN
    r = -(-(top_timing(worst, params)["process"] + 1) // clocks_per_r)
    return r if r <= params.max_r else params.max_r + 1


def adc_ports(cfg: Any, poly_u: Sequence[int], poly_v: Sequence[int],
              indices: Sequence[int], params: TopParams, columns: int = 1) -> dict[str, int]:
    """``rx_adc_top`` port values (those of :func:`cosim.top_ports
    <cdma_lidar.hdl_ref.cosim.top_ports>`); ConfigError naming ``averages`` when R is
    below :func:`r_min`, the configuration the RTL refuses at ``start`` (``err_config``)."""
    ports = top_ports(cfg, poly_u, poly_v, indices, params, columns=columns)
    lo = r_min(params, int(poly_u[0]), cfg.samples_per_chip)
    if lo > params.max_r:
        raise out_of_range("averages", f"in R_MIN..{params.max_r}, and this build keeps up "
                           f"with no R at degree {poly_u[0]}, samples_per_chip "
                           f"{cfg.samples_per_chip}", cfg.averages)
    if not lo <= cfg.averages <= params.max_r:
        raise out_of_range("averages", f"{lo}..{params.max_r} (R_MIN of this build: below it "
                           "rx_top falls behind a fixed-rate ADC)", cfg.averages)
    return ports


def run_adc_bench(vec_dir: str | Path, work_dir: str | Path, adc_ps: int = 4000,
                  fab_ps: int | None = None, phase_ps: int = 0, gap: tuple[int, int] = (0, 0),
                  timeout_s: float = 3600.0, simulator: str = "icarus",
                  pins: bool = False, runs: int = 1, restart: int = 24) -> str:
    """Compile and run the fixed-rate ADC bench on a vector folder; its verdict line.

    ``adc_ps``, ``fab_ps`` (default P_IN samples), ``phase_ps``: the ADC clock's and
    the fabric clock's periods and the fabric clock's start offset, picoseconds; ``gap =
    (every, length)``: the ADC's valid drops for ``length`` ADC clocks after every
    ``every`` samples (0: never). ``pins``: ``rx_adc_top`` with ``PINS = 1``, the DDR
    pins through ``adc_pins`` and our models of the ECP5 gearing (P_IN must be 4, no gaps);
    ``adc_ps`` is then the DDR data clock's period, two samples (8 000 for 250 MS/s);
    ``runs``: with the pins, start the acquisition that many times (``restart`` fabric
    clocks after each ``done``; ``rx_adc_top`` refuses a start sooner than 2^FIFO_AW + 8),
    the same samples and words each time.
    ``simulator``: ``"icarus"`` (built in ``work_dir``) or
    ``"verilator"`` (built once per ``params.vh`` into the cache; raises
    ``cosim.SimulatorMissing`` without Verilator or g++). The line starts ``rx_adc_top
    vectors: PASS``, ``FAIL`` or ``REFUSED`` (``rx_adc_top_vectors_check.v``'s header).
    """
    if simulator not in SIMULATORS:
        raise out_of_range("simulator", " or ".join(SIMULATORS), simulator)
    vec_dir, work_dir = Path(vec_dir), Path(work_dir)
    rtl = default_rtl_dir()
    p_in = _define(vec_dir, "VEC_P")
    if pins and p_in != 4:
        raise out_of_range("samples_per_clock", "4 with the DDR pins (one IDDRX2F word)", p_in)
    if pins and gap != (0, 0):
        raise out_of_range("gap", "(0, 0) with the DDR pins (the converter never pauses)", gap)
    if not (1 <= runs if pins else runs == 1):
        raise out_of_range("runs", "1 or more with the DDR pins, else 1", runs)
    check_int("restart", restart, 1, 1_000_000)
    sources = [*(rtl / n for n in (PIN_SOURCES if pins else ADC_SOURCES)),
               *([GEARING_MODELS] if pins else []), CHECK]
    if fab_ps is None:
        fab_ps = (p_in // 2 if pins else p_in) * adc_ps
    args = [f"+VEC={vec_dir}/", f"+ADC_PS={adc_ps}", f"+FAB_PS={fab_ps}",
            f"+PHASE_PS={phase_ps}", f"+GAP_EVERY={gap[0]}", f"+GAP_LEN={gap[1]}",
            f"+RUNS={runs}", f"+RESTART={restart}"]
    if simulator == "icarus":
        work_dir.mkdir(parents=True, exist_ok=True)
        vvp = work_dir / "adc_tb.vvp"
        subprocess.run(["iverilog", "-g2005", "-I", str(vec_dir), *(["-DVEC_PINS"] if pins
                        else []), "-o", str(vvp), str(TB), *map(str, sources)],
                       check=True, capture_output=True, text=True)
        cmd = ["vvp", "-n", str(vvp), *args]
    else:
        cmd = [str(_verilator_bench(vec_dir, sources, pins)), *args]
    out = subprocess.run(cmd, check=True, capture_output=True, text=True,
                         timeout=timeout_s).stdout
    return [line for line in out.splitlines() if line.startswith("rx_adc_top vectors:")][-1]


def _define(vec_dir: Path, name: str) -> int:
    """The value of ``name`` in the vector folder's ``params.vh``."""
    for line in (vec_dir / "params.vh").read_text().splitlines():
        f = line.split()
        if len(f) == 3 and f[0] == "`define" and f[1] == name:
            return int(f[2])
    raise out_of_range("params.vh", f"a vector folder's file that defines {name}", vec_dir)


def _verilator_bench(vec_dir: Path, sources: Sequence[Path], pins: bool = False) -> Path:
    """The Verilator bench for the vector folder's ``params.vh`` (cached: the build depends
    on the sources and on params.vh only; the hex files are read at run time)."""
    params_vh = (vec_dir / "params.vh").read_text() + ("`define VEC_PINS\n" if pins else "")
    h = hashlib.sha256(params_vh.encode())
    for path in (*sources, MAIN):
        h.update(path.read_bytes())
    folder = engine.cache_root().parent / "adc-bench" / h.hexdigest()[:20]
    # -O1: the paper build's C++ is large; compiling it at -O2 costs more than it saves
    return engine.verilate(folder, "rx_adc_top_vectors_check",
                           [*map(str, sources), str(MAIN)], vec_dir.name,
                           files={"params.vh": params_vh}, c_opt="-O1")
