"""The project's one exception family.

Every error the toolkit raises on purpose derives from :class:`CdmaLidarError`.
Subclasses also inherit the matching built-in, so callers may catch either::

    CdmaLidarError
    +-- ConfigError(ValueError)        a parameter, file field or CLI argument is out of range
    |   +-- FieldError                 an encoder was handed a bad message field
    +-- FrameError                     bytes on the wire are not a valid frame (decoder-internal)
    +-- LinkError(OSError)             the link to the device failed
    |   +-- LinkTimeout(TimeoutError)  a request got no answer after its retries
    |   +-- DeviceError                the device answered NAK
    +-- CalibrationError               a calibration could not be made or does not apply
    +-- ScanAborted                    a scan stopped early (Ctrl-C, lost link); it can be resumed

Messages share one shape: ``<field> must be <allowed>, not <value>``. Use
:func:`out_of_range` to build them so the CLI prints one consistent line.
"""

from __future__ import annotations

__all__ = [
    "CalibrationError",
    "CdmaLidarError",
    "ConfigError",
    "DeviceError",
    "FieldError",
    "FrameError",
    "LinkError",
    "LinkTimeout",
    "MissingExtra",
    "ScanAborted",
    "out_of_range",
]


class CdmaLidarError(Exception):
    """Root of every error raised on purpose by cdma-lidar."""


class ConfigError(CdmaLidarError, ValueError):
    """A parameter, a file field or a CLI argument is outside its allowed range.

    ``field`` names the offending parameter (dotted for nested fields) so callers
    and the protocol's NAK can point at it.
    """

    def __init__(self, message: str, field: str | None = None) -> None:
        super().__init__(message)
        self.field = field


class FieldError(ConfigError):
    """An encoder was asked to put a value on the wire that its field cannot hold."""


class FrameError(CdmaLidarError):
    """Wire bytes that are not a valid frame. The stream decoder counts these, never raises.

    ``field`` names the payload field or CONFIG key that failed to decode, when known, so
    the device's NAK MALFORMED can point at it.
    """

    def __init__(self, message: str, field: str | None = None) -> None:
        super().__init__(message)
        self.field = field


class LinkError(CdmaLidarError, OSError):
    """The link to the device failed (port cannot be opened, peer vanished, ...)."""


class LinkTimeout(LinkError, TimeoutError):
    """A request got no valid answer within its timeout and retries.

    ``diagnosis`` says what was seen on the line, one of ``cdma_lidar.protocol.requests``'s
    ``DIAG_*`` strings: no bytes at all, bytes but no valid frame, frames but wrong
    session, frames but no answer, or frames of another protocol version
    (``cdma_lidar.protocol.requests.DIAG_HINTS`` maps each to what the user should check).
    """

    def __init__(self, message: str, diagnosis: str = "") -> None:
        super().__init__(message)
        self.diagnosis = diagnosis


class DeviceError(LinkError):
    """The device refused a request with a NAK; ``code`` and ``field`` say why."""

    def __init__(self, message: str, code: int = 0, field: str | None = None) -> None:
        super().__init__(message)
        self.code = code
        self.field = field


class CalibrationError(CdmaLidarError):
    """A calibration could not be made (multimodal or too-wide histogram) or does not apply."""


class ScanAborted(CdmaLidarError):
    """A scan stopped before its last column; the partial file can be resumed."""


class MissingExtra(CdmaLidarError, ImportError):
    """An optional library is not installed; the message names the extra that brings it.

    ``extra`` is the name in ``pip install 'cdma-lidar[EXTRA]'``.
    """

    def __init__(self, what: str, library: str, extra: str) -> None:
        super().__init__(f"{what} needs {library}: pip install 'cdma-lidar[{extra}]'")
        self.extra = extra


def out_of_range(field: str, allowed: str, value: object, cls: type[ConfigError] = ConfigError):
    """Build the standard error ``Argument 'field' must be <allowed>, not <value>.``

    Returns the exception (the caller raises it) so tracebacks point at the check.
    """
    return cls(f"{field} must be {allowed}, not {value!r}", field=field)
