"""The device as the host sees it: a link, its INFO, its configuration, and what follows.

:func:`connect` opens any port URL (a device path, a pty, ``socket://``,
``virtual://SCENE``), says HELLO and reads the configuration. :class:`Device` then
derives everything the range pipeline needs from what the device announced: the
lag-to-range scale (chip rate, samples per chip, code length), our UID, the nominal
grating geometry, the channel wavelengths and column angles, and the identity and
configuration a calibration is tied to.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, replace
from typing import Any

import numpy as np
from numpy.typing import NDArray

from cdma_lidar.errors import LinkError, LinkTimeout
from cdma_lidar.host.ranging import DEFAULT_SNR_THRESHOLD_DB, RangingConfig
from cdma_lidar.optics.grating import GratingGeometry
from cdma_lidar.protocol.link import DIAG_HINTS, DIAG_SILENT, HostLink
from cdma_lidar.protocol.ports import open_port

__all__ = ["Device", "connect"]

log = logging.getLogger(__name__)


@dataclass
class Device:
    """An open session with a device (``link`` is a :class:`cdma_lidar.protocol.link.HostLink`)."""

    link: Any
    info: Any
    config: dict[str, Any]
    url: str = ""

    def close(self) -> None:
        """Close the link."""
        self.link.close()

    def __enter__(self) -> Device:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def refresh_config(self) -> dict[str, Any]:
        """Read the configuration again (after a ``set_config``)."""
        self.config = self.link.get_config()
        return self.config

    @property
    def channels(self) -> int:
        """K channels."""
        return int(self.info.channels)

    @property
    def columns(self) -> int:
        """C columns in a default frame."""
        return int(self.config.get("columns_per_frame", self.info.column_count))

    @property
    def code_length(self) -> int:
        """N chips: 2^m - 1 for the configured Gold pair of degree m."""
        return (1 << int(self.config["poly_u"][0])) - 1

    @property
    def wavelengths_m(self) -> NDArray[np.float64]:
        """(K,) nominal channel wavelengths (m)."""
        return np.asarray(self.info.wavelengths_m, dtype=np.float64)

    @property
    def column_angles_deg(self) -> NDArray[np.float64]:
        """(C,) nominal grating rotation of each column (deg)."""
        return np.asarray(self.info.column_angles_deg, dtype=np.float64)[: self.columns]

    def identity(self) -> dict[str, Any]:
        """What identifies the physical device (recorded in calibration files)."""
        return {"serial": self.info.serial, "firmware_version": self.info.firmware_version}

    def calibration_config(self) -> dict[str, Any]:
        """Configuration recorded with a calibration: the device's keys plus chip rate and K."""
        cfg = {k: v for k, v in self.config.items() if k not in ("mode",)}
        cfg["chip_rate_hz"] = int(self.info.chip_rate_hz)
        cfg["channels"] = self.channels
        cfg["code_length"] = self.code_length
        return cfg

    def geometry(self) -> GratingGeometry:
        """Nominal grating geometry from INFO."""
        return GratingGeometry(grooves_per_mm=float(self.info.grooves_per_mm),
                               incidence_deg=float(self.info.incidence_deg),
                               tilt_deg=self.info.tilt_deg,
                               reference_wavelength_m=float(self.info.reference_wavelength_m))

    def ranging_config(self, **changes: Any) -> RangingConfig:
        """RangingConfig for the current configuration; ``changes`` override fields."""
        base = RangingConfig(samples_per_chip=int(self.config["samples_per_chip"]),
                             chip_rate_hz=float(self.info.chip_rate_hz),
                             code_length=self.code_length, uid=int(self.config.get("uid", 0)),
                             snr_threshold_db=DEFAULT_SNR_THRESHOLD_DB)
        return replace(base, **changes)


def connect(url: str, *, timeout_s: float = 1.0, retries: int = 3) -> Device:
    """Open ``url``, say HELLO and read the configuration.

    Raises LinkError with one line that says what to do when the port cannot be
    opened or the device does not answer.
    """

    port = open_port(url)
    link = HostLink(port, timeout_s=timeout_s, retries=retries)
    try:
        info = link.hello()
        config = link.get_config()
    except LinkTimeout as exc:
        link.close()
        diagnosis = getattr(exc, "diagnosis", "") or DIAG_SILENT
        hint = DIAG_HINTS.get(diagnosis, DIAG_HINTS[DIAG_SILENT])
        raise LinkError(f"no answer from {url} ({diagnosis}); {hint}") from exc
    except BaseException:
        link.close()
        raise
    log.info("connected to %s: %s, %d channels, %d columns", url, info.serial, info.channels,
             info.column_count)
    return Device(link=link, info=info, config=config, url=url)
