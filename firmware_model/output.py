"""What the receive chain reports for one column: :class:`ReceiverOutput`.

The fields are the receiver's side of the column record; ``corr`` (the whole gated
trace) stays on the device unless CAPTURE asks for it. Both implementations in
:mod:`cdma_lidar.firmware_model.receiver` return this class, and the virtual board
packs it into a COLUMN_RESULT.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np
from cdma_lidar.firmware_model.snr import snr_xc_db
from numpy.typing import NDArray

__all__ = ["ReceiverOutput"]


@dataclass(frozen=True, eq=False)
class ReceiverOutput:
    """Integers the chain reports for one column, one row per channel (K channels).

    corr (K, G) int64          ``out`` over the gate, j = 0..G-1
    peak_lag (K,) int64        lag of the first peak in samples (lag_j, not j); -1 if none
    peak (K,) int64            signed ``out`` at the peak (0 if none)
    neighbours (K, 2) int64    ``out`` at peak_lag - 1 and + 1 (mod N*S)
    noise_count/_sum/_sumsq    noise floor statistics (K,) int64
    uid_signs (K, n) int8      sign of each period's raw correlation at peak_lag
    uid_observed (K,) int64    bit p set where uid_signs[:, p] < 0
    uid_match (K,) bool        no zero sign and uid_observed == uid
    extra_lag/extra_peak (K, P-1) int64, extra_signs (K, P-1, n) int8: later peaks
    """

    corr: NDArray[np.int64]
    peak_lag: NDArray[np.int64]
    peak: NDArray[np.int64]
    neighbours: NDArray[np.int64]
    noise_count: NDArray[np.int64]
    noise_sum: NDArray[np.int64]
    noise_sumsq: NDArray[np.int64]
    uid_signs: NDArray[np.int8]
    uid_observed: NDArray[np.int64]
    uid_match: NDArray[np.bool_]
    extra_lag: NDArray[np.int64]
    extra_peak: NDArray[np.int64]
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
