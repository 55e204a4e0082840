"""``cdma-lidar codes ...``: m-sequences, Gold codes, preferred pairs, pair checks, UIDs.

Commands (a contract: users and tests rely on these forms)::

    cdma-lidar codes mseq  --poly 10,3 [--seed BITS] [--chips N] [--format bits|bipolar|hex]
    cdma-lidar codes gold  --poly-u 10,3 --poly-v 10,9,8,6,3,2 --index K
                           [--seed-u BITS] [--seed-v BITS] [--chips N] [--format ...]
    cdma-lidar codes pairs [--degree M] [--verify]
    cdma-lidar codes check --poly-u ... --poly-v ...
    cdma-lidar codes uid   --bits N
    cdma-lidar codes seeds --poly-u ... --poly-v ... --index K   (FPGA register seeds)

Chip output formats (one line on stdout, nothing else):

* ``bits``: one ``0``/``1`` character per chip, chip 0 first.
* ``bipolar``: chips as ``1``/``-1`` (bit 0 -> +1, bit 1 -> -1), separated by spaces.
* ``hex``: chips packed MSB first into bytes (chip 0 is the top bit of the first
  byte), the last byte padded with zero bits, written as lowercase hex, two
  digits per byte (ceil(chips / 8) bytes).

This module holds only the options (no numpy), so ``codes --help`` starts as fast as
Python; the work is in :mod:`cdma_lidar.firmware_model.commands`, imported when a command
runs. Bad arguments raise ConfigError naming the option; the dispatcher prints one
line and exits with status 2.
"""

from __future__ import annotations

import argparse

from cdma_lidar.lazy import later

__all__ = ["FORMATS", "MAX_UID_BITS", "register"]

#: The module that does the commands' work.
COMMANDS_MODULE = "cdma_lidar.firmware_model.commands"

FORMATS = ("bits", "bipolar", "hex")

#: :data:`cdma_lidar.firmware_model.uid.MAX_UID_BITS`, written here so that the help
#: needs no numpy (tests/firmware_model/test_cli_codes.py checks the two agree).
MAX_UID_BITS = 24


def _add_chip_options(p: argparse.ArgumentParser) -> None:
    p.add_argument("--chips", type=int, metavar="N", help="number of chips (default one period)")
    p.add_argument("--format", choices=FORMATS, default="bits",
                   help="bits: 0/1 chars; bipolar: 1/-1; hex: MSB-first packed bytes")


def _add_pair_options(p: argparse.ArgumentParser) -> None:
    p.add_argument("--poly-u", required=True, metavar="EXPS", help="u polynomial, e.g. 11,2")
    p.add_argument("--poly-v", required=True, metavar="EXPS", help="v polynomial, e.g. 11,8,5,2")


def register(subparsers: argparse._SubParsersAction) -> None:
    """Add the ``codes`` command and its subcommands to the ``cdma-lidar`` parser."""
    codes = subparsers.add_parser(
        "codes", help="m-sequences, Gold codes, preferred pairs, UIDs",
        description="Bit-exact code generator (Fibonacci LFSR, stage 1 first seeds).")
    sub = codes.add_subparsers(dest="codes_command", metavar="KIND")
    sub.required = True

    p = sub.add_parser("mseq", help="chips of an m-sequence")
    p.add_argument("--poly", required=True, metavar="EXPS", help="exponents, e.g. 10,3")
    p.add_argument("--seed", metavar="BITS", help="seed bits, stage 1 first (default all ones)")
    _add_chip_options(p)
    p.set_defaults(func=later("cmd_mseq", COMMANDS_MODULE))

    p = sub.add_parser("gold", help="chips of one Gold family member")
    _add_pair_options(p)
    p.add_argument("--index", required=True, type=int, metavar="K",
                   help="member: 0..N-1 u^v delayed by K, N is u, N+1 is v")
    p.add_argument("--seed-u", metavar="BITS", help="u seed, stage 1 first (default all ones)")
    p.add_argument("--seed-v", metavar="BITS", help="v seed, stage 1 first (default all ones)")
    _add_chip_options(p)
    p.set_defaults(func=later("cmd_gold", COMMANDS_MODULE))

    p = sub.add_parser("pairs", help="verified preferred pairs")
    p.add_argument("--degree", type=int, metavar="M", help="only this degree (5..20, not 4k)")
    p.add_argument("--verify", action="store_true",
                   help="recompute each pair's cross-correlation now (exit 1 if one fails)")
    p.set_defaults(func=later("cmd_pairs", COMMANDS_MODULE))

    p = sub.add_parser("check", help="cross-correlation values of a pair")
    _add_pair_options(p)
    p.set_defaults(func=later("cmd_check", COMMANDS_MODULE))

    p = sub.add_parser("uid", help="UID necklaces of N bits and u(N)")
    p.add_argument("--bits", required=True, type=int, metavar="N", help=f"1..{MAX_UID_BITS}")
    p.set_defaults(func=later("cmd_uid", COMMANDS_MODULE))

    p = sub.add_parser("seeds", help="FPGA register seeds for one Gold member")
    _add_pair_options(p)
    p.add_argument("--index", required=True, type=int, metavar="K", help="member 0..N+1")
    p.set_defaults(func=later("cmd_seeds", COMMANDS_MODULE))

