"""The ADC: analog values on a fine grid -> signed ``adc_bits`` codes.

The analog input arrives on a grid ``frac_bits`` finer than the ADC's LSB,
``analog_lsb = analog_fine / 2**frac_bits``, so the model stays bit-exact (the
scene code converts its float signal to that grid first)::

    code = clip((analog_fine + 2**(frac_bits - 1)) >> frac_bits,      # round half up
                -2**(adc_bits - 1), 2**(adc_bits - 1) - 1)            # saturate

``>>`` is an arithmetic shift (floor), so the rounding is floor(x + 1/2): ties go
towards plus infinity. With ``frac_bits = 0`` the input is already in LSBs and
is only clipped. Values beyond full scale clip to the end codes (no wrap).

``analog_fine`` is an integer array; with ``float_input=True`` it may be a float
array instead, first rounded to the fine grid by ``rint`` (nearest, ties to even):
``quantise(x, F, b, float_input=True) == quantise(rint(x).astype(int64), F, b)``
bit for bit, infinities clipping to the end codes. See docs/firmware.md, section 6.
"""

from __future__ import annotations

import logging

import numpy as np
from numpy.typing import ArrayLike, NDArray

from cdma_lidar.checks import check_int
from cdma_lidar.errors import out_of_range

__all__ = ["ADC_BITS_RANGE", "FRAC_BITS_RANGE", "adc_limits", "quantise"]

log = logging.getLogger(__name__)

ADC_BITS_RANGE = (8, 16)
FRAC_BITS_RANGE = (0, 40)

#: float64 holds every integer up to 2**53; the float path needs the clip point below it.
_FLOAT_EXACT = 1 << 52


def adc_limits(adc_bits: int) -> tuple[int, int]:
    """Return the (lowest, highest) code of a signed ``adc_bits`` ADC."""
    check_int("adc_bits", adc_bits, *ADC_BITS_RANGE)
    return -(1 << (adc_bits - 1)), (1 << (adc_bits - 1)) - 1


def quantise(analog_fine: ArrayLike, frac_bits: int, adc_bits: int, *,
             float_input: bool = False, overwrite_input: bool = False) -> NDArray[np.int16]:
    """Quantise analog values (units of 2**-frac_bits LSB) to ADC codes.

    Parameters
    ----------
    analog_fine:
        The analog value in units of 2**-frac_bits ADC LSB, any shape: an integer
        array that fits in int64, or with ``float_input`` a float array.
    frac_bits:
        Extra fractional bits of the input grid, 0..40.
    adc_bits:
        ADC width b, 8..16.
    float_input:
        Accept a float array and round it to the fine grid first with ``rint``
        (nearest, ties to even), then quantise as above. Computed in float64 (five
        passes, exact: every value up to the clip point is an integer below 2**52)
        when ``(2**(b-1) + 1) * 2**frac_bits <= 2**52``, in int64 otherwise; both
        give ``quantise(rint(x).astype(int64), ...)`` bit for bit, and +-inf clip to
        the end codes. NaN is not checked (its code is undefined).
    overwrite_input:
        With ``float_input`` and a float64 array: use it as the work buffer (its
        contents are destroyed), saving an allocation of the input's size.

    Returns
    -------
    Signed codes in [-2**(b-1), 2**(b-1) - 1] as int16, same shape as the input:
    rounded half up (floor(x + 1/2)), then clipped.
    """
    check_int("frac_bits", frac_bits, *FRAC_BITS_RANGE)
    lo, hi = adc_limits(adc_bits)
    if float_input:
        return _quantise_float(analog_fine, frac_bits, lo, hi, overwrite_input)
    x = np.asarray(analog_fine)
    if x.dtype.kind not in "iu":
        raise out_of_range("analog_fine", "an integer array", f"dtype {x.dtype}")
    if x.dtype.kind == "u" and x.dtype.itemsize >= 8:
        if x.size and int(x.max()) > np.iinfo(np.int64).max:
            raise out_of_range("analog_fine", "values that fit in int64", int(x.max()))
    return _quantise_int(x.astype(np.int64, copy=False), frac_bits, lo, hi)


def _quantise_int(x: NDArray[np.int64], frac_bits: int, lo: int, hi: int) -> NDArray[np.int16]:
    if frac_bits:
        # Clip first (in fine units, generously outside full scale) so the
        # rounding offset cannot overflow int64; the result is unchanged.
        big = (hi + 2) << frac_bits
        x = np.clip(x, -big, big)
        x = (x + (1 << (frac_bits - 1))) >> frac_bits
    return np.clip(x, lo, hi).astype(np.int16)


def _quantise_float(analog_fine: ArrayLike, frac_bits: int, lo: int, hi: int,
                    overwrite: bool) -> NDArray[np.int16]:
    """``_quantise_int(rint(x))`` for a float array x, in float64 where that is exact.

    With ``x = rint(fine)`` an integer-valued float64, ``(x + 2**(F-1)) >> F`` is
    ``floor((x + 2**(F-1)) * 2**-F)``, every step exact while ``|x| < 2**52``. Each step
    is monotone, so when the clip point ``(hi + 1) 2**F`` lies below 2**52 every larger
    (or infinite) value still clips to the same end code.
    """
    x = np.asarray(analog_fine)
    if x.dtype.kind != "f":
        raise out_of_range("analog_fine", "a float array (float_input=True)", f"dtype {x.dtype}")
    if (hi + 1) << frac_bits > _FLOAT_EXACT:
        fine = np.clip(np.rint(x.astype(np.float64)), -2.0**62, 2.0**62).astype(np.int64)
        return _quantise_int(fine, frac_bits, lo, hi)
    if overwrite and x.dtype == np.float64:
        fine = x
        np.rint(fine, out=fine)
    else:
        fine = np.rint(x, dtype=np.float64)
    fine += float(1 << frac_bits >> 1)
    fine *= 1.0 / (1 << frac_bits)
    np.floor(fine, out=fine)
    np.clip(fine, lo, hi, out=fine)
    return fine.astype(np.int16)
