"""The ADC: integer analog values on a fine grid -> signed ``adc_bits`` codes.

The analog input arrives as an integer on a grid ``frac_bits`` finer than the
ADC's LSB, ``analog_lsb = analog_fine / 2**frac_bits``, so the model stays
bit-exact (the scene code converts its float signal to that grid first)::

    code = clip((analog_fine + 2**(frac_bits - 1)) >> frac_bits,      # round half up
                -2**(adc_bits - 1), 2**(adc_bits - 1) - 1)            # saturate

``>>`` is an arithmetic shift (floor), so the rounding is floor(x + 1/2): ties go
towards plus infinity. With ``frac_bits = 0`` the input is already in LSBs and
is only clipped. Values beyond full scale clip to the end codes (no wrap).
See docs/firmware.md, section 6.
"""

from __future__ import annotations

import logging

import numpy as np
from numpy.typing import ArrayLike, NDArray

from cdma_lidar.errors import out_of_range

__all__ = ["ADC_BITS_RANGE", "FRAC_BITS_RANGE", "adc_limits", "quantise"]

log = logging.getLogger(__name__)

ADC_BITS_RANGE = (8, 16)
FRAC_BITS_RANGE = (0, 40)


def adc_limits(adc_bits: int) -> tuple[int, int]:
    """Return the (lowest, highest) code of a signed ``adc_bits`` ADC."""
    _check_int("adc_bits", adc_bits, *ADC_BITS_RANGE)
    return -(1 << (adc_bits - 1)), (1 << (adc_bits - 1)) - 1


def quantise(analog_fine: ArrayLike, frac_bits: int, adc_bits: int) -> NDArray[np.int16]:
    """Quantise integer analog values (units of 2**-frac_bits LSB) to ADC codes.

    Parameters
    ----------
    analog_fine:
        Integer array (any shape), the analog value in units of 2**-frac_bits
        ADC LSB. Must fit in int64.
    frac_bits:
        Extra fractional bits of the input grid, 0..40.
    adc_bits:
        ADC width b, 8..16.

    Returns
    -------
    Signed codes in [-2**(b-1), 2**(b-1) - 1] as int16, same shape as the input:
    rounded half up (floor(x + 1/2)), then clipped.
    """
    _check_int("frac_bits", frac_bits, *FRAC_BITS_RANGE)
    lo, hi = adc_limits(adc_bits)
    x = np.asarray(analog_fine)
    if x.dtype.kind not in "iu":
        raise out_of_range("analog_fine", "an integer array", f"dtype {x.dtype}")
    if x.dtype.kind == "u" and x.dtype.itemsize >= 8:
        if x.size and int(x.max()) > np.iinfo(np.int64).max:
            raise out_of_range("analog_fine", "values that fit in int64", int(x.max()))
    x = x.astype(np.int64, copy=False)
    if frac_bits:
        # Clip first (in fine units, generously outside full scale) so the
        # rounding offset cannot overflow int64; the result is unchanged.
        big = (hi + 2) << frac_bits
        x = np.clip(x, -big, big)
        x = (x + (1 << (frac_bits - 1))) >> frac_bits
    return np.clip(x, lo, hi).astype(np.int16)


def _check_int(field: str, value: object, lo: int, hi: int) -> None:
    if isinstance(value, bool) or not isinstance(value, int | np.integer):
        raise out_of_range(field, f"an integer in {lo}..{hi}", value)
    if not lo <= int(value) <= hi:
        raise out_of_range(field, f"an integer in {lo}..{hi}", value)
