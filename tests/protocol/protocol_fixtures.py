"""Test fixtures for the protocol: a synthetic device application, an in-memory lossy link,
and a device played by the test on a fake clock (:class:`ScriptedPort`).

``SyntheticApp`` is a small but complete :class:`cdma_lidar.protocol.endpoint.DeviceApp` whose
columns are a pure function of (frame, column, config), so a test can recompute
what every received column must be. The lossy in-memory link is
:func:`cdma_lidar.virtual.line.pipe_pair`.
"""

from __future__ import annotations

import threading
import time
import weakref
from collections.abc import Callable, Iterator
from typing import Any

import numpy as np

from cdma_lidar.errors import ConfigError, DeviceError, out_of_range
from cdma_lidar.protocol.columns import ColumnResult
from cdma_lidar.protocol.endpoint import DeviceApp, DeviceEndpoint, Engine
from cdma_lidar.protocol.framing import Frame, FrameDecoder, encode_frame
from cdma_lidar.protocol.link import HostLink
from cdma_lidar.protocol.messages import CaptureKind, ErrorCode, Info, MsgType, encode_payload
from cdma_lidar.virtual.line import pipe_pair


# ---- synthetic device application ------------------------------------------------------
def expected_column(frame: int, column: int, channels: int, peaks: int, uid_bits: int,
                    calibration: bool = False) -> ColumnResult:
    """The column SyntheticApp produces: deterministic in its arguments."""
    rng = np.random.default_rng([frame, column, channels, peaks, uid_bits, int(calibration)])
    k, e, n = channels, peaks - 1, uid_bits
    return ColumnResult.from_arrays(
        frame, column, (column * 0.05 % 360.0 - 20.0) if not calibration else 0.0,
        peak_lag=rng.integers(0, 8000, k), peak=rng.integers(-(2**31), 2**31, k),
        neighbours=rng.integers(-(2**31), 2**31, (k, 2)), noise_count=rng.integers(1, 65, k),
        noise_sum=rng.integers(-(2**20), 2**20, k), noise_sumsq=rng.integers(2**40, 2**62, k),
        uid_signs=rng.integers(-1, 2, (k, n)), uid_observed=rng.integers(0, 1 << n, k),
        uid_match=rng.integers(0, 2, k).astype(bool),
        saturated=rng.integers(0, 2, k).astype(bool),
        extra_lag=rng.integers(0, 8000, (k, e)) if e else None,
        extra_peak=rng.integers(-1000, 1000, (k, e)) if e else None,
        extra_signs=rng.integers(-1, 2, (k, e, n)) if e else None,
        calibration=calibration, timestamp_us=column * 1000)


