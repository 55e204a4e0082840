"""Test vectors for anyone's testbench: the files of ``cdma-lidar hdl vectors``.

What the files hold, the plain Verilog testbench that plays them and the ``--set`` keys
are told by the command's help (:mod:`cdma_lidar.hdl_ref.cli`, which imports this module
when the command runs). The expected words come from :mod:`cdma_lidar.firmware_model`
(the vectorised receiver, bit-identical to the streaming reference); nothing of the RTL
is used to make them.
"""

from __future__ import annotations

import argparse
import dataclasses
import logging
import sys
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from cdma_lidar.checks import check_int
from cdma_lidar.errors import ConfigError, out_of_range
from cdma_lidar.fileio import atomic_write_text, check_writable
from cdma_lidar.firmware_model.gold import gold_code
from cdma_lidar.firmware_model.output import ReceiverOutput
from cdma_lidar.firmware_model.pairs import preferred_pairs
from cdma_lidar.firmware_model.receiver import FastReceiver, ReceiverConfig
from cdma_lidar.hdl_ref.cosim import TOP_FILES, TopParams, top_ports, top_schedule
from cdma_lidar.hdl_ref.stimuli import echo_column

__all__ = ["CFG_ORDER", "RESULT_ORDER", "VectorSpec", "cmd_vectors", "expected_words",
           "spec_from_settings", "write_vectors"]

log = logging.getLogger(__name__)

#: Configuration ports in the order of ``config.hex`` (one line each).
CFG_ORDER: tuple[str, ...] = (
    "cfg_columns", "cfg_degree", "cfg_taps_u", "cfg_taps_v", "cfg_seed_u", "cfg_seed_v",
    "cfg_spc", "cfg_averages", "cfg_uid_bits", "cfg_uid", "cfg_gate_start", "cfg_gate_len",
    "cfg_peak_exclude", "cfg_ghost_start", "cfg_ghost_len", "cfg_out_shift", "cfg_rounding",
    "cfg_out_bits", "cfg_peaks",
)
#: Result ports in the order of ``results.hex`` (one line each, per column and channel).
RESULT_ORDER: tuple[str, ...] = (
    "res_found", "res_lag", "res_index", "res_peak", "res_neg", "res_nz", "res_nb_lo",
    "res_nb_hi", "res_noise_count", "res_noise_sum", "res_noise_sumsq", "res_uid_observed",
    "res_uid_match", "res_saturated",
)
_EXTRA_KEYS = ("degree", "pair", "channels", "lanes", "samples_per_clock", "first_index",
               "amplitude", "noise", "ghost", "ghost2")
_CFG_KEYS = tuple(f.name for f in dataclasses.fields(ReceiverConfig) if f.name != "ghost_windows")


@dataclasses.dataclass(frozen=True)
class VectorSpec:
    """What to export: configuration, code pair, K members and the stimulus level."""

    cfg: ReceiverConfig
    degree: int = 7
    pair: int = 0
    channels: int = 4
    lanes: int = 2
    samples_per_clock: int = 1  # P_IN of the build: ADC samples per clock
    first_index: int = 0
    amplitude: float = 0.3      # echo amplitude, fraction of full scale
    noise: float = 0.1          # noise rms, fraction of full scale

    def params(self) -> TopParams:
        """The smallest ``rx_top`` build that runs this configuration."""
        c = self.cfg
        return TopParams(channels=self.channels, lanes=self.lanes, max_deg=self.degree,
                         max_s=c.samples_per_chip, max_uid=c.uid_bits, max_r=c.averages,
                         max_g=c.gate_len, max_p=c.peaks, nghost=max(1, len(c.ghost_windows)),
                         adc_w=c.adc_bits, out_w=32, samples_per_clock=self.samples_per_clock)

    def polys(self) -> tuple[tuple[int, ...], tuple[int, ...]]:
        """The preferred pair used (``preferred_pairs(degree)[pair]``)."""
        pairs = preferred_pairs(self.degree)
        if not 0 <= self.pair < len(pairs):
            raise out_of_range("pair", f"0..{len(pairs) - 1} for degree {self.degree}", self.pair)
        return pairs[self.pair]

    def indices(self) -> tuple[int, ...]:
        """Gold member of each channel."""
        n = (1 << self.degree) - 1
        last = self.first_index + self.channels - 1
        if self.first_index < 0 or last > n + 1:
            raise out_of_range("first_index", f"0..{n + 2 - self.channels} (members 0..N+1)",
                               self.first_index)
        return tuple(range(self.first_index, self.first_index + self.channels))


