"""The work of ``cdma-lidar codes ...``: its options and output formats are in
:mod:`cdma_lidar.firmware_model.cli`, which imports this module when a command runs.

Bad arguments raise ConfigError naming the option; the dispatcher prints one
line and exits with status 2.
"""

from __future__ import annotations

import argparse
import logging
import sys

import numpy as np

from cdma_lidar.checks import check_int
from cdma_lidar.errors import out_of_range
from cdma_lidar.firmware_model.cli import FORMATS
from cdma_lidar.firmware_model.gold import (
    check_pair,
    family_size,
    gold_code,
    gold_seeds,
    t_value,
    xcorr_values,
)
from cdma_lidar.firmware_model.lfsr import (
    check_primitive,
    format_poly,
    mseq,
    parse_poly,
    parse_seed,
)
from cdma_lidar.firmware_model.pairs import pair_table
from cdma_lidar.firmware_model.uid import MAX_UID_BITS, necklace_count, necklaces, uid_to_str
from cdma_lidar.poly import Poly

__all__ = ["cmd_check", "cmd_gold", "cmd_mseq", "cmd_pairs", "cmd_seeds", "cmd_uid",
           "format_chips"]

log = logging.getLogger(__name__)

#: Longest chip request the CLI accepts (the output is one line).
MAX_CHIPS = 1 << 26

#: Largest degree ``codes check`` correlates (degree 24: about 0.9 GB and 5 s).
MAX_CHECK_DEGREE = 24


def format_chips(bits: np.ndarray, fmt: str) -> str:
    """Render chip bits as one line (without newline) in ``bits``, ``bipolar`` or ``hex``."""
    bits = np.asarray(bits, dtype=np.uint8)
    if fmt == "bits":
        return (bits + ord("0")).tobytes().decode("ascii")
    if fmt == "bipolar":
        return " ".join(np.where(bits == 0, "1", "-1").tolist())
    if fmt == "hex":
        return np.packbits(bits).tobytes().hex()
    raise out_of_range("--format", "one of " + ", ".join(FORMATS), fmt)


def _poly(text: str, field: str) -> Poly:
    return check_primitive(parse_poly(text, field=field), field=field)


def _pair(args: argparse.Namespace) -> tuple[Poly, Poly]:
    pu = _poly(args.poly_u, "--poly-u")
    pv = _poly(args.poly_v, "--poly-v")
    return check_pair(pu, pv, field_u="--poly-u", field_v="--poly-v")


def _chips(value: int | None, degree: int) -> int:
    """--chips checked against MAX_CHIPS; default one period, which must itself fit."""
    if value is None:
        period = (1 << degree) - 1
        if period > MAX_CHIPS:
            raise out_of_range("--chips", f"given (1..{MAX_CHIPS}) for degree {degree} "
                               f"(one period is 2^{degree} - 1 = {period} chips)", value)
        return period
    return check_int("--chips", value, 1, MAX_CHIPS)


def _write(line: str) -> None:
    sys.stdout.write(line + "\n")


def cmd_mseq(args: argparse.Namespace) -> int:
    """``codes mseq``: the first N chips of the Fibonacci m-sequence."""
    poly = _poly(args.poly, "--poly")
    seed = parse_seed(args.seed, poly[0], field="--seed") if args.seed is not None else None
    _write(format_chips(mseq(poly, seed, _chips(args.chips, poly[0])), args.format))
    return 0


def _index(value: int, poly: Poly) -> int:
    return check_int("--index", value, 0, 1 << poly[0])  # 0..N+1, N = 2^m - 1


def cmd_gold(args: argparse.Namespace) -> int:
    """``codes gold``: member K of the Gold family of (u, v)."""
    pu, pv = _pair(args)
    m = pu[0]
    seed_u = None if args.seed_u is None else parse_seed(args.seed_u, m, field="--seed-u")
    seed_v = None if args.seed_v is None else parse_seed(args.seed_v, m, field="--seed-v")
    index = _index(args.index, pu)
    code = gold_code(pu, pv, index, chips=_chips(args.chips, m), seed_u=seed_u,
                     seed_v=seed_v)
    _write(format_chips(code, args.format))
    return 0


def cmd_seeds(args: argparse.Namespace) -> int:
    """``codes seeds``: register seeds (stage 1 first) that produce member K from chip 0."""
    pu, pv = _pair(args)
    seed_u, seed_v = gold_seeds(pu, pv, _index(args.index, pu))
    _write(f"{seed_u} {seed_v}")
    return 0


def cmd_pairs(args: argparse.Namespace) -> int:
    """``codes pairs``: the verified preferred pairs (optionally re-verified now)."""
    entries = pair_table(args.degree, field="--degree")
    header = f"{'degree':>6}  {'poly_u':<18} {'poly_v':<30} {'t(m)':>5} {'codes':>8}"
    if args.verify:
        header += "  preferred"
    _write(header + "  source")
    failed = 0
    for e in entries:
        line = (f"{e.degree:>6}  {format_poly(e.u):<18} {format_poly(e.v):<30} "
                f"{t_value(e.degree):>5} {family_size(e.degree):>8}")
        if args.verify:
            t = t_value(e.degree)
            ok = set(xcorr_values(e.u, e.v)) <= {-1, -t, t - 2}
            failed += not ok
            line += f"  {'yes' if ok else 'NO':<9}"
        _write(line + "  " + e.source)
    return 1 if failed else 0


def cmd_check(args: argparse.Namespace) -> int:
    """``codes check``: cross-correlation values of u and v, their counts, preferred or not."""
    pu, pv = _pair(args)
    m = pu[0]
    if m > MAX_CHECK_DEGREE:
        raise out_of_range("--poly-u", f"of degree 2..{MAX_CHECK_DEGREE} (the check "
                           "correlates whole periods in memory)", format_poly(pu))
    t = t_value(m)
    values = xcorr_values(pu, pv)
    allowed = {-1, -t, t - 2}
    preferred = pu != pv and set(values) <= allowed
    _write(f"degree {m}, N = {(1 << m) - 1} chips, t(m) = {t}, "
           f"preferred values {{-1, {-t}, {t - 2}}}")
    _write(f"{'value':>8} {'count':>8}")
    for value, count in values.items():
        _write(f"{value:>8} {count:>8}")
    reason = "" if m % 4 else " (degrees that are multiples of 4 have no preferred pairs)"
    _write(f"preferred: {'yes' if preferred else 'no'}{'' if preferred else reason}")
    return 0


def cmd_uid(args: argparse.Namespace) -> int:
    """``codes uid``: the n-bit necklaces (canonical UIDs) and u(n)."""
    n = args.bits
    if not 1 <= n <= MAX_UID_BITS:
        raise out_of_range("--bits", f"an integer in 1..{MAX_UID_BITS}", n)
    _write(f"{'uid':>8}  bits (period 0 first)")
    for value in necklaces(n):
        _write(f"{value:>8}  {uid_to_str(value, n)}")
    _write(f"u({n}) = {necklace_count(n)}")
    return 0


