"""Frames straight from the scene's instrument and the receive-chain model, without a link.

The virtual device acquires a frame through :func:`cdma_lidar.scene.acquire.acquire`
(the instrument's repetition sums, then :class:`cdma_lidar.firmware_model.receiver.FastReceiver`)
with the receiver configuration :func:`cdma_lidar.scene.acquire.receiver_config` and its boot
power matrix; this module runs the very same path in-process, so a study frame equals the
device's scan of the same scene, seed and frame id (``cdma-lidar study frame``), and the
host's range pipeline can be measured and tested on a scene with known truth without the
serial protocol in between (benchmarks, unit tests). Scans for users go through
:mod:`cdma_lidar.host.scan` and a real or ``virtual://`` port.
"""

from __future__ import annotations

import os
from collections.abc import Iterator
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from cdma_lidar.errors import ConfigError, DeviceError
from cdma_lidar.firmware_model.receiver import FastReceiver, ReceiverConfig
from cdma_lidar.host.connection import Device
from cdma_lidar.host.frame import FrameData
from cdma_lidar.host.ranging import RangingConfig, default_snr_threshold_db, precision_eq27_m
from cdma_lidar.host.scan import ScanOptions, ScanResult, run_scan
from cdma_lidar.optics.grating import GratingGeometry
from cdma_lidar.protocol.columns import ColumnResult
from cdma_lidar.scene import load_scene
from cdma_lidar.scene.acquire import (
    acquire_frame,
    boot_power_codes,
    power_w_of_codes,
    receiver_config,
)
from cdma_lidar.scene.instrument import Instrument
from cdma_lidar.units import delay_to_range_m
from cdma_lidar.virtual.board import VirtualFirmware

