"""Typed views of the INFO and STATUS payloads, with SI-unit accessors.

:class:`Info` (reply to HELLO) and :class:`Status` (reply to STATUS_GET, and the
HEARTBEAT stream) hold the wire fields in wire units (pm, µdeg, m°C, ms, 0.001
lines/mm); their field names are the payload's (a test checks). ``to_fields`` gives
the dict :func:`cdma_lidar.protocol.messages.encode_payload` takes, ``from_fields`` /
``Status(**fields)`` read a decoded payload.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from cdma_lidar.protocol.messages import State

__all__ = ["TEMPERATURE_UNKNOWN", "TILT_AUTO", "Info", "Status"]

#: Sentinel of Info.tilt_udeg: no nominal tilt, the host derives it (reference wavelength
#: horizontal at zero rotation).
TILT_AUTO = -(2**31)
#: Sentinel of Status.temperature_mc: no sensor.
TEMPERATURE_UNKNOWN = -(2**31)


@dataclass(frozen=True)
class Info:
    """INFO payload: identity, limits and nominal geometry (wire units, see the spec).

    The device endpoint fills ``protocol_version``, ``session_id``, ``schema_crc``,
    ``max_frame``, ``ring_columns`` and ``heartbeat_ms``; the device application
    fills the rest (see :meth:`nominal`).
    """

    firmware_version: str
    serial: str
    wavelengths_pm: tuple[int, ...]
    protocol_version: int = 3
    session_id: int = 1
    schema_crc: int = 0
    max_frame: int = 16384
    ring_columns: int = 1024
    heartbeat_ms: int = 200
    max_degree: int = 20
    max_channels: int = 64
    adc_bits: int = 12
    spc_min: int = 1
    spc_max: int = 64
    max_averages: int = 1 << 20
    max_uid_bits: int = 8
    max_peaks: int = 8
    max_gate_len: int = 1 << 20
    max_columns: int = 65535
    chip_rate_hz: int = 1_000_000_000
    grooves_per_mm_milli: int = 600_000
    incidence_udeg: int = 60_000_000
    tilt_udeg: int = TILT_AUTO
    reference_wavelength_pm: int = 1_587_000
    column_start_udeg: int = 0
    column_step_udeg: int = 100_000
    column_count: int = 1
    session_idle_ms: int = 10_000
    auth: int = 0
    device_mac: bytes = bytes(32)
    pixel_power_max_uw: int = 0
    column_power_cap_uw: int = 0

    @classmethod
    def nominal(cls, *, serial: str, firmware_version: str, wavelengths_m: Sequence[float],
                grooves_per_mm: float, incidence_deg: float, tilt_deg: float | None,
                reference_wavelength_m: float, chip_rate_hz: float,
                column_start_deg: float, column_step_deg: float, column_count: int,
                **limits: int) -> Info:
        """Build from SI units and degrees (rounded to the wire's pm / µdeg / 0.001 /mm)."""
        return cls(
            firmware_version=firmware_version, serial=serial,
            wavelengths_pm=tuple(round(w * 1e12) for w in wavelengths_m),
            grooves_per_mm_milli=round(grooves_per_mm * 1e3),
            incidence_udeg=round(incidence_deg * 1e6),
            tilt_udeg=TILT_AUTO if tilt_deg is None else round(tilt_deg * 1e6),
            reference_wavelength_pm=round(reference_wavelength_m * 1e12),
            chip_rate_hz=round(chip_rate_hz), column_start_udeg=round(column_start_deg * 1e6),
            column_step_udeg=round(column_step_deg * 1e6), column_count=column_count,
            **limits)

    @property
    def channels(self) -> int:
        """K, number of channels."""
        return len(self.wavelengths_pm)

    @property
    def wavelengths_m(self) -> NDArray[np.float64]:
        """(K,) nominal channel wavelengths (m)."""
        return np.asarray(self.wavelengths_pm, dtype=np.float64) * 1e-12

    @property
    def column_angles_deg(self) -> NDArray[np.float64]:
        """(C,) nominal grating rotation angle of each column (deg)."""
        return (self.column_start_udeg + self.column_step_udeg *
                np.arange(self.column_count, dtype=np.float64)) * 1e-6

    @property
    def grooves_per_mm(self) -> float:
        """Grating groove density (lines/mm)."""
        return self.grooves_per_mm_milli * 1e-3

    @property
    def incidence_deg(self) -> float:
        """Incidence angle (deg)."""
        return self.incidence_udeg * 1e-6

    @property
    def tilt_deg(self) -> float | None:
        """Mounting tilt (deg), or None when the host should derive it."""
        return None if self.tilt_udeg == TILT_AUTO else self.tilt_udeg * 1e-6

    @property
    def reference_wavelength_m(self) -> float:
        """Wavelength made horizontal by the default tilt (m)."""
        return self.reference_wavelength_pm * 1e-12

    def to_fields(self) -> dict[str, Any]:
        """Field dict for :func:`encode_payload` (MsgType.INFO)."""
        d = dataclasses.asdict(self)
        d["wavelengths_pm"] = list(self.wavelengths_pm)
        return d

    @classmethod
    def from_fields(cls, d: dict[str, Any]) -> Info:
        """From a decoded INFO payload."""
        d = dict(d)
        d["wavelengths_pm"] = tuple(d["wavelengths_pm"])
        return cls(**d)


@dataclass(frozen=True)
class Status:
    """STATUS / HEARTBEAT payload."""

    state: int = 0
    frame: int = 0
    next_column: int = 0
    last_end: int = 0
    columns_sent: int = 0
    uptime_ms: int = 0
    rx_frames: int = 0
    rx_errors: int = 0
    tx_frames: int = 0
    replays: int = 0
    temperature_mc: int = TEMPERATURE_UNKNOWN
    faults: int = 0

    @property
    def state_name(self) -> str:
        """``idle``, ``scanning`` or ``calibrating``."""
        return State(self.state).name.lower() if self.state in iter(State) else str(self.state)

    @property
    def temperature_c(self) -> float:
        """Board temperature (°C), NaN without a sensor."""
        return math.nan if self.temperature_mc == TEMPERATURE_UNKNOWN else \
            self.temperature_mc * 1e-3

    def to_fields(self) -> dict[str, Any]:
        """Field dict for :func:`encode_payload`."""
        return dataclasses.asdict(self)
