"""``virtual://SCENE?seed=N&line_error_rate=P``: the virtual device as a pyserial port.

Registered the way pyserial registers ``loop://``: a module ``protocol_virtual`` with a
``Serial`` class, in a package listed in ``serial.protocol_handler_packages``
(importing :mod:`cdma_lidar.virtual` adds ``cdma_lidar.virtual.urlhandler``)::

    import serial
    import cdma_lidar.virtual  # registers virtual://
    port = serial.serial_for_url("virtual://paper-scene1?seed=3")

Opening the port starts, in a daemon thread, a :class:`cdma_lidar.protocol.endpoint.DeviceEndpoint`
serving :class:`cdma_lidar.virtual.board.VirtualFirmware` over two in-process byte pipes.
Closing the port stops it.

URL: ``SCENE`` is a preset name (``virtual://flat-wall``) or a path to a .toml file
(``virtual:///abs/scene.toml``). Query options:

    seed=N               noise seed (default 0)
    line_error_rate=P    probability of flipping each bit on the line, both directions
                         (default 0), to prove the link loses nothing
    line_seed=N          seed of the line errors (default: seed): the same N flips the
                         same bit positions of each direction's byte stream
    line_baud=N          the line keeps a UART's pace, N bit/s 8N1 (default: none, as
                         fast as memory), e.g. 921600 to see what a noisy serial line costs
    session=N            session id of the device (default: random, as at a real boot)
    engine=model|rtl     the receive chain: the model (default) or the reference RTL
                         under Verilator (the same outputs; cdma_lidar.hdl_ref.engine)
    anything else        a scene option (``distance=7.5``, ``instrument.snr_db=-5``)
"""

from __future__ import annotations

import functools
import logging
import threading
import urllib.parse
from typing import Any

from serial.serialutil import PortNotOpenError, SerialBase, SerialException

from cdma_lidar.errors import CdmaLidarError
from cdma_lidar.protocol.endpoint import DeviceEndpoint
from cdma_lidar.scene import load_scene
from cdma_lidar.scene.model import Scene
from cdma_lidar.virtual.board import VirtualFirmware
from cdma_lidar.virtual.line import BytePipe, LineNoise, PipePort

__all__ = ["Serial", "parse_url"]

log = logging.getLogger(__name__)

_OWN_OPTIONS = ("seed", "line_error_rate", "line_seed", "line_baud", "session")


def parse_url(url: str) -> tuple[str, dict[str, Any], dict[str, str]]:
    """Split ``virtual://SCENE?opts`` into (scene, own options, scene options)."""
    parts = urllib.parse.urlsplit(url)
    if parts.scheme != "virtual":
        raise SerialException(f"expected a URL of the form virtual://SCENE?seed=N, not {url!r}")
    scene = parts.netloc + parts.path
    if not scene:
        raise SerialException("virtual:// needs a scene: e.g. virtual://paper-scene1")
    own: dict[str, Any] = {}
    rest: dict[str, str] = {}
    for key, values in urllib.parse.parse_qs(parts.query, keep_blank_values=True).items():
        value = values[-1]
        if key == "engine":
            if value not in ("model", "rtl"):
                raise SerialException(f"virtual:// option engine must be model or rtl, "
                                      f"not {value!r}")
            own[key] = value
        elif key in _OWN_OPTIONS:
            try:
                own[key] = float(value) if key == "line_error_rate" else int(value)
            except ValueError:
                raise SerialException(f"virtual:// option {key}={value!r} is not a number"
                                      ) from None
            if key != "line_error_rate" and not 0 <= own[key] < 2**63:
                raise SerialException(f"virtual:// option {key} must be a non-negative "
                                      f"integer, not {value!r}")
        else:
            rest[key] = value
    return scene, own, rest


@functools.lru_cache(maxsize=16)
def _preset(spec: str) -> Scene:
    return load_scene(spec)


def _load(spec: str) -> Scene:
    """The scene of ``spec``; presets are built once per process (a Scene is frozen),
    files are read each time (they may change)."""
    name = spec.split("?", 1)[0]
    return load_scene(spec) if "/" in name or name.endswith(".toml") else _preset(spec)


