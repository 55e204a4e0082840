"""Live view of a scan in rerun: the cloud, the range and SNR_XC images, the power matrix.

``cdma-lidar view --port URL [scan options]`` scans as ``scan`` does and sends every
frame, as it is finished, to a rerun recording (the ``rerun-sdk`` package, optional extra
``view``; imported when a view opens). One frame on the ``frame`` timeline (and the host's
clock on ``time``) logs these entities:

=================  ======================================================================
``cloud``          the points with a range, x forward, y left, z up (m), coloured by
                   range, SNR_XC, intensity or ring (``--color-by``); rerun shows each
                   point's fields
``color_scale``    the points' colour scale: a turbo bar (``color_scale/span``: the field
                   and the values at its two ends, in the field's unit)
``range``          range image (m), channels down, columns across; rejected pixels 0
``snr_xc``         SNR_XC image (dB), channels down, columns across
``power``          the (K, C) power matrix the frame was scanned with (fractions of the
                   per-pixel maximum): constant without ``--near-far``, the control
                   variable with it
``valid_percent``  pixels above the SNR_XC threshold, per cent (a time series)
``log``            one line per frame (valid pixels, largest column power sum)
=================  ======================================================================

Where it goes (any combination): ``--save FILE.rrd`` (open later with ``rerun FILE.rrd``),
``--web`` (a web viewer: open the printed URL; Ctrl-C ends it), ``--spawn`` (rerun's
native viewer window). With none of them: ``--spawn`` where there is a display, else
``--web``. The viewers are rerun's own command (``python -m rerun``, the pinned
``rerun-sdk``) in a child process, started with ``--bind``: everything served listens on
127.0.0.1 unless ``--bind`` names another address (rerun's in-process web server has no
bind address and would listen on every interface). A port already taken, or ``--spawn``
without a display, is refused before the scan starts. The 3D view's camera is aimed at
the first frame's points from behind, left and above, so the cloud fills the view.

The frames come from :func:`cdma_lidar.host.scan.run_scan`'s ``on_frame`` hook (the
viewer is a consumer of finished frames and needs nothing else of the scan).
"""

from __future__ import annotations

import argparse
import ipaddress
import logging
import os
import signal
import socket
import subprocess
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from cdma_lidar.errors import ConfigError, MissingExtra
from cdma_lidar.fileio import check_writable
from cdma_lidar.host.pointcloud import PointCloud
from cdma_lidar.host.settings import (
    COLOR_MAPS,
    DEFAULT_SNR_THRESHOLD_DB,
    GRPC_PORT,
    LOOPBACK,
    WEB_PORT,
)

__all__ = ["COLOR_BY", "ENTITIES", "LiveView", "ViewOptions", "check_port_free",
           "has_display", "view_options", "wait_forever"]

log = logging.getLogger(__name__)

#: What each logged entity path holds (the module docstring's table).
ENTITIES = ("cloud", "color_scale", "color_scale/span", "range", "snr_xc", "power",
            "valid_percent", "log")

#: Point colourings (the keys are :data:`cdma_lidar.host.settings.COLOR_MAPS`): field of
#: the cloud, the colour scale's fixed span (None: the frame's own 2nd to 98th
#: percentile) and its unit.
COLOR_BY: dict[str, tuple[str, tuple[float, float] | None, str]] = {
    "range": ("range", None, "m"),
    "snr": ("snr_xc", (0.0, 50.0), "dB"),   # the threshold (16) sits in the lower third
    "intensity": ("intensity", None, "intensity units"),
    "ring": ("ring", None, "channel"),
}
assert tuple(COLOR_BY) == COLOR_MAPS