def _number(key: str, text: str) -> float:
    try:
        return float(text)
    except ValueError:
        raise out_of_range(key, "a number", text) from None


def _integer(key: str, text: str) -> int:
    try:
        return int(text, 0)
    except ValueError:
        raise out_of_range(key, "an integer", text) from None


def spec_from_settings(settings: Sequence[str]) -> VectorSpec:
    """A :class:`VectorSpec` from ``KEY=VALUE`` strings (``--set``); ConfigError names the key."""
    cfg_fields: dict[str, Any] = {"averages": 2, "gate_len": 16, "gate_start": 40,
                                  "samples_per_chip": 2}
    extra: dict[str, Any] = {}
    ghosts = []
    for item in settings:
        key, sep, value = item.partition("=")
        key = key.strip()
        if not sep:
            raise out_of_range("--set", "KEY=VALUE", item)
        if key in ("ghost", "ghost2"):
            start, colon, length = value.partition(":")
            if not colon:
                raise out_of_range(key, "START:LEN (samples)", value)
            ghosts.append((_integer(key, start), _integer(key, length)))
        elif key == "rounding":
            cfg_fields[key] = value
        elif key in _CFG_KEYS:
            cfg_fields[key] = _integer(key, value)
        elif key in ("amplitude", "noise"):
            extra[key] = _number(key, value)
        elif key in _EXTRA_KEYS:
            extra[key] = _integer(key, value)
        else:
            raise out_of_range("--set", "one of " + ", ".join((*_CFG_KEYS, *_EXTRA_KEYS)), key)
    check_int("degree", extra.get("degree", 7), 5, 11)
    check_int("channels", extra.get("channels", 4), 1, 64)
    check_int("lanes", extra.get("lanes", 2), 1, 32)
    check_int("samples_per_clock", extra.get("samples_per_clock", 1), 1, 16)
    cfg = ReceiverConfig(**cfg_fields, ghost_windows=tuple(ghosts))
    spec = VectorSpec(cfg=cfg, **extra)
    n_chips = (1 << spec.degree) - 1
    cfg.widths(n_chips)                       # gate and ghosts inside the period
    top_ports(cfg, *spec.polys(), spec.indices(), spec.params())   # fits the build
    return spec


def _hex(value: int, bits: int) -> str:
    """Two's complement of ``value`` in ``bits`` bits, as hex digits (no prefix)."""
    return format(value & ((1 << bits) - 1), f"0{(bits + 3) // 4}x")


def expected_words(out: ReceiverOutput, k: int, ports: Mapping[str, int],
                   params: TopParams) -> dict[str, int]:
    """The result port words ``rx_top`` must show for channel ``k`` of a model output.

    The inverse of :func:`cdma_lidar.hdl_ref.cosim.decode_rx_result`: packed fields,
    two's complement, lag and index 0 for a missing peak.
    """
    ow, lw, gw, uw = params.out_w, params.rx().lag_w, params.rx().g_w, params.max_uid
    ns = ((1 << ports["cfg_degree"]) - 1) * ports["cfg_spc"]
    lags = [int(out.peak_lag[k]), *map(int, out.extra_lag[k])]
    vals = [int(out.peak[k]), *map(int, out.extra_peak[k])]
    signs = [list(map(int, out.uid_signs[k])), *[list(map(int, s)) for s in out.extra_signs[k]]]
    w = dict.fromkeys(("res_found", "res_lag", "res_index", "res_peak", "res_neg", "res_nz"), 0)
    for q, (lag, val, sg) in enumerate(zip(lags, vals, signs, strict=True)):
        if lag < 0:
            continue
        w["res_found"] |= 1 << q
        w["res_lag"] |= lag << (q * lw)
        w["res_index"] |= ((lag - ports["cfg_gate_start"]) % ns) << (q * gw)
        w["res_peak"] |= (val & ((1 << ow) - 1)) << (q * ow)
        w["res_neg"] |= sum(1 << p for p, s in enumerate(sg) if s < 0) << (q * uw)
        w["res_nz"] |= sum(1 << p for p, s in enumerate(sg) if s != 0) << (q * uw)
    w["res_nb_lo"] = int(out.neighbours[k, 0]) & ((1 << ow) - 1)
    w["res_nb_hi"] = int(out.neighbours[k, 1]) & ((1 << ow) - 1)
    w["res_noise_count"] = int(out.noise_count[k])
    w["res_noise_sum"] = int(out.noise_sum[k]) & ((1 << (ow + gw)) - 1)
    w["res_noise_sumsq"] = int(out.noise_sumsq[k])
    w["res_uid_observed"] = int(out.uid_observed[k])
    w["res_uid_match"] = int(bool(out.uid_match[k]))
    w["res_saturated"] = int(bool(out.saturated[k]))
    return w