class SyntheticApp(DeviceApp):
    """A device application for tests: validated config, power store, columns, captures."""

    def __init__(self, channels: int = 8, columns: int = 64, column_delay_s: float = 0.0) -> None:
        self.channels = channels
        self.columns = columns
        self.column_delay_s = column_delay_s
        self.tick: Callable[[], None] | None = None
        self.config: dict[str, Any] = {
            "poly_u": (11, 2), "poly_v": (11, 8, 5, 2), "code_index": tuple(range(channels)),
            "uid_bits": 1, "uid": 0, "samples_per_chip": 4, "averages": 10, "adc_bits": 12,
            "gate_start": 0, "gate_len": 64, "peak_exclude": 8, "ghost_windows": (),
            "out_shift": 0, "rounding": "truncate", "out_bits": 32, "peaks": 1,
            "columns_per_frame": columns, "mode": "ranging", "cancel_rounds": 0,
            "cancel_snr_q8": 10192}
        self.power = np.full((channels, columns), 65535, dtype=np.uint16)
        self.set_config_calls = 0
        self.scan_calls = 0
        self.aborts = 0
        self.fail_at: int | None = None  # column at which the generator raises

    def info(self) -> Info:
        return Info.nominal(
            serial="SYN-0001", firmware_version="test-1.0",
            wavelengths_m=1570e-9 + 0.875e-9 * np.arange(self.channels), grooves_per_mm=600.0,
            incidence_deg=60.0, tilt_deg=None, reference_wavelength_m=1587e-9,
            chip_rate_hz=1e9, column_start_deg=-20.0, column_step_deg=0.05,
            column_count=self.columns, max_channels=self.channels, adc_bits=12)

    def get_config(self) -> dict[str, Any]:
        return dict(self.config)

    def set_config(self, values: dict[str, Any]) -> None:
        new = dict(self.config)
        new.update(values)
        if not 1 <= new["peaks"] <= 8:
            raise out_of_range("peaks", "an integer from 1 to 8", new["peaks"])
        if not 1 <= new["uid_bits"] <= 8:
            raise out_of_range("uid_bits", "an integer from 1 to 8", new["uid_bits"])
        if len(new["code_index"]) != self.channels:
            raise ConfigError(f"code_index must have {self.channels} items", "code_index")
        self.set_config_calls += 1
        self.config = new

    def set_power(self, channel_start: int, column_start: int, power: np.ndarray) -> None:
        r, c = power.shape
        if channel_start + r > self.channels or column_start + c > self.columns:
            raise out_of_range("channel_start", f"a rectangle inside ({self.channels}, "
                               f"{self.columns})", (channel_start, column_start, r, c))
        self.power[channel_start:channel_start + r, column_start:column_start + c] = power

    def get_power(self) -> np.ndarray:
        return self.power.copy()

    def _columns(self, frame: int, first: int, count: int,
                 calibration: bool) -> Iterator[ColumnResult]:
        for col in range(first, first + count):
            if col == self.fail_at:
                raise RuntimeError(f"sensor fault at column {col}")
            if self.column_delay_s:
                time.sleep(self.column_delay_s)
            if self.tick is not None:  # a column takes time on an injected clock
                self.tick()
            yield expected_column(frame, col, self.channels, self.config["peaks"],
                                  self.config["uid_bits"], calibration)

    def scan(self, frame: int, first_column: int, columns: int) -> Iterator[ColumnResult]:
        if first_column + columns > self.columns:
            raise out_of_range("columns", f"at most {self.columns - first_column}", columns)
        self.scan_calls += 1
        return self._columns(frame, first_column, columns, False)

    def calibrate(self, frame: int, shots: int) -> Iterator[ColumnResult]:
        return self._columns(frame, 0, shots, True)

    def capture(self, kind: CaptureKind, column: int, channel: int) -> np.ndarray:
        if column >= self.columns:
            raise DeviceError("no such column", code=ErrorCode.OUT_OF_RANGE, field="column")
        rng = np.random.default_rng([int(kind), column, channel])
        if kind == CaptureKind.RAW:
            return rng.integers(-2048, 2048, 20000).astype(np.int16)
        return rng.integers(-(2**40), 2**40, 3000)

    def abort(self) -> None:
        self.aborts += 1


def capture_expected(kind: CaptureKind, column: int, channel: int) -> np.ndarray:
    """What SyntheticApp.capture returns."""
    return SyntheticApp(1, column + 1).capture(kind, column, channel)


class RunningDevice:
    """A DeviceEndpoint serving in a daemon thread; use as a context manager."""

    def __init__(self, port: Any, app: DeviceApp, **kw: Any) -> None:
        self.endpoint = DeviceEndpoint(port, app, **kw)
        self.stop = threading.Event()
        self.thread = threading.Thread(target=self.endpoint.serve_forever, args=(self.stop,),
                                       daemon=True)

    def __enter__(self) -> DeviceEndpoint:
        self.thread.start()
        return self.endpoint

    def __exit__(self, *exc: object) -> None:
        self.stop.set()
        self.thread.join(2.0)


def hello_fields(nonce: int, max_frame: int = 65535, flags: int = 0) -> dict[str, Any]:
    """HELLO payload fields of a keyless host whose nonce is derived from ``nonce``."""
    return {"host_max_frame": max_frame, "flags": flags,
            "host_nonce": nonce.to_bytes(16, "little"), "device_nonce": bytes(16),
            "mac": bytes(32)}


# ---- a device played by the test, in the host's thread, on a fake clock -----------------
class FakeClock:
    """Seconds that pass only while the host waits (:class:`ScriptedPort` moves them)."""

    def __init__(self) -> None:
        self.now = 0.0

    def __call__(self) -> float:
        return self.now


class ScriptedPort:
    """The host's port onto a device that the test plays, with no thread and no real time.

    ``answer(frame)`` gets each frame the host writes (also kept in ``requests``) and
    returns the bytes the device sends back (b"": none). A read that finds nothing
    queued moves ``clock`` on by ``timeout`` (the host's poll, s) and queues
    ``idle(now)``: what the device sends by itself by then (heartbeats, slow columns).
    Timeouts and deadlines are then exact and independent of the machine's load.
    """

    name = "script://device"

    def __init__(self, answer: Callable[[Frame], bytes] | None = None,
                 idle: Callable[[float], bytes] | None = None, data: bytes = b"") -> None:
        self.clock = FakeClock()
        self.timeout = 0.05
        self.answer = answer or (lambda frame: b"")
        self.idle = idle or (lambda now: b"")
        self.requests: list[Frame] = []
        self._decoder = FrameDecoder()
        self._buf = bytearray(data)

    @property
    def in_waiting(self) -> int:
        return len(self._buf)

    def write(self, data: bytes) -> int:
        for frame in self._decoder.feed(data):
            self.requests.append(frame)
            self._buf += self.answer(frame)
        return len(data)

    def read(self, n: int = 1) -> bytes:
        if not self._buf:
            self.clock.now += self.timeout
            self._buf += self.idle(self.clock.now)
            return b""
        out = bytes(self._buf[:n])
        del self._buf[:n]
        return out

    def close(self) -> None:
        """Nothing to close."""


