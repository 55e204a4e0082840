"""The virtual board's application: configuration limits, power control, the receive chain.

:class:`VirtualFirmware` implements :class:`cdma_lidar.protocol.endpoint.DeviceApp`. It sits behind
the protocol's :class:`cdma_lidar.protocol.endpoint.DeviceEndpoint` (which owns framing, sequence
numbers, replay and the column ring buffer) and in front of the simulated instrument
(:class:`cdma_lidar.scene.instrument.Instrument`)::

    host --wire--> DeviceEndpoint --requests--> VirtualFirmware --settings--> Instrument
                                 <--columns---   (receive chain)  <--ADC codes--

* INFO: identity, limits, and the NOMINAL geometry (what the data sheet says); the
  simulated light follows the scene's TRUE geometry, which may differ slightly.
* CONFIG: every key is checked against the limits below; a bad value is refused with
  ``ConfigError`` naming the key (the endpoint answers NAK OUT_OF_RANGE with that field).
  All keys of one CONFIG_SET are applied or none.
* POWER: a (K, C) matrix of per-pixel laser power in 1/65535 of ``max_pixel_power_w``; a
  rectangle that would push any column's total above the eye-safety cap
  ``total_power_cap_w`` is refused (field ``power``), as is one outside the matrix.
* SCAN: renders each column's repetition sums (noise seeded by (seed, frame, column), so
  a resend or a rescan of the same frame id gives the same result) and runs
  ``cdma_lidar.firmware_model.receiver`` (the fast, bit-exact path) with the current
  configuration, a batch of columns at a time (a whole frame when it fits
  ``cdma_lidar.scene.acquire.BATCH_VALUES``): :func:`cdma_lidar.scene.acquire.acquire`,
  the acquisition path every study frame runs too. The boot configuration and power
  are :func:`~cdma_lidar.scene.acquire.receiver_config` and
  :func:`~cdma_lidar.scene.acquire.boot_power_codes`.
* CALIBRATE: ``shots`` columns of the zeroth-order beam-trap target at its fixed
  distance, every channel lit, grating angle reported as 90 degrees.
* CAPTURE: the raw ADC codes of a column (of the last scanned frame id) or one
  channel's correlation trace over the gate.

Limits (virtual board): code degree 3..15, K fixed by the scene, samples per chip
1..16, averages 1..1024, UID bits 1..8, peaks 1..8, gate inside one period, at most
2**25 samples per column.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Iterator
from typing import Any

import numpy as np
from numpy.typing import NDArray

from cdma_lidar.checks import check_int
from cdma_lidar.column_record import RECORD
from cdma_lidar.errors import ConfigError, out_of_range
from cdma_lidar.firmware_model.gold import check_pair, gold_codes
from cdma_lidar.firmware_model.output import ReceiverOutput
from cdma_lidar.firmware_model.receiver import FastReceiver, ReceiverConfig
from cdma_lidar.hdl_ref.engine import RtlReceiver, check_rtl_config, missing_simulator
from cdma_lidar.protocol.columns import ColumnResult, udeg
from cdma_lidar.protocol.config_keys import MODES
from cdma_lidar.protocol.endpoint import DeviceApp
from cdma_lidar.protocol.messages import CaptureKind, Info
from cdma_lidar.scene.acquire import (
    acquire,
    boot_power_codes,
    clock_us,
    column_batches,
    power_limits_uw,
    power_w_of_codes,
    receiver_config,
)
from cdma_lidar.scene.instrument import SUM_TYPE, Instrument, RenderSettings
from cdma_lidar.scene.model import Scene
from cdma_lidar.version import __version__

__all__ = ["LIMITS", "VirtualFirmware"]

log = logging.getLogger(__name__)

#: Limits of the virtual board (also announced in INFO).
LIMITS = {
    "max_degree": 15,
    "spc_min": 1,
    "spc_max": 16,
    "max_averages": 1024,
    "max_uid_bits": 8,
    "max_peaks": 8,
    "max_column_samples": 1 << 25,
}

#: The board's a-priori bound on its own compute per channel and sample of a column (s),
#: before it has timed a batch of the current configuration: about 3x what a loaded 2-core
#: machine takes for paper-massive (1,200 x 65,534 values a column); the RTL engine
#: simulates clock cycles, about 1,000 times slower than the model.
COMPUTE_S_PER_VALUE = {"model": 2e-8, "rtl": 1e-5}

#: Grating angle reported for calibration shots (the grating is turned 90 degrees, Note 6).
CALIBRATION_ANGLE_DEG = 90.0

#: Fields of the channel record that describe peaks 2..P (left out when P = 1).
_EXTRA_FIELDS = frozenset(f.name for f in RECORD if f.per_extra_peak)


def _column_results(frame: int, columns: list[int], angles_deg: list[float],
                    outs: list[ReceiverOutput], calibration: bool,
                    timestamps_us: list[int]) -> list[ColumnResult]:
    """ColumnResults of a batch, checked and packed as ONE array of records.

    ``ColumnResult.from_arrays`` checks every value against its wire field and packs
    the (K,) records of a column; the records of different columns are independent, so
    the batch's B columns are handed to it as one column of B K channel records (at most
    65535 at a time) and each ColumnResult gets its K records as a read-only view. Equal
    to ``ColumnResult.from_receiver`` column by column (tests/virtual/test_board.py), at
    a fraction of the per-column cost of checking and packing 14 small arrays.
    """
    k = outs[0].peak.shape[0]
    extra = outs[0].extra_lag.size > 0
    names = [f.name for f in RECORD if extra or f.name not in _EXTRA_FIELDS]
    per = max(1, 65535 // max(1, k))
    results: list[ColumnResult] = []
    for b0 in range(0, len(outs), per):
        part = outs[b0:b0 + per]
        arrays = {n: np.concatenate([getattr(o, n) for o in part]) for n in names}
        merged = ColumnResult.from_arrays(frame, columns[b0], angles_deg[b0],
                                          calibration=calibration,
                                          timestamp_us=timestamps_us[b0], **arrays)
        for i in range(len(part)):
            col, ts = columns[b0 + i], timestamps_us[b0 + i]
            angle_udeg = udeg(angles_deg[b0 + i])
            if not (0 <= col <= 0xFFFF and 0 <= ts <= 0xFFFFFFFF
                    and -(2**31) <= angle_udeg < 2**31):
                # the one-column path checks it (and names the field out of range)
                results.append(ColumnResult.from_receiver(
                    frame, col, angles_deg[b0 + i], part[i], calibration=calibration,
                    timestamp_us=ts))
                continue
            results.append(ColumnResult(merged.frame, col, angle_udeg,
                                        merged.records[i * k:(i + 1) * k], merged.uid_bits,
                                        merged.calibration, ts))
    return results


class VirtualFirmware(DeviceApp):
    """Device application of the virtual board (implements cdma_lidar.protocol.endpoint.DeviceApp).

    Args:
        scene: the world in front of the instrument (true parameters).
        seed: noise seed; the same scene, seed, configuration and frame ids give the same
            samples and results.
        serial: serial number announced in INFO.
        engine: ``"model"`` (default) computes the receive chain with ``FastReceiver``,
            ``"rtl"`` with the reference RTL under Verilator (``hdl_ref.engine``): the
            same outputs.
    """

    def __init__(self, scene: Scene, seed: int = 0, serial: str | None = None,
                 engine: str = "model") -> None:
        if engine not in ("model", "rtl"):
            raise out_of_range("engine", "model or rtl", engine)
        if engine == "rtl" and missing_simulator():
            raise ConfigError(missing_simulator() or "", field="engine")
        self.engine = engine
        self.scene = scene
        self.instrument = Instrument(scene, seed)
        self.spec = scene.instrument
        self.seed = int(seed)
        self.serial = serial or f"VIRT-{scene.name}-{self.seed}"
        k, c = self.instrument.channels, self.instrument.columns
        self.channels, self.columns = k, c
        rc, _ = receiver_config(self.instrument)  # the boot configuration: every study's
        self._config: dict[str, Any] = {
            "poly_u": self.spec.poly_u, "poly_v": self.spec.poly_v,
            "code_index": tuple(self.spec.code_indices), "uid_bits": rc.uid_bits,
            "uid": rc.uid, "samples_per_chip": rc.samples_per_chip,
            "averages": rc.averages, "adc_bits": rc.adc_bits,
            "gate_start": rc.gate_start, "gate_len": rc.gate_len,
            "peak_exclude": rc.peak_exclude, "ghost_windows": rc.ghost_windows,
            "out_shift": rc.out_shift, "rounding": rc.rounding, "out_bits": rc.out_bits,
            "peaks": rc.peaks, "columns_per_frame": c, "mode": "ranging",
            "cancel_rounds": rc.cancel_rounds, "cancel_snr_q8": rc.cancel_snr_q8,
        }
        self._check(self._config)
        # Power in exact integers: codes (1/65535 of the pixel maximum) and whole µW.
        self._pixel_uw, self._cap_uw = power_limits_uw(self.spec)
        self.power_code = boot_power_codes(self.instrument)
        self._receiver: tuple[tuple, dict[str, FastReceiver]] | None = None
        self._sums: NDArray[np.int32] | None = None  # the batches' sums, reused (_receive)
        self._timed: tuple[dict[str, Any], float] | None = None  # (config, s per column)
        self._last_frame = 0
        #: the device clock as an exact count of chips since power-up (integer: no rounding
        #: accumulates); the wire's microseconds are derived from it by flooring
        self._clock_chips = 0

    # ---- identity -------------------------------------------------------------------
    def info(self) -> Info:
        """Identity, limits and the nominal geometry."""
        spec = self.spec
        geom = spec.geometry(nominal=True)
        rot = spec.rotations_deg
        step = float(rot[1] - rot[0]) if rot.size > 1 else 0.0
        n = spec.code_length
        return Info.nominal(
            serial=self.serial, firmware_version=f"virtual-{__version__}",
            wavelengths_m=spec.wavelengths_m, grooves_per_mm=geom.grooves_per_mm,
            incidence_deg=geom.incidence_deg, tilt_deg=geom.tilt_deg,
            reference_wavelength_m=geom.reference_wavelength_m,
            chip_rate_hz=spec.chip_rate_hz, column_start_deg=float(rot[0]),
            column_step_deg=step, column_count=self.columns,
            max_degree=LIMITS["max_degree"], max_channels=self.channels,
            adc_bits=spec.adc_bits, spc_min=LIMITS["spc_min"], spc_max=LIMITS["spc_max"],
            max_averages=LIMITS["max_averages"], max_uid_bits=LIMITS["max_uid_bits"],
            max_peaks=LIMITS["max_peaks"], max_gate_len=n * LIMITS["spc_max"],
            max_columns=self.columns, pixel_power_max_uw=self._pixel_uw,
            column_power_cap_uw=self._cap_uw)

    # ---- configuration --------------------------------------------------------------
    def get_config(self) -> dict[str, Any]:
        """Current configuration ``{key: value}``."""
        return dict(self._config)

    def set_config(self, values: dict[str, Any]) -> None:
        """Validate the merged configuration, then apply all of ``values``."""
        merged = dict(self._config)
        merged.update(values)
        for name in values:
            if name not in self._config:
                raise out_of_range(name, "a configuration key", name)
        if "adc_bits" in values and values["adc_bits"] != self.spec.adc_bits:
            raise out_of_range("adc_bits", f"{self.spec.adc_bits} (read-only)",
                               values["adc_bits"])
        self._check(merged)
        self._config = merged
        self._receiver = None
        log.info("configuration: %s", ", ".join(f"{k}={v}" for k, v in values.items()
                                                 if k != "code_index"))

    def _check(self, c: dict[str, Any]) -> None:
        """Check a merged configuration once: the board's own limits here (code pair and
        members, UID length, samples per chip, peak exclusion, columns, mode, samples per
        column), the receive chain's fields where the chain's configuration is built
        (``ReceiverConfig``, then ``widths``: the gate inside the period) and, on the RTL
        engine, what the RTL cannot compute (``cancel_rounds`` 0); each error names the
        field and its range."""
        pu, _ = check_pair(c["poly_u"], c["poly_v"])
        degree = pu[0]
        if not 3 <= degree <= LIMITS["max_degree"]:
            raise out_of_range("poly_u", f"a polynomial of degree 3 to {LIMITS['max_degree']}",
                               pu)
        n = (1 << degree) - 1
        idx = tuple(int(x) for x in c["code_index"])
        if len(idx) != self.channels:
            raise out_of_range("code_index", f"{self.channels} items (one per channel)",
                               len(idx))
        if any(not 0 <= x <= n + 1 for x in idx):
            raise out_of_range("code_index", f"members 0 to {n + 1}", idx)
        check_int("uid_bits", c["uid_bits"], 1, LIMITS["max_uid_bits"])
        check_int("samples_per_chip", c["samples_per_chip"], LIMITS["spc_min"], LIMITS["spc_max"])
        check_int("columns_per_frame", c["columns_per_frame"], 1, self.columns)
        if c["mode"] not in MODES:
            raise out_of_range("mode", "one of " + ", ".join(MODES), c["mode"])
        rc = self._receiver_config(c)
        rc.widths(n)
        if self.engine == "rtl":
            check_rtl_config(rc)
        ns = n * c["samples_per_chip"]
        check_int("peak_exclude", c["peak_exclude"], 0, ns)
        samples = c["averages"] * c["uid_bits"] * ns
        if samples > LIMITS["max_column_samples"]:
            raise out_of_range("averages", f"at most {LIMITS['max_column_samples']} samples per "
                               "column (averages * uid_bits * N * samples_per_chip)", samples)

    def _receiver_config(self, c: dict[str, Any]) -> ReceiverConfig:
        """The receive chain's configuration of ``c`` (its fields checked there)."""
        return ReceiverConfig(
            adc_bits=self.spec.adc_bits, samples_per_chip=c["samples_per_chip"],
            averages=c["averages"], uid_bits=c["uid_bits"], uid=c["uid"],
            gate_start=c["gate_start"], gate_len=c["gate_len"],
            peak_exclude=c["peak_exclude"], ghost_windows=tuple(c["ghost_windows"]),
            out_shift=c["out_shift"], rounding=c["rounding"], out_bits=c["out_bits"],
            peaks=c["peaks"], cancel_rounds=c["cancel_rounds"],
            cancel_snr_q8=c["cancel_snr_q8"])

    def render_settings(self) -> RenderSettings:
        """What the instrument emits and samples under the current configuration."""
        c = self._config
        return RenderSettings(samples_per_chip=c["samples_per_chip"], averages=c["averages"],
                              uid_bits=c["uid_bits"], uid=c["uid"],
                              code_index=tuple(int(x) for x in c["code_index"]),
                              poly_u=tuple(c["poly_u"]), poly_v=tuple(c["poly_v"]))

    def receiver(self, method: str = "auto") -> FastReceiver:
        """The receive chain for the current configuration (built once per configuration).

        ``method``: the correlation kernel (see ``firmware_model.receiver``); every kernel
        gives the same integers.
        """
        c = self._config
        key = tuple((k, tuple(v) if isinstance(v, list) else v) for k, v in sorted(c.items()))
        if self._receiver is None or self._receiver[0] != key:
            self._receiver = (key, {})
        chains = self._receiver[1]
        if method not in chains:
            codes = gold_codes(tuple(c["poly_u"]), tuple(c["poly_v"]),
                               tuple(int(x) for x in c["code_index"]))
            chains[method] = (RtlReceiver(self._receiver_config(c), tuple(c["poly_u"]),
                                          tuple(c["poly_v"]), tuple(c["code_index"]))
                              if self.engine == "rtl" else
                              FastReceiver(self._receiver_config(c), codes, method=method))
        return chains[method]

    def column_time_s(self) -> float:
        """Longest the next column may take (s): a batch of columns is computed together,
        so a batch's columns times (the instrument's acquisition time, R n N / f_chip,
        plus the board's compute per column: the larger of the last batch's, timed
        under this configuration, and :data:`COMPUTE_S_PER_VALUE` per channel sample)."""
        c, cfg = self._config, self.render_settings()
        batch = len(next(column_batches(0, c["columns_per_frame"], cfg.frame_samples)))
        compute = COMPUTE_S_PER_VALUE[self.engine] * self.channels * cfg.frame_samples
        timed = self._timed
        if timed is not None and timed[0] is c:
            compute = max(compute, timed[1])
        acquisition = cfg.averages * cfg.frame_chips / self.spec.chip_rate_hz
        return batch * (acquisition + compute)

    def _receive(self, frame: int, columns: list[int], powers: list[NDArray[np.float64]],
                 cfg: RenderSettings, calibration: bool) -> list[ReceiverOutput]:
        """Render ``columns`` (or calibration shots) and run the receive chain on them:
        :func:`cdma_lidar.scene.acquire.acquire`, into the same array of sums batch after
        batch."""
        shape = (len(columns), cfg.uid_bits, cfg.frame_samples // cfg.uid_bits)
        if self._sums is None or self._sums.shape != shape:
            self._sums = np.empty(shape, dtype=SUM_TYPE)
        # "auto" picks the kernel for each batch size; calibration (shots, or a scan in
        # calibration mode): shot c of the target
        config, t0 = self._config, time.perf_counter()
        outs = acquire(self.instrument, self.receiver(), cfg, frame, columns, powers,
                       calibration=calibration, out=self._sums).outputs
        self._timed = (config, (time.perf_counter() - t0) / len(columns))
        return outs

    # ---- power ----------------------------------------------------------------------
    def set_power(self, channel_start: int, column_start: int,
                  power: NDArray[np.uint16]) -> None:
        """Store a rectangle of the power matrix (1/65535 of the per-pixel maximum)."""
        p = np.asarray(power, dtype=np.uint16)
        rows, cols = p.shape
        if not 0 <= channel_start or channel_start + rows > self.channels:
            raise out_of_range("channel_start",
                               f"a rectangle inside channels 0..{self.channels - 1}",
                               channel_start)
        if not 0 <= column_start or column_start + cols > self.columns:
            raise out_of_range("column_start",
                               f"a rectangle inside columns 0..{self.columns - 1}", column_start)
        new = self.power_code.copy()
        new[channel_start:channel_start + rows, column_start:column_start + cols] = p
        # Exact: sum(codes) * pixel_uw <= cap_uw * 65535 (no float rounding refusals).
        scaled = new.astype(np.int64).sum(axis=0) * self._pixel_uw
        worst = int(np.argmax(scaled))
        if int(scaled[worst]) > self._cap_uw * 65535:
            raise out_of_range(
                "power", f"at most {self._cap_uw} µW in total per column (eye-safety cap; "
                f"column {worst} would get {int(scaled[worst]) / 65535:.3f} µW)",
                f"{int(scaled[worst]) / 65535:.3f} µW")
        self.power_code = new

    def get_power(self) -> NDArray[np.uint16]:
        """The (K, C) power matrix (1/65535 of the per-pixel maximum)."""
        return self.power_code.copy()

    def power_w(self) -> NDArray[np.float64]:
        """(K, C) laser power per pixel (W)."""
        return power_w_of_codes(self.spec, self.power_code)

    # ---- measurements ---------------------------------------------------------------
    def _timestamp(self, cfg: RenderSettings) -> int:
        """Simulated device clock (us, 32 bits): advances by one column's acquisition time.

        The clock counts chips exactly (R * n * N per column); the timestamp is the floor of
        that total in microseconds, so a frame of C columns spans C * R * n * N / chip rate
        to within 1 us however many columns went before (eq. 29's frame rate).
        """
        self._clock_chips += cfg.averages * cfg.frame_chips
        return clock_us(self._clock_chips, self.spec.chip_rate_hz)

    def column_samples(self, frame: int, column: int) -> NDArray[np.int16]:
        """ADC codes of one scan column under the current configuration and power."""
        cfg = self.render_settings()
        calibration = self._config["mode"] == "calibration"
        power = self.power_w()[:, column]
        return self.instrument.render(column, cfg, frame, power, calibration=calibration,
                                      shot=column)

    def scan(self, frame: int, first_column: int, columns: int) -> Iterator[ColumnResult]:
        """Validate now, then yield ColumnResults of columns first..first+columns-1."""
        if not 0 <= first_column < self.columns:
            raise out_of_range("first_column", f"0 to {self.columns - 1}", first_column)
        if first_column + columns > self.columns:
            raise out_of_range("columns", f"1 to {self.columns - first_column} from column "
                               f"{first_column}", columns)
        self._last_frame = frame
        self.receiver()  # a configuration the chain refuses fails now, not mid-scan
        cfg = self.render_settings()
        return self._scan_gen(frame, first_column, columns, cfg)

    def _scan_gen(self, frame: int, first: int, count: int,
                  cfg: RenderSettings) -> Iterator[ColumnResult]:
        calibration = self._config["mode"] == "calibration"
        power = self.power_w()
        angles = self.spec.rotations_deg
        for cols in column_batches(first, count, cfg.frame_samples):
            outs = self._receive(frame, cols, [power[:, c] for c in cols], cfg, calibration)
            angle = [CALIBRATION_ANGLE_DEG if calibration else float(angles[c]) for c in cols]
            yield from _column_results(frame, cols, angle, outs, calibration,
                                       [self._timestamp(cfg) for _ in cols])

    def calibrate(self, frame: int, shots: int) -> Iterator[ColumnResult]:
        """Zeroth-order mode: ``shots`` results of the calibration target (column = shot)."""
        if not 1 <= shots <= 65535:
            raise out_of_range("shots", "1 to 65535", shots)
        self.receiver()
        cfg = self.render_settings()
        return self._calibrate_gen(frame, shots, cfg)

    def _calibrate_gen(self, frame: int, shots: int,
                       cfg: RenderSettings) -> Iterator[ColumnResult]:
        power = self.power_w()[:, 0]  # the configured power, as a scan of column 0 would use
        for idx in column_batches(0, shots, cfg.frame_samples):
            outs = self._receive(frame, idx, [power] * len(idx), cfg, True)
            yield from _column_results(frame, idx, [CALIBRATION_ANGLE_DEG] * len(idx), outs,
                                       True, [self._timestamp(cfg) for _ in idx])

    def capture(self, kind: CaptureKind, column: int, channel: int) -> NDArray[np.integer]:
        """Raw ADC codes of ``column`` (last scanned frame id) or channel's gated trace.

        The trace is the scan's own (the same drawn repetition sum). RAW at ``exact``
        fidelity is the R repetitions drawn one by one (another noise realisation of the
        same frame: the scan draws only their sum, scene.instrument.Instrument.render_sum).
        """
        if not 0 <= column < self.columns:
            raise out_of_range("column", f"0 to {self.columns - 1}", column)
        if kind == CaptureKind.RAW:
            return self.column_samples(self._last_frame, column)
        if not 0 <= channel < self.channels:
            raise out_of_range("channel", f"0 to {self.channels - 1}", channel)
        calibration = self._config["mode"] == "calibration"
        (out,) = self._receive(self._last_frame, [column], [self.power_w()[:, column]],
                               self.render_settings(), calibration)
        return out.corr[channel]

    def abort(self) -> None:
        """Nothing to undo: columns are rendered on demand."""
        log.info("scan aborted")

    def health(self) -> tuple[int, int]:
        """A virtual board at a steady 35 degrees C, no faults."""
        return 35_000, 0