@dataclass(frozen=True)
class ViewOptions:
    """Where the recording goes and how the points are coloured.

    Attributes:
        save: an .rrd file to write the recording to (None: no file).
        web: serve a web viewer from this process (gRPC on ``grpc_port``, HTTP on
            ``web_port``).
        spawn: start rerun's native viewer and stream to it.
        color_by: a key of :data:`COLOR_BY`.
        threshold_db: the SNR_XC threshold (dB) ``valid_percent`` counts above.
        grpc_port, web_port: the served ports (``spawn`` uses ``grpc_port + 1``).
        bind: the IP address served ports listen on (loopback unless asked).
    """

    save: str | None = None
    web: bool = False
    spawn: bool = False
    color_by: str = "range"
    threshold_db: float = DEFAULT_SNR_THRESHOLD_DB
    grpc_port: int = GRPC_PORT
    web_port: int = WEB_PORT
    bind: str = LOOPBACK

    def __post_init__(self) -> None:
        try:
            ipaddress.ip_address(self.bind)
        except ValueError:
            raise ConfigError(f"--bind must be an IP address (127.0.0.1, 0.0.0.0, ::1), not "
                              f"{self.bind!r}", field="bind") from None
        if self.color_by not in COLOR_BY:
            raise ConfigError(f"color_by must be one of {', '.join(COLOR_BY)}, not "
                              f"{self.color_by!r}", field="color_by")
        if self.save is not None and not self.save.lower().endswith(".rrd"):
            raise ConfigError(f"--save must be an .rrd file, not {self.save!r}", field="save")
        for name in ("grpc_port", "web_port"):
            port = getattr(self, name)
            if not 1 <= port <= 65535:
                raise ConfigError(f"{name} must be from 1 to 65535, not {port!r}", field=name)

    @property
    def host(self) -> str:
        """Where this machine reaches the served ports (loopback for a wildcard bind)."""
        return LOOPBACK if ipaddress.ip_address(self.bind).is_unspecified else self.bind

    def viewer_commands(self) -> list[list[str]]:
        """The rerun commands (argv) that serve the viewers asked for, bound to ``bind``."""
        rerun = [sys.executable, "-m", "rerun", "--bind", self.bind]
        out = []
        if self.web:
            out.append([*rerun, "--serve-web", "--port", str(self.grpc_port),
                        "--web-viewer-port", str(self.web_port)])
        if self.spawn:
            out.append([*rerun, "--port", str(self.grpc_port + 1)])
        return out

    def grpc_urls(self) -> list[str]:
        """The gRPC proxy URLs the recording streams to (one per viewer command)."""
        ports = [self.grpc_port] * self.web + [self.grpc_port + 1] * self.spawn
        return [f"rerun+http://{self.host}:{p}/proxy" for p in ports]


def check_port_free(bind: str, port: int, option: str) -> None:
    """ConfigError (one line) unless ``port`` can be listened on at ``bind``."""
    family = socket.AF_INET6 if ipaddress.ip_address(bind).version == 6 else socket.AF_INET
    with socket.socket(family, socket.SOCK_STREAM) as s:
        s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)  # as servers do: a port
        try:                                                      # in TIME_WAIT is free
            s.bind((bind, port))
        except OSError as exc:
            raise ConfigError(f"{option} {port} on {bind} is taken ({exc.strerror}): another "
                              f"program (another view?) listens there; choose another with "
                              f"{option}", field=option.lstrip("-")) from None


def _wait_listening(host: str, port: int, proc: Any, within_s: float = 60.0,
                    clock: Callable[[], float] = time.monotonic) -> None:
    """Return once ``host:port`` accepts connections; ConfigError if ``proc`` (the viewer
    serving it) ends first or ``within_s`` pass (rerun starts in about a second)."""
    end = clock() + within_s
    while True:
        try:
            socket.create_connection((host, port), timeout=1.0).close()
            return
        except OSError:
            if proc.poll() is not None or clock() > end:
                raise ConfigError(f"the web viewer (python -m rerun) did not listen on "
                                  f"{host}:{port}" + (f" (it ended with status "
                                  f"{proc.returncode})" if proc.poll() is not None else ""),
                                  field="web") from None
            time.sleep(0.05)


def _colors(values: NDArray[np.float64], span: tuple[float, float] | None) -> NDArray[np.uint8]:
    """RGB (N, 3) of ``values`` on matplotlib's turbo scale, over ``span`` (or 2-98 %)."""
    from matplotlib import colormaps  # deferred: only a view colours points

    if values.size == 0:
        return np.zeros((0, 3), np.uint8)
    lo, hi = span if span is not None else np.nanpercentile(values, [2.0, 98.0])
    t = np.clip((values - lo) / max(float(hi - lo), 1e-9), 0.0, 1.0)
    return (colormaps["turbo"](t)[:, :3] * 255).astype(np.uint8)


