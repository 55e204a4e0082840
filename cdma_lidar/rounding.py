"""The receive chain's output rounding modes: one table for the model, the wire and the RTL.

``out = sat(round(raw / 2**out_shift))`` with ``round`` one of (x = raw / 2**out_shift):

=====  ============  ==============================  =====================
code   name          value                           ties (x = k + 1/2)
=====  ============  ==============================  =====================
0      truncate      floor(x)                        down (towards -inf)
1      half_up       floor(x + 1/2)                  up (towards +inf)
2      convergent    nearest, ties to even           to the even integer
=====  ============  ==============================  =====================

The code is the tuple index: it is the CONFIG wire value and the RTL's ``cfg_rounding``.
"""

from __future__ import annotations

from typing import Literal

__all__ = ["ROUNDING_MODES", "Rounding", "rounding_code"]

#: Rounding mode names; the index of each is its wire and RTL code.
ROUNDING_MODES: tuple[str, ...] = ("truncate", "half_up", "convergent")

Rounding = Literal["truncate", "half_up", "convergent"]


def rounding_code(name: str) -> int:
    """Wire / RTL code of a rounding mode name (raises ValueError for unknown names)."""
    return ROUNDING_MODES.index(name)