class Serial(SerialBase):
    """pyserial port whose other end is the in-process virtual device."""

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        self._to_device: BytePipe | None = None
        self._from_device: BytePipe | None = None
        self._noise: LineNoise | None = None  # host -> device
        self._noise_up: LineNoise | None = None  # device -> host
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self.endpoint = None
        self.firmware = None
        self.line_baud: int | None = None
        super().__init__(*args, **kwargs)

    # ---- open / close -----------------------------------------------------------------
    def open(self) -> None:
        """Build the scene and the virtual board, start the device thread."""
        if self.is_open:
            raise SerialException("Port is already open.")
        if self._port is None:
            raise SerialException("Port must be configured before it can be used.")

        name, own, scene_opts = parse_url(self.portstr)
        seed = int(own.get("seed", 0))
        try:
            query = urllib.parse.urlencode(scene_opts)
            scene = _load(f"{name}?{query}" if query else name)
            rate, line_seed = own.get("line_error_rate", 0.0), int(own.get("line_seed", seed))
            # One noise per direction, each a function of its stream position only: the
            # same line_seed damages the same bits whatever the threads' timing.
            self._noise = LineNoise(rate, [line_seed, 0])
            self._noise_up = LineNoise(rate, [line_seed, 1])
            self.firmware = VirtualFirmware(scene, seed, engine=own.get("engine", "model"))
        except CdmaLidarError as exc:
            raise SerialException(f"virtual://{name}: {exc}") from exc
        baud = own.get("line_baud")
        self.line_baud = baud  # the host's reply timeouts count the line's transmit time
        try:
            self._to_device = BytePipe(noise=self._noise, baud=baud)
            self._from_device = BytePipe(noise=self._noise_up, baud=baud)
        except CdmaLidarError as exc:
            raise SerialException(f"virtual://{name}: {exc}") from exc
        dev_port = PipePort(self._to_device, self._from_device, f"virtual://{name}")
        self.endpoint = DeviceEndpoint(dev_port, self.firmware, session_id=own.get("session"))
        self._stop.clear()
        self._thread = threading.Thread(target=self.endpoint.serve_forever, args=(self._stop,),
                                        name=f"virtual-device-{name}", daemon=True)
        self._thread.start()
        self.is_open = True
        log.info("virtual device %s (seed %d, line error rate %g) started", name, seed,
                 self._noise.rate)

    def close(self) -> None:
        """Stop the device thread and close the pipes."""
        if self.is_open:
            self.is_open = False
            self._stop.set()
            for pipe in (self._to_device, self._from_device):
                if pipe is not None:
                    pipe.close()
            if self._thread is not None:
                self._thread.join(timeout=5.0)
        super().close()

    def from_url(self, url: str) -> str:
        """Check the URL (pyserial calls this through ``open``)."""
        parse_url(url)
        return url

    def _reconfigure_port(self) -> None:
        """Baud rate and framing mean nothing on an in-process line."""

    # ---- data -------------------------------------------------------------------------
    @property
    def in_waiting(self) -> int:
        """Bytes from the device ready to read."""
        if not self.is_open or self._from_device is None:
            raise PortNotOpenError()
        return self._from_device.available()

    def read(self, size: int = 1) -> bytes:
        """Up to ``size`` bytes; returns early at the port's timeout."""
        if not self.is_open or self._from_device is None:
            raise PortNotOpenError()
        return self._from_device.read(size, self._timeout)

    def write(self, data: bytes) -> int:
        """Send bytes to the device (through the line's bit errors)."""
        if not self.is_open or self._to_device is None:
            raise PortNotOpenError()
        raw = bytes(data)
        self._to_device.write(raw)  # through the line's bit errors
        return len(raw)

    def flush(self) -> None:
        """Nothing is buffered on this side."""

    def reset_input_buffer(self) -> None:
        """Drop bytes the device sent but nobody read."""
        if not self.is_open or self._from_device is None:
            raise PortNotOpenError()
        self._from_device.clear()

    def reset_output_buffer(self) -> None:
        """Nothing waits to be sent."""

    @property
    def out_waiting(self) -> int:
        """Nothing waits to be sent."""
        return 0

    # ---- modem lines (meaningless here, as in loop://) ---------------------------------
    def _update_break_state(self) -> None:
        pass

    def _update_rts_state(self) -> None:
        pass

    def _update_dtr_state(self) -> None:
        pass

    @property
    def cts(self) -> bool:
        return True

    @property
    def dsr(self) -> bool:
        return True

    @property
    def ri(self) -> bool:
        return False

    @property
    def cd(self) -> bool:
        return True