__all__ = [
    "FrameLink",
    "SimulatedScan",
    "device_power_w",
    "eq27_from_configuration",
    "ranging_config",
    "receiver_setup",
    "simulate_frame",
    "smallest_out_shift",
    "true_offset_m",
    "write_study_frame",
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

    For a configuration a study changes after :func:`receiver_setup` (ghost windows,
    peak exclusion). Raises the receiver's ConfigError when no shift fits.
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
    """The receive-chain configuration and Gold codes (K, N) the instrument's device uses:
    :func:`cdma_lidar.scene.acquire.receiver_config` at the scene's settings.

    ``gate`` (start, length) in samples defaults to the instrument's
    :meth:`~cdma_lidar.scene.instrument.Instrument.default_gate`.
    """
    return receiver_config(inst, gate=gate, peaks=peaks)


def device_power_w(inst: Instrument) -> NDArray[np.float64]:
    """(K, C) laser power (W) the instrument's device boots with (the scene's, in the
    device's 1/65535 steps, within its eye-safety cap)."""
    return power_w_of_codes(inst.spec, boot_power_codes(inst))


def ranging_config(inst: Instrument) -> RangingConfig:
    """What the host knows of the instrument's configuration (nominal values, no offset),
    with the SNR_XC threshold the host derives for the device's boot configuration
    (:func:`cdma_lidar.host.ranging.default_snr_threshold_db`, dB)."""
    spec = inst.spec
    cfg, _ = receiver_config(inst)
    threshold = default_snr_threshold_db(inst.channels, spec.code_length, spec.samples_per_chip,
                                         cfg.gate_len, cfg.peak_exclude, spec.uid_bits)
    return RangingConfig(samples_per_chip=spec.samples_per_chip,
                         chip_rate_hz=spec.chip_rate_hz, code_length=spec.code_length,
                         uid=spec.uid, snr_threshold_db=threshold)


def true_offset_m(inst: Instrument) -> float:
    """The hidden system delay as a range (m): what a perfect calibration finds."""
    return delay_to_range_m(inst.spec.system_delay_s)


def simulate_frame(scene_name: str, seed: int = 1, *, peaks: int = 1,
                   power_w: NDArray[np.float64] | None = None, frame: int = 0,
                   gate: tuple[int, int] | None = None) -> SimulatedScan:
    """Render and receive every column of ``scene_name`` (a preset or a TOML path).

    The device's acquisition (:func:`cdma_lidar.scene.acquire.acquire`) with its receiver
    configuration (:func:`receiver_setup`) and, where ``power_w`` (K, C) W is None, its
    boot power (:func:`device_power_w`): the same per-pixel results as a scan of
    ``virtual://scene_name?seed=seed`` at frame id ``frame`` (with ``peaks`` and ``gate``
    configured there too).
    """

    scene = load_scene(scene_name)
    inst = Instrument(scene, seed=seed)
    spec = inst.spec
    cfg, codes = receiver_setup(inst, peaks=peaks, gate=gate)
    rx = FastReceiver(cfg, codes)
    power = device_power_w(inst) if power_w is None else np.asarray(power_w, dtype=np.float64)
    data = FrameData.empty(inst.channels, inst.columns, spec.uid_bits, peaks, frame)
    for col, out in enumerate(acquire_frame(inst, rx, frame, power)):
        data.set_column(col, out, angle_deg=float(spec.rotations_deg[col]))
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


class FrameLink:
    """A device link whose scans are study frames: the virtual device's application without
    the wire.

    The columns are :class:`~cdma_lidar.virtual.board.VirtualFirmware`'s own (its
    acquisition, :func:`cdma_lidar.scene.acquire.acquire`, its receiver configuration, its
    clock), and so are the identity and configuration announced and the power matrix the
    host sets (checked against the eye-safety cap by the device's ``set_power``, a refusal
    a DeviceError naming ``power`` as the wire's NAK is). What the host's scan pipeline
    needs of a link, and no more: a configuration change is refused (a study frame runs
    the boot configuration).
    """

    def __init__(self, scene_name: str, seed: int, engine: str = "model") -> None:
        self._device = VirtualFirmware(load_scene(scene_name), seed, engine=engine)
        self.info, self.config = self._device.info(), self._device.get_config()

    def hello(self) -> Any:
        """The identity (INFO)."""
        return self.info

    def get_config(self, *names: str) -> dict[str, Any]:
        """The boot configuration (``names``: those keys only)."""
        return {k: v for k, v in self.config.items() if not names or k in names}

    def set_config(self, **values: Any) -> None:
        """Refused: a study frame runs the device's boot configuration."""
        raise ConfigError("a study frame runs the device's boot configuration; "
                          f"cannot set {', '.join(values)}", field=next(iter(values), "config"))

    def set_power(self, matrix: Any, channel_start: int = 0, column_start: int = 0) -> None:
        """Store a rectangle of the power matrix (1/65535 of the per-pixel maximum)."""
        try:
            self._device.set_power(channel_start, column_start,
                                   np.asarray(matrix, dtype=np.uint16))
        except ConfigError as exc:
            raise DeviceError(str(exc), field=exc.field) from exc

    def scan(self, first_column: int = 0, columns: int | None = None, frames: int = 1,
             frame: int | None = None) -> Iterator[ColumnResult]:
        """Column results of ``frames`` frames from frame id ``frame`` (default 0), columns
        first..first+count-1: the device application's own scan, without the wire."""
        count = self._device.columns - first_column if columns is None else columns
        first_frame = 0 if frame is None else int(frame)
        for frame_id in range(first_frame, first_frame + frames):
            yield from self._device.scan(frame_id, first_column, count)

    def close(self) -> None:
        """Nothing to close."""


def write_study_frame(scene_name: str, seed: int, frame_id: int,
                      out: str | os.PathLike[str], options: ScanOptions | None = None, *,
                      force: bool = False, engine: str = "model") -> ScanResult:
    """Write a study frame of ``scene_name`` to ``out`` as ``cdma-lidar scan`` writes a scan.

    The host's scan (:func:`cdma_lidar.host.scan.run_scan`, ``options`` default as the
    command's) of a :class:`FrameLink`: the same arrays, with equal values, as ``cdma-lidar
    scan --port 'virtual://SCENE?seed=N' --frame-id F --out FILE`` (the wall-clock stamp
    aside); ``engine`` ``"rtl"``: the receive chain is the reference RTL
    (``virtual://SCENE?engine=rtl``).
    """
    link = FrameLink(scene_name, seed, engine)
    device = Device(link=link, info=link.info, config=link.get_config(),  # type: ignore[arg-type]
                    url=f"study://{scene_name}?seed={seed}")
    return run_scan(device, out, options or ScanOptions(), force=force, progress=False,
                    frame_id=frame_id)
