"""Physical constants and unit conversions shared by every layer (one speed of light).

Ranges are in metres, delays in seconds; a round trip covers the range twice.
"""

from __future__ import annotations

__all__ = ["SPEED_OF_LIGHT_M_S", "delay_to_range_m", "range_to_delay_s"]

#: Speed of light in vacuum (m/s), exact by the SI definition of the metre.
SPEED_OF_LIGHT_M_S = 299_792_458.0


def range_to_delay_s(range_m: float) -> float:
    """Round-trip delay (s) of an echo from ``range_m`` metres: ``2 R / c``."""
    return 2.0 * range_m / SPEED_OF_LIGHT_M_S


def delay_to_range_m(delay_s: float) -> float:
    """Range (m) of an echo whose round trip took ``delay_s`` seconds: ``c t / 2``."""
    return delay_s * SPEED_OF_LIGHT_M_S / 2.0