def _port_widths(params: TopParams) -> dict[str, int]:
    rx = params.rx()
    lw, gw, ow, uw, p = rx.lag_w, rx.g_w, params.out_w, params.max_uid, params.max_p
    return {
        "res_found": p, "res_lag": p * lw, "res_index": p * gw, "res_peak": p * ow,
        "res_neg": p * uw, "res_nz": p * uw, "res_nb_lo": ow, "res_nb_hi": ow,
        "res_noise_count": gw, "res_noise_sum": ow + gw, "res_noise_sumsq": 2 * ow + gw,
        "res_uid_observed": uw, "res_uid_match": 1, "res_saturated": 1,
    }


def write_vectors(spec: VectorSpec, columns: int, seed: int, out_dir: str | Path,
                  params: TopParams | None = None) -> Path:
    """Write the vector files for ``columns`` columns of seeded echoes into ``out_dir``.

    ``params``: the build (default ``spec.params()``, the smallest that runs ``spec``).
    """
    check_int("columns", columns, 1, 1000)
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    params = params or spec.params()
    cfg = spec.cfg
    poly_u, poly_v = spec.polys()
    indices = spec.indices()
    ports = top_ports(cfg, poly_u, poly_v, indices, params, columns=columns)
    n_chips = (1 << spec.degree) - 1
    ns = n_chips * cfg.samples_per_chip
    codes = np.stack([gold_code(poly_u, poly_v, i) for i in indices])
    rng = np.random.default_rng(seed)
    full = 1 << (cfg.adc_bits - 1)
    cols = []
    for c in range(columns):
        delay = (cfg.gate_start + int(rng.integers(0, cfg.gate_len))) % ns
        cols.append(echo_column(codes[c % len(indices)], spc=cfg.samples_per_chip,
                                averages=cfg.averages, uid_bits=cfg.uid_bits, tx_uid=cfg.uid,
                                adc_bits=cfg.adc_bits, delay=delay,
                                amplitude=spec.amplitude * full, noise_rms=spec.noise * full,
                                rng=rng))
    samples = np.stack(cols)
    outs = FastReceiver(cfg, codes).frame(samples)
    widths = _port_widths(params)
    res_w = max(widths.values())
    cfg_w = max(max(int(ports[name]).bit_length() for name in CFG_ORDER), 32)
    adc_lines = [_hex(int(v), params.adc_w) for v in samples.reshape(-1)]
    corr_lines = [_hex(int(v), params.out_w) for o in outs for v in o.corr.reshape(-1)]
    res_lines = []
    for o in outs:
        for k in range(params.channels):
            words = expected_words(o, k, ports, params)
            res_lines += [_hex(words[name], res_w) for name in RESULT_ORDER]
    cfg_lines = [_hex(int(ports[name]), cfg_w) for name in CFG_ORDER]
    defines = {
        "VEC_K": params.channels, "VEC_L": params.lanes, "VEC_P": params.samples_per_clock,
        "VEC_MAX_DEG": params.max_deg,
        "VEC_MAX_S": params.max_s, "VEC_MAX_UID": params.max_uid, "VEC_MAX_R": params.max_r,
        "VEC_MAX_G": params.max_g, "VEC_MAX_P": params.max_p, "VEC_NGHOST": params.nghost,
        "VEC_ADC_W": params.adc_w, "VEC_OUT_W": params.out_w, "VEC_CFG_W": cfg_w,
        "VEC_RES_W": res_w, "VEC_N_CFG": len(cfg_lines), "VEC_N_ADC": len(adc_lines),
        "VEC_N_CORR": len(corr_lines), "VEC_N_RES": len(res_lines),
        "VEC_N_RES_PORTS": len(RESULT_ORDER), "VEC_GATE_LEN": cfg.gate_len,
        "VEC_COLUMNS": columns,
        # the bench's watchdog: twice the clocks cosim.top_schedule needs, plus 1000
        "VEC_MAX_CLOCKS": 2 * top_schedule(ports, params, len(adc_lines),
                                           lambda clock: True)["done"] + 1000,
    }
    files = {
        "config.hex": cfg_lines, "adc.hex": adc_lines, "corr.hex": corr_lines,
        "results.hex": res_lines,
    }
    for name, lines in files.items():
        atomic_write_text(out_dir / name, "\n".join(lines) + "\n")
    atomic_write_text(out_dir / "params.vh", "".join(
        f"`define {k} {v}\n" for k, v in defines.items()))
    atomic_write_text(out_dir / "README.md", _readme(spec, columns, seed, defines, widths,
                                                     poly_u, poly_v, indices))
    log.info("wrote %d columns of vectors to %s", columns, out_dir)
    return out_dir