def scripted_link(port: ScriptedPort, session: int = 0x42, **kw: Any) -> HostLink:
    """A HostLink on ``port``'s clock, in session ``session`` of a SyntheticApp device, as
    if HELLO and CONFIG_GET had gone before."""
    link = HostLink(port, clock=port.clock, **kw)
    link.session = session
    link.info = SyntheticApp().info()
    link.config = SyntheticApp().get_config()
    return link


def reply(t: MsgType, fields: Any, seq: int, session: int = 0x42) -> bytes:
    """Wire bytes of a device frame of type ``t`` (fields: a dict, a Status or a column)."""
    fields = fields.to_fields() if hasattr(fields, "to_fields") else fields
    return encode_frame(t, encode_payload(t, fields), seq, session)


def ack(req: Frame, session: int = 0x42) -> bytes:
    """The ACK of request ``req``."""
    return encode_frame(MsgType.ACK, bytes([req.msg_type]), req.seq, session)
#: The endpoints of SteppedDevices (weakly: a test need not close them), by their core.
_LOOPS: weakref.WeakKeyDictionary[Any, list[weakref.ref]] = weakref.WeakKeyDictionary()


class SteppedDevice:
    """A DeviceEndpoint behind the host end of a pipe, stepped by the host's reads on an
    injected clock, with no thread: its engine runs each step at once.

    The object is the host's port: every ``read`` or ``in_waiting`` first runs one turn
    of the device's loop (:meth:`DeviceEndpoint.poll`: it reads the requests, answers
    them, computes and sends the next column of a running stream), and of every other
    SteppedDevice's on the same core first, as their loops would run meanwhile. A read
    that finds nothing moves the shared clock ``now`` on by ``tick_s``, so host
    timeouts, heartbeats and idle limits come due without real waiting. Give the host
    ``clock=dev.clock``.
    """

    def __init__(self, app: DeviceApp | None, *, tick_s: float = 0.001,
                 now: list[float] | None = None, faults: Any = None, seed: int = 0,
                 max_read: int | None = None, **kw: Any) -> None:
        self.now = [100.0] if now is None else now  # shared by devices of one core
        self.tick_s, self.max_read = tick_s, max_read  # max_read: partial reads, as pyserial's
        self.host, dev = pipe_pair(faults, faults, seed=seed)  # the same Faults both ways
        self.name = "stepped://device"
        self.timeout: float | None = 0.0
        if "core" not in kw:
            kw["engine"] = Engine(threaded=False)
        self.endpoint = DeviceEndpoint(dev, app, clock=self.clock, poll_s=0.0, **kw)
        self.loops = _LOOPS.setdefault(self.endpoint.core, [])  # of the core's devices
        self.loops.append(weakref.ref(self.endpoint))

    def _poll(self) -> None:
        others = [e for e in (r() for r in self.loops) if e not in (None, self.endpoint)]
        for ep in [*others, self.endpoint]:
            ep.poll()

    def clock(self) -> float:
        return self.now[0]

    @property
    def rx(self) -> Any:
        """The pipe the host reads (a test injects frames into it)."""
        return self.host.rx

    @property
    def in_waiting(self) -> int:
        self._poll()
        return self.host.rx.available()

    def read(self, n: int = 1) -> bytes:
        self._poll()
        data = self.host.rx.read(min(n, self.max_read or n), 0)
        if not data:
            self.now[0] += self.tick_s
        return data

    def write(self, data: bytes) -> int:
        return self.host.write(data)

    def flush(self) -> None:
        """Nothing to flush."""

    def close(self) -> None:
        self.__exit__()
        self.host.close()

    def __enter__(self) -> DeviceEndpoint:
        return self.endpoint

    def __exit__(self, *exc: object) -> None:
        self.endpoint.close()
        self.loops[:] = [r for r in self.loops if r() not in (None, self.endpoint)]
