"""Stimuli for co-simulating ``rx_chain``: ADC columns with a coded echo, noise and extremes.

Everything is seeded (``numpy.random.Generator``) and returns plain integer
arrays in the sample order of docs/firmware.md: repetition r, then UID period p,
then sample i (``t = (r * n + p) * NS + i``). The echo is what our own emitter
sends: Gold member chips, period p inverted when bit p of the emitter's UID is
1, each chip held for S samples, delayed circularly by ``delay`` samples.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from cdma_lidar.errors import out_of_range

__all__ = ["adc_range", "echo_column", "full_scale_column"]


def adc_range(adc_bits: int) -> tuple[int, int]:
    """Smallest and largest code of a signed ``adc_bits`` ADC."""
    if not 2 <= adc_bits <= 32:
        raise out_of_range("adc_bits", "2..32", adc_bits)
    return -(1 << (adc_bits - 1)), (1 << (adc_bits - 1)) - 1


def _echo_period_wave(code: NDArray[np.uint8], spc: int, delay: int) -> NDArray[np.int64]:
    """One period of the bipolar code held S samples per chip, delayed by ``delay`` samples."""
    wave = np.repeat(1 - 2 * np.asarray(code, dtype=np.int64), spc)
    return np.roll(wave, delay)


def echo_column(code: NDArray[np.uint8], *, spc: int, averages: int, uid_bits: int,
                tx_uid: int, adc_bits: int, delay: int, amplitude: float,
                noise_rms: float, rng: np.random.Generator,
                offset: float = 0.0) -> NDArray[np.int64]:
    """``averages * uid_bits * N * spc`` ADC codes of one echo plus Gaussian noise.

    ``amplitude`` and ``noise_rms`` are in ADC LSB; the analog value is rounded to
    the nearest code (half away from zero, numpy ``rint`` is half to even: either
    is fine for a stimulus) and clipped to the ADC range, so large amplitudes give
    full-scale clipped inputs.
    """
    wave = _echo_period_wave(code, spc, delay)
    ns = wave.size
    signs = np.array([-1 if tx_uid >> p & 1 else 1 for p in range(uid_bits)], dtype=np.int64)
    clean = (signs[None, :, None] * wave[None, None, :]).astype(np.float64) * amplitude
    clean = np.broadcast_to(clean, (averages, uid_bits, ns))
    analog = clean + offset + rng.normal(0.0, noise_rms, size=(averages, uid_bits, ns))
    lo, hi = adc_range(adc_bits)
    return np.clip(np.rint(analog), lo, hi).astype(np.int64).reshape(-1)


def full_scale_column(code: NDArray[np.uint8], *, spc: int, averages: int, uid_bits: int,
                      tx_uid: int, adc_bits: int, delay: int) -> NDArray[np.int64]:
    """The echo at full scale: chip bit 0 -> largest code, bit 1 -> smallest code.

    This drives every accumulator and the correlation to its extreme magnitude
    (the most negative code is one LSB larger in magnitude than the largest).
    """
    lo, hi = adc_range(adc_bits)
    wave = _echo_period_wave(code, spc, delay)
    rows = []
    for p in range(uid_bits):
        w = -wave if tx_uid >> p & 1 else wave
        rows.append(np.where(w > 0, hi, lo))
    period_block = np.concatenate(rows)
    return np.tile(period_block, averages).astype(np.int64)
