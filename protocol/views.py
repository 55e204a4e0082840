"""INFO and STATUS: their payload fields declared once, as typed dataclasses.

:class:`Info` (reply to HELLO) and :class:`Status` (reply to STATUS_GET, and HEARTBEAT)
hold the fields in wire units (pm, µdeg, m°C, ms, 0.001 lines/mm) and wire order, each
with its payload declaration (:func:`~cdma_lidar.protocol.schema.wire`). ``to_fields``
gives what ``encode_payload`` takes; ``from_fields`` / ``Status(**fields)`` read a payload.
"""

from __future__ import annotations

import dataclasses
import enum
import math
from collections.abc import Sequence
from dataclasses import MISSING, dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from cdma_lidar.protocol.framing import PROTOCOL_VERSION
from cdma_lidar.protocol.schema import array, i, nbytes, text, u, wire

__all__ = ["TEMPERATURE_UNKNOWN", "TILT_AUTO", "Info", "State", "Status"]

#: Sentinels of Info.tilt_udeg (no nominal tilt: the host derives it, the reference
#: wavelength horizontal at zero rotation) and Status.temperature_mc (no sensor).
TILT_AUTO = TEMPERATURE_UNKNOWN = -(2**31)


class State(enum.IntEnum):
    """Device state in STATUS / HEARTBEAT."""

    IDLE = 0
    SCANNING = 1
    CALIBRATING = 2


@dataclass(frozen=True, kw_only=True)
class Info:
    """INFO payload: identity, limits and nominal geometry (wire units, see the spec). The
    device endpoint fills ``protocol_version``, ``session_id``, ``schema_crc``, ``max_frame``,
    ``ring_columns``, ``heartbeat_ms``, ``session_idle_ms``, ``auth`` and ``device_mac``;
    the device application the rest (:meth:`nominal`)."""

    protocol_version: int = wire(PROTOCOL_VERSION, u, 8,
                                 f"protocol version spoken ({PROTOCOL_VERSION})")
    session_id: int = wire(1, u, 32, "session id chosen for this HELLO, also in every frame "
                           "header", lo=1, hi=2**32 - 1)
    session_idle_ms: int = wire(10_000, u, 32, "a session idle this long may be taken by "
                                "another host without take-over", "ms", 1)
    auth: int = wire(0, u, 8, "0 no key; 1 HMAC-SHA256 challenge-response, every frame "
                     "signed", lo=0, hi=1)
    device_mac: bytes = wire(bytes(32), nbytes, 32, "HMAC-SHA256 proof that the device "
                             "holds the key; zeros when auth is 0")
    pixel_power_max_uw: int = wire(0, u, 32, "laser power of one pixel at power 65535; 0: "
                                   "no power control", "µW")
    column_power_cap_uw: int = wire(0, u, 32, "eye-safety cap on the sum over a column's "
                                    "channels; 0: none", "µW")
    schema_crc: int = wire(0, u, 32, "CRC-32 of the message schema (see Versioning)")
    max_frame: int = wire(16384, u, 16, "largest frame the device accepts (header + payload "
                          "+ signature + CRC); the host's requests stay within "
                          "min(max_frame, max(host_max_frame, 256))", "bytes", 256, 65535)
    ring_columns: int = wire(1024, u, 16, "recent columns kept for RESEND", "columns")
    heartbeat_ms: int = wire(200, u, 16, "HEARTBEAT interval while scanning", "ms", 1, 65535)
    max_degree: int = wire(20, u, 8, "largest LFSR degree m of the code family", "", 2, 32)
    max_channels: int = wire(64, u, 16, "largest number of channels", "", 1, 65535)
    adc_bits: int = wire(12, u, 8, "ADC resolution", "bits", 8, 16)
    spc_min: int = wire(1, u, 16, "smallest samples per chip", "samples/chip", 1, 65535)
    spc_max: int = wire(64, u, 16, "largest samples per chip", "samples/chip", 1, 65535)
    max_averages: int = wire(1 << 20, u, 32, "largest number of averaged code repetitions",
                             "", 1)
    max_uid_bits: int = wire(8, u, 8, "largest UID length n", "bits", 1, 8)
    max_peaks: int = wire(8, u, 8, "largest peaks per channel P", "", 1, 8)
    max_gate_len: int = wire(1 << 20, u, 32, "largest lag gate", "samples", 1)
    max_columns: int = wire(65535, u, 16, "largest columns in one scan", "", 1)
    chip_rate_hz: int = wire(1_000_000_000, u, 32, "code chip rate", "Hz", 1)
    grooves_per_mm_milli: int = wire(600_000, u, 32, "grating groove density",
                                     "0.001 lines/mm", 1)
    incidence_udeg: int = wire(60_000_000, i, 32, "incidence angle theta_i on the grating",
                               "µdeg")
    tilt_udeg: int = wire(TILT_AUTO, i, 32, "mounting tilt gamma; -2^31 = host derives it",
                          "µdeg")
    reference_wavelength_pm: int = wire(1_587_000, u, 32, "wavelength horizontal at zero "
                                        "rotation", "pm")
    column_start_udeg: int = wire(0, i, 32, "rotation angle of column 0", "µdeg")
    column_step_udeg: int = wire(100_000, i, 32, "rotation step between columns", "µdeg")
    column_count: int = wire(1, u, 16, "columns in a full frame", "", 1)
    firmware_version: str = wire(MISSING, text, "firmware version string")
    serial: str = wire(MISSING, text, "device serial number")
    wavelengths_pm: tuple[int, ...] = wire(
        MISSING, array, 16, "u", 32, "nominal wavelength of each channel (count K)", "pm", 1,
        max_items=65535, allowed="K = 1..max_channels items", min_items=1)

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

    #: The field dict encode_payload(MsgType.INFO, ...) takes.
    to_fields = dataclasses.asdict

    @classmethod
    def from_fields(cls, d: dict[str, Any]) -> Info:
        """From a decoded INFO payload."""
        return cls(**{**d, "wavelengths_pm": tuple(d["wavelengths_pm"])})


