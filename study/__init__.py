"""Studies: frames simulated in-process (no link) and, later, sweeps of the speed/accuracy trade.

The top of the stack beside the CLI: may import every layer below it.
"""