def _readme(spec: VectorSpec, columns: int, seed: int, d: Mapping[str, int],
            widths: Mapping[str, int], poly_u, poly_v, indices) -> str:
    cfg = spec.cfg
    cfg_text = ", ".join(f"{f.name}={getattr(cfg, f.name)!r}" for f in dataclasses.fields(cfg))
    res_rows = "\n".join(f"| {i} | `{n}` | {widths[n]} |" for i, n in enumerate(RESULT_ORDER))
    cfg_rows = "\n".join(f"| {i} | `{n}` |" for i, n in enumerate(CFG_ORDER))
    files = [
        ("params.vh", "", "Verilog defines: build parameters, word widths, line counts"),
        ("config.hex", d["VEC_N_CFG"], f"one `rx_top` configuration port per line "
         f"({d['VEC_CFG_W']} bits), order below; apply, then pulse `start`"),
        ("adc.hex", d["VEC_N_ADC"], f"ADC samples ({d['VEC_ADC_W']} bits), column by column, "
         f"{d['VEC_P']} per clock (the earliest in the low bits of `s_data`); "
         "within a column repetition r, UID period p, sample i"),
        ("corr.hex", d["VEC_N_CORR"], f"expected `corr_data` ({d['VEC_OUT_W']} bits): column, "
         "then channel 0..K-1, then gate index j = 0..G-1 (the order `rx_top` streams them)"),
        ("results.hex", d["VEC_N_RES"], f"expected result ports ({d['VEC_RES_W']} bits, "
         f"zero-extended): column, then channel, then the {len(RESULT_ORDER)} ports below, "
         "valid in the clock `res_valid` is high"),
    ]
    rtl_files = " \\\n    ".join(" ".join(f"hdl_ref/rtl/{name}" for name in TOP_FILES[i:i + 4])
                                  for i in range(0, len(TOP_FILES), 4))
    file_rows = "| file | lines | layout |\n|---|---|---|\n" + "\n".join(
        f"| `{name}` | {lines} | {text} |" for name, lines, text in files)
    return f"""# rx_top test vectors

Written by `cdma-lidar hdl vectors` (seed {seed}, {columns} columns). Every
expected word comes from the bit-exact model (`cdma_lidar.firmware_model`), not
from the RTL. All files are `$readmemh` text: one word per line, hex, two's
complement where signed, the widths below.

Configuration: {cfg_text}; degree {spec.degree}, pair {list(poly_u)} / {list(poly_v)},
channel k correlates Gold member {list(indices)}[k]. Build parameters
(`params.vh`): K={d['VEC_K']}, L={d['VEC_L']}, P_IN={d['VEC_P']}, MAX_DEG={d['VEC_MAX_DEG']},
MAX_S={d['VEC_MAX_S']}, MAX_UID={d['VEC_MAX_UID']}, MAX_R={d['VEC_MAX_R']},
MAX_G={d['VEC_MAX_G']}, MAX_P={d['VEC_MAX_P']}, NGHOST={d['VEC_NGHOST']},
ADC_W={d['VEC_ADC_W']}, OUT_W={d['VEC_OUT_W']}.

{file_rows}

Configuration order (`config.hex` line: port):

| line | port |
|---|---|
{cfg_rows}

Result order (line within a channel's block: port, width in bits):

| line | port | bits |
|---|---|---|
{res_rows}

Run with the plain Verilog testbench of the repository (no Python needed):

```
iverilog -g2005 -I <this folder> -o tb.vvp hdl_ref/tb/rx_top_vectors_tb.v \\
    {rtl_files}
vvp tb.vvp +VEC=<this folder>/
```
"""


def _check_out_dir(out: str) -> None:
    """Create ``out`` (with parents) and prove a file can be written in it, or ConfigError."""
    try:
        Path(out).mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise ConfigError(f"--out {out!r}: cannot create the folder ({exc.strerror}); choose "
                          "a writable folder", field="out") from None
    check_writable(Path(out) / "probe", "--out")


def cmd_vectors(args: argparse.Namespace) -> int:
    """``cdma-lidar hdl vectors``: write the files and say where."""
    spec = spec_from_settings(args.set or [])
    if args.seed < 0:
        raise out_of_range("--seed", ">= 0", args.seed)
    _check_out_dir(args.out)
    out = write_vectors(spec, args.columns, args.seed, args.out)
    sys.stdout.write(f"wrote {args.columns} columns of rx_top vectors to {out}\n")
    return 0