class LiveView:
    """A rerun recording that frames are logged to; use :meth:`log_frame` as ``on_frame``.

    ``rr`` is the ``rerun`` module (tests may pass it; by default it is imported here and
    a missing package is a :class:`MissingExtra` naming the extra ``view``). ``popen``
    starts the viewer commands (:meth:`ViewOptions.viewer_commands`; tests may pass a
    stand-in). ``color_by`` and ``threshold_db`` start as the options say and may be
    changed while frames come (:mod:`cdma_lidar.host.steer`).
    """

    def __init__(self, options: ViewOptions, *, rr: Any = None,
                 description: str = "cdma-lidar scan",
                 popen: Callable[..., Any] = subprocess.Popen) -> None:
        if rr is None:
            try:
                import rerun as rr  # optional extra `view`: loaded only when a view opens
            except ImportError as exc:
                raise MissingExtra("the live viewer", "rerun-sdk", "view") from exc
        if options.spawn and not has_display():
            raise ConfigError("--spawn needs a display (DISPLAY and WAYLAND_DISPLAY are "
                              "unset): use --web or --save FILE.rrd", field="spawn")
        if options.save is not None:
            check_writable(options.save, "--save")
        ports = ([("--grpc-port", options.grpc_port), ("--web-port", options.web_port)]
                 * options.web + [("--grpc-port", options.grpc_port + 1)] * options.spawn)
        for option, port in ports:
            check_port_free(options.bind, port, option)
        self.rr, self.options = rr, options
        self.color_by, self.threshold_db = options.color_by, options.threshold_db
        self.frames = 0
        self.url: str | None = None
        self._last: tuple[int, PointCloud] | None = None
        self.viewers = [popen(argv, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
                        for argv in options.viewer_commands()]
        self.rec = rr.RecordingStream("cdma-lidar")
        sinks = [rr.GrpcSink(url) for url in options.grpc_urls()]
        if options.save is not None:
            sinks.append(rr.FileSink(options.save))
        self.rec.set_sinks(*sinks, default_blueprint=self._blueprint())
        if options.web:
            try:
                for port in (options.grpc_port, options.web_port):
                    _wait_listening(options.host, port, self.viewers[0])
            except BaseException:
                self.viewers[0].terminate()
                raise
            self.url = (f"http://{options.host}:{options.web_port}/?url="
                        f"{options.grpc_urls()[0]}")
        self.rec.log("cloud", rr.ViewCoordinates.FLU, static=True)
        self.rec.log("description", rr.TextDocument(description), static=True)

    def _blueprint(self, eye: Any = None) -> Any:
        """Cloud and colour scale left; range, SNR_XC and power images and the valid-pixel
        series right. ``eye``: the 3D view's camera (None: rerun's default)."""
        rrb = self.rr.blueprint
        return rrb.Blueprint(rrb.Horizontal(
            rrb.Vertical(rrb.Spatial3DView(origin="cloud", name="cloud", eye_controls=eye),
                         rrb.Spatial2DView(origin="color_scale", name="colour scale"),
                         rrb.TextLogView(origin="log", name="frames"), row_shares=[6, 1, 1]),
            rrb.Vertical(rrb.Spatial2DView(origin="range", name="range (m)"),
                         rrb.TensorView(origin="snr_xc", name="SNR_XC (dB)"),
                         rrb.TensorView(origin="power", name="power (of max)"),
                         rrb.TimeSeriesView(origin="valid_percent", name="valid (%)")),
            column_shares=[3, 2]),
            rrb.BlueprintPanel(state="collapsed"), rrb.SelectionPanel(state="collapsed"),
            rrb.TimePanel(timeline="frame"))

    def frame_camera(self, cloud: PointCloud) -> None:
        """Aim the 3D camera at ``cloud``: at the middle of its points (2nd to 98th
        percentile box), from behind, left and above at about 0.8 times the box's largest
        side, so that both its depth and its width fill the view (a scan is a narrow cone:
        seen from the sensor its points would sit in a few degrees)."""
        ok = cloud.has_range
        if not ok.any():
            return
        xyz = np.stack([cloud.x[ok], cloud.y[ok], cloud.z[ok]], axis=1)
        lo, hi = np.percentile(xyz, [2.0, 98.0], axis=0)
        centre, size = (lo + hi) / 2, max(float(np.max(hi - lo)), 0.1)
        eye = centre + size * np.array([-0.5, 0.5, 0.3])
        self.rec.send_blueprint(self._blueprint(self.rr.blueprint.EyeControls3D(
            position=eye.tolist(), look_target=centre.tolist(), eye_up=[0.0, 0.0, 1.0])))

    def log_frame(self, index: int, cloud: PointCloud, power: NDArray[np.float64]) -> None:
        """Log one finished frame (the ``on_frame`` signature of ``run_scan``)."""
        rr, rec = self.rr, self.rec
        rec.set_time("frame", sequence=int(index))
        rec.set_time("time", timestamp=float(cloud.stamp_unix_s or time.time()))
        if self.frames == 0:
            self.frame_camera(cloud)
        self._log_cloud(cloud)
        ok = cloud.has_range
        rng = np.where(ok, cloud.range, 0.0).astype(np.float32)
        rec.log("range", rr.DepthImage(rng, meter=1.0, colormap="turbo"))
        snr = np.nan_to_num(cloud.snr_xc, nan=0.0).astype(np.float32)
        rec.log("snr_xc", rr.Tensor(snr, dim_names=("channel", "column")))
        rec.log("power", rr.Tensor(np.asarray(power, np.float32),
                                   dim_names=("channel", "column")))
        valid = 100.0 * float(np.mean(np.nan_to_num(cloud.snr_xc, nan=-np.inf)
                                      >= self.threshold_db))
        rec.log("valid_percent", rr.Scalars(valid))
        rec.log("log", rr.TextLog(
            f"frame {index}: {int(ok.sum())} points, {valid:.1f} % of pixels above "
            f"{self.threshold_db:g} dB, largest column power sum "
            f"{float(np.sum(power, axis=0).max()):.3g}"))
        self._last = (index, cloud)
        self.frames += 1

    def recolor(self, color_by: str) -> None:
        """Colour the points by ``color_by`` (a key of :data:`COLOR_BY`) from now on; the
        last frame's cloud is logged again in the new colours."""
        if color_by not in COLOR_BY:
            raise ConfigError(f"color must be one of {', '.join(COLOR_BY)}, not "
                              f"{color_by!r}", field="color_by")
        self.color_by = color_by
        if self._last is not None:
            self.rec.set_time("frame", sequence=self._last[0])
            self._log_cloud(self._last[1])

    def _log_cloud(self, cloud: PointCloud) -> None:
        """The points in the current colours, and the colour scale they use."""
        rr, rec = self.rr, self.rec
        ok = cloud.has_range
        field, span, unit = COLOR_BY[self.color_by]
        values = np.asarray(getattr(cloud, field), float)[ok]
        lo, hi = span if span is not None else (
            tuple(np.nanpercentile(values, [2.0, 98.0])) if values.size else (0.0, 1.0))
        xyz = np.stack([cloud.x[ok], cloud.y[ok], cloud.z[ok]], axis=1).astype(np.float32)
        rec.log("cloud", rr.Points3D(
            xyz, colors=_colors(values, (float(lo), float(hi))),
            radii=rr.Radius.ui_points(3.0)),
            rr.AnyValues(range_m=cloud.range[ok].astype(np.float32),
                         snr_xc_db=cloud.snr_xc[ok].astype(np.float32),
                         intensity=cloud.intensity[ok].astype(np.float32),
                         ring=cloud.ring[ok].astype(np.uint16),
                         column=cloud.column[ok].astype(np.uint16)))
        bar = np.repeat(_colors(np.linspace(0.0, 1.0, 256), (0.0, 1.0))[None], 12, axis=0)
        rec.log("color_scale", rr.Image(bar))
        rec.log("color_scale/span", rr.TextDocument(
            f"{self.color_by}: {float(lo):.4g} {unit} (left, blue) to {float(hi):.4g} "
            f"{unit} (right, red)"))

    def close(self, wait: Callable[[], None] | None = None) -> None:
        """Flush the recording; while serving a web viewer, ``wait()`` first (Ctrl-C), then
        end the web viewer (a native viewer window stays open until its user closes it)."""
        if self.options.web and wait is not None:
            try:
                wait()
            except KeyboardInterrupt:
                pass
        self.rec.flush()
        self.rec.disconnect()
        if self.options.web and self.viewers:
            self.viewers[0].terminate()
            self.viewers[0].wait()


def wait_forever() -> None:
    """Block until Ctrl-C (the web viewer is served while this process lives).

    Sleeps in short slices: Python raises KeyboardInterrupt when the main thread next
    runs Python code, and a SIGINT handled while that thread was not inside its sleep (on
    one of the viewer's threads, or just before the sleep began) does not interrupt the
    sleep; one sleep of an hour could hold it that long. (A command started in the
    background by a non-interactive shell inherits SIGINT ignored, and no Ctrl-C reaches
    it at all: SIGTERM, which ends the wait the same way, still does.)"""
    signal.signal(signal.SIGTERM, signal.default_int_handler)  # `kill` ends it as Ctrl-C
    while True:
        time.sleep(0.2)


def has_display() -> bool:
    """Whether a native viewer window could open here (X11 or Wayland)."""
    return bool(os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY"))


def view_options(args: argparse.Namespace, threshold_db: float) -> ViewOptions:
    """:class:`ViewOptions` from the parsed ``view`` arguments (the sink default applied)."""
    web, spawn = args.web, args.spawn
    if not (args.save or web or spawn):
        spawn, web = has_display(), not has_display()
    return ViewOptions(save=args.save, web=web, spawn=spawn, color_by=args.color_by,
                       threshold_db=threshold_db, grpc_port=args.grpc_port,
                       web_port=args.web_port, bind=args.bind)
