"""Test vectors for anyone's testbench: ``cdma-lidar hdl vectors``.

Writes ``$readmemh`` files of one ``rx_top`` run (configuration port values, the
ADC samples of C columns, and every output word the model expects: the gate
trace of every channel and every result port), plus ``params.vh`` (the build's
parameters and the file sizes as Verilog defines) and a README naming each
file's layout. The expected words come from :mod:`cdma_lidar.firmware_model`
(the vectorised receiver, bit-identical to the streaming reference); nothing of
the RTL is used to make them. ``hdl_ref/tb/rx_top_vectors_tb.v`` is a plain
Verilog testbench that plays the files into ``rx_top`` and compares (no Python
in the loop)::

    cdma-lidar hdl vectors --set degree=7 --set channels=4 --columns 3 --seed 1 --out vec/
    iverilog -g2005 -I vec -o tb.vvp hdl_ref/tb/rx_top_vectors_tb.v hdl_ref/rtl/*.v
    vvp tb.vvp +VEC=vec/        # prints "rx_top vectors: PASS ..." or "FAIL ..."

``--set`` keys: every field of ``ReceiverConfig`` except ``ghost_windows``
(``ghost=START:LEN`` instead, repeatable through ``ghost2=``), plus ``degree``
(5..11, the preferred pair ``pair`` of that degree), ``channels`` (K),
``lanes`` (L), ``samples_per_clock`` (P_IN, dividing samples_per_chip),
``first_index`` (channel k correlates member first_index + k),
``amplitude`` and ``noise`` (echo and noise in ADC LSB).
"""

from __future__ import annotations

import argparse

from cdma_lidar.lazy import later

__all__ = ["register"]


def register(subparsers: argparse._SubParsersAction) -> None:
    """Add ``cdma-lidar hdl vectors`` to the command-line parser.

    This module's text is the command's help and it imports no numpy, so the help starts
    as fast as Python; :func:`cdma_lidar.hdl_ref.vectors.cmd_vectors` does the work (its
    module imported when the command runs).
    """
    hdl = subparsers.add_parser("hdl", help="reference RTL: test vectors",
                                description="Reference RTL (hdl_ref) tools.")
    sub = hdl.add_subparsers(dest="hdl_command", metavar="KIND")
    sub.required = True
    p = sub.add_parser("vectors", help="$readmemh vectors of an rx_top run for any testbench",
                       description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--set", action="append", metavar="KEY=VALUE",
                   help="configuration value (repeatable), e.g. degree=7 averages=4")
    p.add_argument("--columns", type=int, default=2, metavar="C", help="columns (default 2)")
    p.add_argument("--seed", type=int, default=0, metavar="S", help="stimulus seed")
    p.add_argument("--out", required=True, metavar="DIR", help="output folder")
    p.set_defaults(func=later("cmd_vectors", "cdma_lidar.hdl_ref.vectors"))
