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
import os
from dataclasses import dataclass, replace
from typing import Any

import numpy as np
from numpy.typing import NDArray

from cdma_lidar.errors import DeviceError, LinkError, LinkTimeout
from cdma_lidar.host.ranging import DEFAULT_SNR_THRESHOLD_DB, RangingConfig
from cdma_lidar.optics.grating import GratingGeometry
from cdma_lidar.protocol.auth import load_key
from cdma_lidar.protocol.link import DIAG_HINTS, DIAG_SILENT, HostLink
from cdma_lidar.protocol.messages import ErrorCode
from cdma_lidar.protocol.ports import open_port

__all__ = ["KEY_FILE_ENV", "Device", "connect", "resolve_key"]

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


#: Environment variable naming the key file of a device reached over a network.
KEY_FILE_ENV = "CDMA_LIDAR_KEY_FILE"


def resolve_key(url: str, key_file: str | None = None) -> bytes | None:
    """The key for ``url``: from ``key_file``, else from $CDMA_LIDAR_KEY_FILE for network URLs.

    The environment variable applies to ``socket://`` URLs only, so serial ports, ptys
    and ``virtual://`` (which hold no key) keep working with it set. Raises ConfigError
    naming the file when it cannot be read or is not private (mode 0600).
    """
    if key_file:
        return load_key(key_file)
    env = os.environ.get(KEY_FILE_ENV)
    if env and url.lower().startswith("socket://"):
        return load_key(env)
    return None


def connect(url: str, *, timeout_s: float = 1.0, retries: int = 3, key_file: str | None = None,
            take_over: bool = False, keep_config: bool = False) -> Device:
    """Open ``url``, say HELLO and read the configuration.

    ``key_file`` (or $CDMA_LIDAR_KEY_FILE for ``socket://``) holds the device's key;
    ``take_over`` ends another host's session instead of failing BUSY; ``keep_config``
    keeps the previous session's configuration instead of the device's defaults.
    Raises LinkError with one line that says what to do when the port cannot be
    opened, the device does not answer, or another host owns it.
    """

    key = resolve_key(url, key_file)
    port = open_port(url)
    link = HostLink(port, timeout_s=timeout_s, retries=retries, key=key, take_over=take_over,
                    keep_config=keep_config)
    try:
        info = link.hello()
        config = link.get_config()
    except LinkTimeout as exc:
        link.close()
        diagnosis = getattr(exc, "diagnosis", "") or DIAG_SILENT
        hint = DIAG_HINTS.get(diagnosis, DIAG_HINTS[DIAG_SILENT])
        raise LinkError(f"no answer from {url} ({diagnosis}); {hint}") from exc
    except DeviceError as exc:
        link.close()
        if exc.code == ErrorCode.BUSY and exc.field == "session":
            raise LinkError(f"{url} is busy: {exc}; or use --take-over") from None
        raise
    except BaseException:
        link.close()
        raise
    log.info("connected to %s: %s, %d channels, %d columns", url, info.serial, info.channels,
             info.column_count)
    return Device(link=link, info=info, config=config, url=url)
