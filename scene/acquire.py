"""Render and receive: the one acquisition path of the virtual device and every study.

::

    settings, powers -> Instrument.render_sums -> (B, n, N S) sums -> receiver.from_accumulators
                        (echoes, noise, ADC,                        -> B ReceiverOutput
                         the drawn sums)

:func:`acquire` renders a batch of columns (or calibration shots) and hands their
repetition sums to a receiver: the virtual board (``cdma_lidar.virtual.board``), the
trade-off study and every study frame (``cdma_lidar.study.simulate``) call it, so a
study frame and a device scan of the same scene, seed, frame id, settings and power
are the same numbers. The receiver is passed in: anything with the batch interface
``from_accumulators((B, n, N S) integers) -> list[ReceiverOutput]``
(:class:`cdma_lidar.firmware_model.receiver.FastReceiver`, or an RTL model of it).

:func:`receiver_config` is the receive chain's configuration of an instrument (the
device's boot configuration and every study's), :func:`boot_power_codes` the device's
boot power matrix (1/65535 of ``max_pixel_power_w``, within the eye-safety cap) and
:func:`power_w_of_codes` its watts.
"""

from __future__ import annotations

import time
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from fractions import Fraction
from typing import Protocol

import numpy as np
from numpy.typing import ArrayLike, NDArray

from cdma_lidar.firmware_model.gold import gold_codes
from cdma_lidar.firmware_model.output import ReceiverOutput
from cdma_lidar.firmware_model.receiver import ReceiverConfig
from cdma_lidar.firmware_model.snr import snr_q8
from cdma_lidar.scene.instrument import Instrument, RenderSettings
from cdma_lidar.scene.model import InstrumentSpec

__all__ = [
    "BATCH_VALUES",
    "Acquisition",
    "BatchReceiver",
    "acquire",
    "acquire_frame",
    "boot_power_codes",
    "clock_us",
    "column_batches",
    "out_bits_for_gate",
    "power_limits_uw",
    "power_w_of_codes",
    "receiver_config",
    "within_cap",
]

#: Columns rendered and received together: at most this many accumulator values (n N S
#: per column; int64 in the receive chain, 16 MB), so a frame of paper-scene1 (160
#: columns of 8188) is one batch. The receive chain's matrix kernel pays a fixed cost per
#: call (a batch of 4 columns costs 2 ms a column, one of 160 0.35 ms), so batches are as
#: large as memory allows. The values do not depend on the batches (each column has its
#: own noise generator).
BATCH_VALUES = 1 << 21


class BatchReceiver(Protocol):
    """A receive chain that finishes a batch of columns from their repetition sums."""

    def from_accumulators(self, acc: ArrayLike) -> list[ReceiverOutput]:
        """(B, n, N S) integer repetition sums -> B outputs."""
        ...


@dataclass(frozen=True)
class Acquisition:
    """What :func:`acquire` gives: the receiver's outputs, which sums the fidelity level
    drew directly (the others were rendered repetition by repetition, :meth:`Instrument.
    render_sums` with ``complete``), and the process CPU time (s) of each step."""

    outputs: list[ReceiverOutput]
    drawn: NDArray[np.bool_]
    render_cpu_s: float
    receive_cpu_s: float


def acquire(inst: Instrument, receiver: BatchReceiver, settings: RenderSettings, frame: int,
            columns: Sequence[int], powers: Sequence[NDArray[np.float64]], *,
            calibration: bool = False, out: NDArray[np.int32] | None = None) -> Acquisition:
    """Render ``columns`` (``calibration``: calibration shots) of frame ``frame`` and receive them.

    ``powers``: each column's laser power (K,) W. ``out``: the (B, n, N S) int32 array the
    sums are written into (a caller that acquires batch after batch passes the same one;
    the receiver keeps nothing of it). Every column's sum is its own (seeded by scene
    seed, frame and column), whatever batch it comes in.
    """
    t0 = time.process_time()
    sums, drawn = inst.render_sums(columns, settings, frame, powers, calibration=calibration,
                                   complete=True, out=out)
    t1 = time.process_time()
    outputs = receiver.from_accumulators(sums)
    return Acquisition(outputs, drawn, t1 - t0, time.process_time() - t1)


def acquire_frame(inst: Instrument, receiver: BatchReceiver, frame: int,
                  power_w: NDArray[np.float64], settings: RenderSettings | None = None
                  ) -> list[ReceiverOutput]:
    """Every column of frame ``frame`` through :func:`acquire`, batch by batch as the
    virtual device scans it: ``power_w`` (K, C) laser power (W); ``settings`` default the
    scene's. Returns the C outputs in column order."""
    s = settings or RenderSettings.from_spec(inst.spec)
    outputs: list[ReceiverOutput] = []
    for cols in column_batches(0, inst.columns, s.frame_samples):
        outputs += acquire(inst, receiver, s, frame, cols, [power_w[:, c] for c in cols]).outputs
    return outputs


