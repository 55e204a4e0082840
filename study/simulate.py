"""Frames straight from the scene's instrument and the receive-chain model, without a link.

The virtual device renders ADC samples with :class:`cdma_lidar.scene.instrument.Instrument` and
runs them through :class:`cdma_lidar.firmware_model.receiver.FastReceiver`; this module does the
same two steps in-process so the host's range pipeline can be measured and tested
on a scene with known truth without the serial protocol in between (benchmarks,
unit tests). Scans for users go through :mod:`cdma_lidar.host.scan` and a real or ``virtual://``
port.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from cdma_lidar.errors import ConfigError
from cdma_lidar.firmware_model.gold import gold_code
from cdma_lidar.firmware_model.receiver import FastReceiver, ReceiverConfig
from cdma_lidar.host.frame import FrameData
from cdma_lidar.host.ranging import RangingConfig, precision_eq27_m
from cdma_lidar.optics.grating import GratingGeometry
from cdma_lidar.scene import load_scene
from cdma_lidar.scene.instrument import Instrument
from cdma_lidar.units import delay_to_range_m

__all__ = [
    "SimulatedScan",
    "eq27_from_configuration",
    "ranging_config",
    "receiver_setup",
    "simulate_frame",
    "smallest_out_shift",
    "true_offset_m",
]


@dataclass
class SimulatedScan:
    """A frame rendered in-process, with the truth and the nominal parameters the host knows.

    ``true_offset_m`` is the instrument's hidden system delay as a range (m), i.e. what
    a perfect calibration would find.
    """

    frame: FrameData
    truth_range_m: NDArray[np.float64]
    ranging: RangingConfig
    geometry: GratingGeometry
    wavelengths_m: NDArray[np.float64]
    rotations_deg: NDArray[np.float64]
    true_offset_m: float


def smallest_out_shift(cfg: ReceiverConfig, n_chips: int) -> ReceiverConfig:
    """``cfg`` with the smallest ``out_shift`` whose derived widths fit (noise_sumsq in int64).

    A long code, many samples per chip or many repetitions make the 32-bit output's
    noise accumulator too wide at shift 0; the device would be configured the same way.
    Raises the receiver's ConfigError when no shift fits.
    """
    for shift in range(63):
        try:
            cfg.replace(out_shift=shift).widths(n_chips)
        except ConfigError:
            continue
        return cfg.replace(out_shift=shift)
    cfg.widths(n_chips)  # raises the receiver's own error
    return cfg


def receiver_setup(inst: Instrument, *, peaks: int = 1, gate: tuple[int, int] | None = None
                   ) -> tuple[ReceiverConfig, NDArray[np.uint8]]:
    """The receive-chain configuration and Gold codes (K, N) the instrument's device uses.

    ``gate`` (start, length) in samples defaults to the instrument's
    :meth:`~cdma_lidar.scene.instrument.Instrument.default_gate`; the output shift is the
    smallest that fits (:func:`smallest_out_shift`).
    """
    spec = inst.spec
    gate_start, gate_len = gate if gate is not None else inst.default_gate()
    codes = np.stack([gold_code(spec.poly_u, spec.poly_v, k) for k in spec.code_indices])
    cfg = ReceiverConfig(adc_bits=spec.adc_bits,
                         samples_per_chip=spec.samples_per_chip,
                         averages=spec.averages, uid_bits=spec.uid_bits, uid=spec.uid,
                         gate_start=gate_start, gate_len=gate_len, peaks=peaks)
    return smallest_out_shift(cfg, codes.shape[1]), codes


def ranging_config(inst: Instrument) -> RangingConfig:
    """What the host knows of the instrument's configuration (nominal values, no offset)."""
    spec = inst.spec
    return RangingConfig(samples_per_chip=spec.samples_per_chip,
                         chip_rate_hz=spec.chip_rate_hz, code_length=spec.code_length,
                         uid=spec.uid)


def true_offset_m(inst: Instrument) -> float:
    """The hidden system delay as a range (m): what a perfect calibration finds."""
    return delay_to_range_m(inst.spec.system_delay_s)


def simulate_frame(scene_name: str, seed: int = 1, *, peaks: int = 1,
                   power_w: NDArray[np.float64] | None = None, frame: int = 0,
                   gate: tuple[int, int] | None = None) -> SimulatedScan:
    """Render and receive every column of ``scene_name`` (a preset or a TOML path)."""

    scene = load_scene(scene_name)
    inst = Instrument(scene, seed=seed)
    spec = inst.spec
    cfg, codes = receiver_setup(inst, peaks=peaks, gate=gate)
    rx = FastReceiver(cfg, codes)
    data = FrameData.empty(inst.channels, inst.columns, spec.uid_bits, peaks, frame)
    for col in range(inst.columns):
        pw = None if power_w is None else power_w[:, col]
        data.set_column(col, rx.column(inst.render(col, frame=frame, power_w=pw)),
                        angle_deg=float(spec.rotations_deg[col]))
    return SimulatedScan(frame=data, truth_range_m=inst.truth.range_m,
                         ranging=ranging_config(inst), geometry=spec.geometry(nominal=True),
                         wavelengths_m=np.asarray(spec.wavelengths_m),
                         rotations_deg=np.asarray(spec.rotations_deg),
                         true_offset_m=true_offset_m(inst))


def eq27_from_configuration(scene_name: str) -> float:
    """Eq. 27 with the per-sample SNR of eq. 30 from the scene's own parameters (median pixel).

    SNR_k = A_k^2 / (sigma^2 / R + sum_{j != k, same column} A_j^2): echo amplitudes A
    (V) from the instrument's link budget, thermal noise sigma (V) averaged over R
    frames, every other lit channel of the column as interference.
    """

    inst = Instrument(load_scene(scene_name), seed=0)
    spec = inst.spec
    a2 = (inst.gain_v_per_w * inst.default_power_w) ** 2
    others = a2.sum(axis=0, keepdims=True) - a2
    snr = a2 / (inst.noise_rms_v**2 / spec.averages + others)
    lit = inst.gain_v_per_w > 0
    return float(precision_eq27_m(spec.chip_rate_hz, spec.code_length * spec.samples_per_chip,
                                  snr=float(np.median(snr[lit]))))
