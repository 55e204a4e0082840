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
from collections.abc import Iterator
from dataclasses import dataclass, replace
from typing import Any, Protocol

import numpy as np
from numpy.typing import ArrayLike, NDArray

from cdma_lidar.errors import ConfigError, DeviceError, LinkError, LinkTimeout
from cdma_lidar.host.ranging import RangingConfig, default_snr_threshold_db
from cdma_lidar.optics.grating import GratingGeometry, azimuth_elevation_deg
from cdma_lidar.paths import default_key_file
from cdma_lidar.protocol.auth import load_key
from cdma_lidar.protocol.link import HostLink
from cdma_lidar.protocol.messages import ErrorCode
from cdma_lidar.protocol.ports import open_port
from cdma_lidar.protocol.requests import DIAG_HINTS, DIAG_SILENT

__all__ = ["KEY_FILE_ENV", "Device", "DeviceLink", "check_socket_url", "connect",
           "default_key_file", "resolve_key"]

log = logging.getLogger(__name__)


class DeviceLink(Protocol):
    """What the host asks of a link to a device: :class:`cdma_lidar.protocol.link.HostLink`
    is one, a replayed recording or a test double can be another.

    Column results (``ColumnResult``) and INFO are the protocol's records
    (:mod:`cdma_lidar.protocol.messages`); power matrices are uint16 counts of the
    per-pixel maximum (65535 = the maximum).
    """

    def hello(self) -> Any:
        """Open a session; returns INFO (identity, geometry, limits)."""
        ...

    def get_config(self, *names: str) -> dict[str, Any]:
        """The configuration (all keys, or ``names``)."""
        ...

    def set_config(self, **values: Any) -> None:
        """Change configuration keys; a refused value raises DeviceError naming it."""
        ...

    def set_power(self, matrix: ArrayLike, channel_start: int = 0,
                  column_start: int = 0) -> None:
        """Send a (K, C) power matrix (uint16 counts)."""
        ...

    def scan(self, first_column: int = 0, columns: int | None = None, frames: int = 1,
             frame: int | None = None) -> Iterator[Any]:
        """Column results of ``frames`` frames, in column order, each once."""
        ...

    def calibrate(self, shots: int, frame: int | None = None) -> list[Any]:
        """``shots`` zeroth-order calibration columns."""
        ...

    def capture(self, kind: str | int = "raw", column: int = 0, channel: int = 0) -> NDArray:
        """A debug capture: raw ADC samples or one channel's correlation trace."""
        ...

    def abort(self) -> None:
        """Stop a running scan (harmless when idle)."""
        ...

    def close(self) -> None:
        """End the session and close the port."""
        ...


@dataclass
class Device:
    """An open session with a device over a :class:`DeviceLink`."""

    link: DeviceLink
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

    def beam_angles_deg(self) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """(elevation, azimuth), each (K, C) deg, of every pixel's beam from the nominal
        grating: elevation positive up (set by the channel's wavelength), azimuth positive
        left (set by the column's rotation)."""
        dirs = self.geometry().directions(self.wavelengths_m[:, None],
                                          self.column_angles_deg[None, :])
        az, el = azimuth_elevation_deg(dirs)
        return np.asarray(el), np.asarray(az)

    def ranging_config(self, **changes: Any) -> RangingConfig:
        """RangingConfig for the current configuration; ``changes`` override fields.

        The SNR_XC threshold defaults to :func:`default_snr_threshold_db` of the device's
        K, N, S, gate length, peak exclusion and UID bits (16 dB unless interference caps SNR_XC).
        """
        s = int(self.config["samples_per_chip"])
        ns = self.code_length * s
        threshold = default_snr_threshold_db(
            self.channels, self.code_length, s, int(self.config.get("gate_len", ns)),
            int(self.config.get("peak_exclude", 8)), int(self.config.get("uid_bits", 1)))
        base = RangingConfig(samples_per_chip=s, chip_rate_hz=float(self.info.chip_rate_hz),
                             code_length=self.code_length, uid=int(self.config.get("uid", 0)),
                             snr_threshold_db=threshold)
        return replace(base, **changes)


#: Environment variable naming the key file of a device reached over a network.
KEY_FILE_ENV = "CDMA_LIDAR_KEY_FILE"


def resolve_key(url: str, key_file: str | None = None) -> bytes | None:
    """The key for ``url``: ``key_file``, else for network URLs $CDMA_LIDAR_KEY_FILE, else
    :func:`default_key_file` when it exists.

    The fallbacks apply to ``socket://`` URLs only, so serial ports, ptys and
    ``virtual://`` (which hold no key) keep working with them set. Raises ConfigError
    naming the file when it cannot be read or is not private (mode 0600).
    """
    if key_file:
        return load_key(key_file)
    if not url.lower().startswith("socket://"):
        return None
    env = os.environ.get(KEY_FILE_ENV)
    if env:
        return load_key(env)
    default = default_key_file()
    return load_key(default) if default.is_file() else None


def check_socket_url(url: str) -> None:
    """Refuse a ``socket://HOST:PORT`` URL without a host or with a port outside 1..65535.

    pyserial's own message for these is Python internals; this one names the field.
    """
    if not url.lower().startswith("socket://"):
        return
    where = url[len("socket://"):].split("?", 1)[0].rstrip("/")
    host, sep, port = where.rpartition(":")
    if not sep or not host:
        raise ConfigError(f"--port {url!r} must be socket://HOST:PORT with a port number",
                          field="port")
    if not port.isdigit() or not 1 <= int(port) <= 65535:
        raise ConfigError(f"--port {url!r}: the TCP port must be from 1 to 65535, not "
                          f"{port!r}", field="port")


def connect(url: str, *, timeout_s: float = 1.0, retries: int = 3, key_file: str | None = None,
            take_over: bool = False, keep_config: bool = False) -> Device:
    """Open ``url``, say HELLO and read the configuration.

    ``key_file`` (or $CDMA_LIDAR_KEY_FILE for ``socket://``) holds the device's key;
    ``take_over`` ends another host's session instead of failing BUSY; ``keep_config``
    keeps the previous session's configuration instead of the device's defaults.
    Raises LinkError with one line that says what to do when the port cannot be
    opened, the device does not answer, or another host owns it.
    """

    check_socket_url(url)
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