def column_batches(first: int, count: int, column_values: int = 1) -> Iterator[list[int]]:
    """Consecutive index lists covering first..first+count-1, each at most
    BATCH_VALUES values of ``column_values`` (and at least one column)."""
    size = max(1, BATCH_VALUES // max(1, column_values))
    for pos in range(first, first + count, size):
        yield list(range(pos, min(pos + size, first + count)))


def clock_us(chips: int, chip_rate_hz: float) -> int:
    """The device clock's timestamp (us, 32 bits) after ``chips`` chips since power-up:
    the floor of ``chips / chip_rate`` in microseconds, in exact integers (the rate's own
    binary value as a fraction), wrapped to 32 bits. A column of settings ``s`` takes
    ``s.averages * s.frame_chips`` chips."""
    rate = Fraction(chip_rate_hz)
    return (chips * 1_000_000 * rate.denominator // rate.numerator) & 0xFFFFFFFF


def out_bits_for_gate(gate_len: int) -> int:
    """Widest output whose noise sum of squares fits 63 bits: 2 b - 2 + bitlen(gate) <= 63
    (8 to 32 bits)."""
    return max(8, min(32, (65 - int(gate_len).bit_length()) // 2))


def receiver_config(inst: Instrument, settings: RenderSettings | None = None, *,
                    gate: tuple[int, int] | None = None, peaks: int = 1
                    ) -> tuple[ReceiverConfig, NDArray[np.uint8]]:
    """(the receive chain's configuration, the (K, N) uint8 Gold codes) of ``inst`` under
    ``settings`` (default: the scene's): the device's boot configuration and every study's.

    ``gate`` (start, length) in samples defaults to :meth:`Instrument.default_gate`; the
    output is :func:`out_bits_for_gate` wide with no shift (every width then fits: the
    noise's sum of squares in 63 bits); the interference cancellation is the scene's
    (``cancel_rounds``, ``cancel_snr_db`` as the chain's Q8 power ratio); the other fields
    are ReceiverConfig's defaults.
    """
    spec = inst.spec
    s = settings or RenderSettings.from_spec(spec)
    start, length = gate if gate is not None else inst.default_gate(s.samples_per_chip)
    cfg = ReceiverConfig(adc_bits=spec.adc_bits, samples_per_chip=s.samples_per_chip,
                         averages=s.averages, uid_bits=s.uid_bits, uid=s.uid,
                         gate_start=start, gate_len=length, out_shift=0,
                         out_bits=out_bits_for_gate(length), peaks=peaks,
                         cancel_rounds=spec.cancel_rounds,
                         cancel_snr_q8=snr_q8(spec.cancel_snr_db))
    return cfg, gold_codes(s.poly_u, s.poly_v, s.code_index, field="code_index")


def boot_power_codes(inst: Instrument) -> NDArray[np.uint16]:
    """(K, C) power matrix the device boots with: the scene's laser power in 1/65535 of
    ``max_pixel_power_w``, rounded, then lowered where a column would pass the eye-safety
    cap ``total_power_cap_w`` (:func:`within_cap`, exact integers)."""
    spec = inst.spec
    codes = np.clip(np.round(inst.default_power_w / spec.max_pixel_power_w * 65535), 0, 65535)
    pixel_uw, cap_uw = power_limits_uw(spec)
    return within_cap(codes.astype(np.int64), pixel_uw, cap_uw).astype(np.uint16)


def power_limits_uw(spec: InstrumentSpec) -> tuple[int, int]:
    """(the largest pixel power, the cap on a column's total), whole µW."""
    return round(spec.max_pixel_power_w * 1e6), round(spec.total_power_cap_w * 1e6)


def power_w_of_codes(spec: InstrumentSpec, codes: NDArray[np.integer]) -> NDArray[np.float64]:
    """Laser power (W) of power codes (1/65535 of ``max_pixel_power_w``)."""
    return codes.astype(np.float64) / 65535 * spec.max_pixel_power_w


def within_cap(codes: NDArray[np.int64], pixel_uw: int, cap_uw: int) -> NDArray[np.int64]:
    """``codes`` lowered where needed so every column sum is within the cap (exact integers).

    A column over ``cap_uw * 65535 / pixel_uw`` codes loses the excess from its largest
    codes, one code at a time, so rounding never leaves the boot matrix over the cap.
    """
    out = codes.copy()
    limit = cap_uw * 65535 // max(pixel_uw, 1)
    for c in np.flatnonzero(out.sum(axis=0) > limit):
        excess = int(out[:, c].sum()) - limit
        while excess > 0:
            k = int(np.argmax(out[:, c]))
            step = min(excess, int(out[k, c]))
            out[k, c] -= step
            excess -= step
    return out
