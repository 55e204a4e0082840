"""The one integer-range check behind every public entry point.

Configuration keys, wire fields, CLI options and model parameters all say the same
thing when an integer is out of range: ``<field> must be an integer in lo..hi, not v``.
``bool`` is refused (``True`` is an ``int`` to Python, never a count to us); numpy
integers are accepted.
"""

from __future__ import annotations

import numpy as np

from cdma_lidar.errors import ConfigError, out_of_range

__all__ = ["check_int", "is_int"]


def is_int(value: object) -> bool:
    """True for Python and numpy integers, False for ``bool`` and everything else."""
    return isinstance(value, int | np.integer) and not isinstance(value, bool | np.bool_)


def check_int(field: str, value: object, lo: int, hi: int,
              cls: type[ConfigError] = ConfigError) -> int:
    """Return ``value`` as an ``int`` if it is an integer in ``lo..hi`` (both inclusive).

    Raises ``cls`` (a :class:`ConfigError`; the protocol's encoders pass ``FieldError``)
    naming ``field`` and the range otherwise.
    """
    if not is_int(value) or not lo <= int(value) <= hi:  # type: ignore[call-overload]
        raise out_of_range(field, f"an integer in {lo}..{hi}", value, cls)
    return int(value)  # type: ignore[call-overload]
