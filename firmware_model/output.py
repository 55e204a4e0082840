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

from cdma_lidar.column_record import record_fields
from cdma_lidar.firmware_model.snr import snr_xc_db

__all__ = ["ReceiverOutput", "saturated_flags"]


@dataclass(frozen=True, eq=False)
@record_fields(after="corr")
class ReceiverOutput:
    """Integers the chain reports for one column, one row per channel (K channels).

    ``corr`` (K, G) int64 is ``out`` over the gate, j = 0..G-1 (receiver only); the
    other fields, one attribute each, are the column record
    (:data:`cdma_lidar.column_record.RECORD`, lags in samples and -1 where there is
    no peak):
    """

    corr: NDArray[np.int64]

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