@dataclass(frozen=True)
class Status:
    """STATUS / HEARTBEAT payload."""

    state: int = wire(0, u, 8, "0 idle, 1 scanning, 2 calibrating", lo=0, hi=2)
    frame: int = wire(0, u, 32, "frame id of the current or last scan")
    next_column: int = wire(0, u, 16, "next column (or shot) the current or last scan "
                            "produces")
    last_end: int = wire(0, u, 8, "how the last scan ended: 0 complete, 1 aborted, 2 device "
                         "error", lo=0, hi=2)
    columns_sent: int = wire(0, u, 32, "COLUMN_RESULT frames sent since boot (resends "
                             "included)")
    uptime_ms: int = wire(0, u, 32, "time since boot", "ms")
    rx_frames: int = wire(0, u, 32, "valid frames received since boot")
    rx_errors: int = wire(0, u, 32, "rejected chunks since boot (COBS, CRC, length, size, "
                          "version)")
    tx_frames: int = wire(0, u, 32, "frames sent since boot")
    replays: int = wire(0, u, 32, "retransmitted requests answered from the replay cache")
    temperature_mc: int = wire(TEMPERATURE_UNKNOWN, i, 32, "board temperature; -2^31 = no "
                               "sensor", "m°C")
    faults: int = wire(0, u, 32, "device-specific fault bits, 0 = healthy")
    column_time_ms: int = wire(0, u, 32, "longest the device may take to deliver its next "
                               "column with the current configuration (a batch of columns "
                               "computed together included); the host's no-progress limit "
                               "follows it; 0: not stated", "ms")

    @property
    def state_name(self) -> str:
        """``idle``, ``scanning`` or ``calibrating``."""
        return State(self.state).name.lower() if self.state in iter(State) else str(self.state)

    @property
    def column_time_s(self) -> float:
        """:attr:`column_time_ms` in seconds (0.0: not stated)."""
        return self.column_time_ms * 1e-3

    @property
    def temperature_c(self) -> float:
        """Board temperature (°C), NaN without a sensor."""
        return math.nan if self.temperature_mc == TEMPERATURE_UNKNOWN else \
            self.temperature_mc * 1e-3

    #: The field dict encode_payload(MsgType.STATUS or HEARTBEAT, ...) takes.
    to_fields = dataclasses.asdict
