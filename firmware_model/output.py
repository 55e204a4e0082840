"""What the receive chain reports for one column: :class:`ReceiverOutput`.

Its fields are ``corr`` (the whole gated trace, which stays on the device unless
CAPTURE asks for it) followed by the column record declared in
:mod:`cdma_lidar.column_record`. Both implementations in
:mod:`cdma_lidar.firmware_model.receiver` return this class, and the virtual board
packs it into a COLUMN_RESULT.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from cdma_lidar.firmware_model.snr import snr_xc_db

__all__ = ["FIELDS", "ReceiverOutput", "saturated_flags"]


@dataclass(frozen=True, eq=False)
class ReceiverOutput:
    """Integers the chain reports for one column, one row per channel (K channels).

    ``corr`` is the gated trace (receiver only); the other fields, in order, are the
    column record (:data:`cdma_lidar.column_record.RECORD`, which gives each one's
    allowed values and wire encoding; a test checks the two lists agree). Lags are in
    samples, -1 where there is no peak; ``out`` values in LSB of the ``out_bits`` word.
    """

    #: (K, G) ``out`` over the gate, j = 0..G-1
    corr: NDArray[np.int64]
    #: (K,) [samples] lag of the strongest peak; -1: no eligible lag
    peak_lag: NDArray[np.int64]
    #: (K,) [out LSB] scaled correlation out at peak_lag
    peak: NDArray[np.int64]
    #: (K, 2) [out LSB] out at peak_lag-1, peak_lag+1
    neighbours: NDArray[np.int64]
    #: (K,) [lags] gate lags in the noise floor
    noise_count: NDArray[np.int64]
    #: (K,) [out LSB] sum of out over the noise lags
    noise_sum: NDArray[np.int64]
    #: (K,) [out LSB^2] sum of out^2 over the noise lags (an object array of Python
    #: integers when ``Widths.wide_sumsq``)
    noise_sumsq: NDArray[np.int64]
    #: (K, n) sign of each period's raw correlation at peak_lag
    uid_signs: NDArray[np.int8]
    #: (K,) observed UID: bit p set where period p's sign is -1
    uid_observed: NDArray[np.int64]
    #: (K,) no sign is 0 and uid_observed == uid
    uid_match: NDArray[np.bool_]
    #: (K,) peak is at a rail of out_bits (it may have been clipped, so peak_lag can sit
    #: early on a plateau): :func:`saturated_flags`
    saturated: NDArray[np.bool_]
    #: (K, P-1) [samples] lags of peaks 2..P; -1: no such peak
    extra_lag: NDArray[np.int64]
    #: (K, P-1) [out LSB] out at peaks 2..P
    extra_peak: NDArray[np.int64]
    #: (K, P-1, n) signs of each period at peaks 2..P
    extra_signs: NDArray[np.int8]

    def snr_db(self) -> NDArray[np.float64]:
        """SNR_XC in dB per channel (:func:`cdma_lidar.firmware_model.snr.snr_xc_db`)."""
        return snr_xc_db(self.peak, self.noise_count, self.noise_sum, self.noise_sumsq)

    def mismatches(self, other: ReceiverOutput) -> list[str]:
        """Names of the fields whose values, shapes or dtypes differ from ``other``."""
        bad = []
        for f in dataclasses.fields(self):
            a, b = getattr(self, f.name), getattr(other, f.name)
            if a.dtype != b.dtype or a.shape != b.shape or not np.array_equal(a, b):
                bad.append(f.name)
        return bad

    def same_as(self, other: ReceiverOutput) -> bool:
        """True when every field is bit-identical (values, shapes and dtypes)."""
        return not self.mismatches(other)


def saturated_flags(peak_lag: ArrayLike, peak: ArrayLike, out_bits: int) -> NDArray[np.bool_]:
    """The record's ``saturated`` field: a peak exists and its ``out`` word is at a rail.

    ``out`` saturates to -2^(out_bits-1) .. 2^(out_bits-1)-1 (docs/firmware.md section 3);
    a peak at either end may have been clipped, and then every lag of the plateau
    ties and the search reports the lowest gate index: the lag can be early. An
    exact value at the rail is flagged too (the word cannot tell them apart).
    Elementwise over any shape of ``peak_lag``/``peak`` (lag -1: no peak).
    """
    top = (1 << (int(out_bits) - 1)) - 1
    p = np.asarray(peak, dtype=np.int64)
    return (np.asarray(peak_lag) >= 0) & ((p >= top) | (p <= -top - 1))


#: Field names of :class:`ReceiverOutput` in order: ``corr``, then the column record's.
FIELDS: tuple[str, ...] = tuple(f.name for f in dataclasses.fields(ReceiverOutput))
