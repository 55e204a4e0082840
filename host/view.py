"""Live view of a scan in rerun: the cloud, the range and SNR_XC images, the power matrix.

``cdma-lidar view --port URL [scan options]`` scans as ``scan`` does and sends every
frame, as it is finished, to a rerun recording (the ``rerun-sdk`` package, optional extra
``view``; imported when a view opens). One frame on the ``frame`` timeline (and the host's
clock on ``time``) logs these entities:

=================  ======================================================================
``cloud``          the points with a range, x forward, y left, z up (m), coloured by
                   range or SNR_XC (``--color-by``); rerun shows each point's fields
``range``          range image (m), channels down, columns across; rejected pixels 0
``snr_xc``         SNR_XC image (dB), channels down, columns across
``power``          the (K, C) power matrix the frame was scanned with (fractions of the
                   per-pixel maximum): constant without ``--near-far``, the control
                   variable with it
``valid_percent``  pixels above the SNR_XC threshold, per cent (a time series)
``log``            one line per frame (valid pixels, largest column power sum)
=================  ======================================================================

Where it goes (any combination): ``--save FILE.rrd`` (open later with ``rerun FILE.rrd``),
``--web`` (a web viewer served from this process: open the printed URL; Ctrl-C ends it),
``--spawn`` (rerun's native viewer window). With none of them: ``--spawn`` where there
is a display, else ``--web``.

The frames come from :func:`cdma_lidar.host.scan.run_scan`'s ``on_frame`` hook (the
viewer is a consumer of finished frames and needs nothing else of the scan).
"""

from __future__ import annotations

import argparse
import logging
import os
import signal
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from cdma_lidar.errors import ConfigError, MissingExtra
from cdma_lidar.fileio import check_writable
from cdma_lidar.host.pointcloud import PointCloud
from cdma_lidar.host.ranging import DEFAULT_SNR_THRESHOLD_DB

__all__ = ["COLOR_BY", "ENTITIES", "LiveView", "ViewOptions", "add_view_options"]

log = logging.getLogger(__name__)

#: What each logged entity path holds (the module docstring's table).
ENTITIES = ("cloud", "range", "snr_xc", "power", "valid_percent", "log")

#: Point colourings: field of the cloud, and the colour scale's fixed span (None: the
#: frame's own 2nd to 98th percentile).
COLOR_BY: dict[str, tuple[str, tuple[float, float] | None]] = {
    "range": ("range", None),
    "snr": ("snr_xc", (0.0, 50.0)),   # dB: the threshold (16) sits in the lower third
}

#: rerun's default ports: gRPC (the log stream) and the web viewer (HTTP).
GRPC_PORT, WEB_PORT = 9876, 9090


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
    """

    save: str | None = None
    web: bool = False
    spawn: bool = False
    color_by: str = "range"
    threshold_db: float = DEFAULT_SNR_THRESHOLD_DB
    grpc_port: int = GRPC_PORT
    web_port: int = WEB_PORT

    def __post_init__(self) -> None:
        if self.color_by not in COLOR_BY:
            raise ConfigError(f"color_by must be one of {', '.join(COLOR_BY)}, not "
                              f"{self.color_by!r}", field="color_by")
        if self.save is not None and not self.save.lower().endswith(".rrd"):
            raise ConfigError(f"--save must be an .rrd file, not {self.save!r}", field="save")
        for name in ("grpc_port", "web_port"):
            port = getattr(self, name)
            if not 1 <= port <= 65535:
                raise ConfigError(f"{name} must be from 1 to 65535, not {port!r}", field=name)


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
    a missing package is a :class:`MissingExtra` naming the extra ``view``).
    """

    def __init__(self, options: ViewOptions, *, rr: Any = None,
                 description: str = "cdma-lidar scan") -> None:
        if rr is None:
            try:
                import rerun as rr  # optional extra `view`: loaded only when a view opens
            except ImportError as exc:
                raise MissingExtra("the live viewer", "rerun-sdk", "view") from exc
        self.rr = rr
        self.options = options
        self.frames = 0
        self.url: str | None = None
        self.rec = rr.RecordingStream("cdma-lidar")
        sinks = []
        if options.save is not None:
            check_writable(options.save, "--save")
            sinks.append(rr.FileSink(options.save))
        if options.web:   # loopback only: reach it from elsewhere through an SSH tunnel
            server = rr.GrpcServerSink(bind_ip="127.0.0.1", port=options.grpc_port)
            sinks.append(server)
        if options.spawn:
            self.rec.spawn(port=options.grpc_port + 1, connect=False)
            sinks.append(rr.GrpcSink(f"rerun+http://127.0.0.1:{options.grpc_port + 1}/proxy"))
        self.rec.set_sinks(*sinks, default_blueprint=self._blueprint())
        if options.web:
            rr.serve_web_viewer(web_port=options.web_port, open_browser=False,
                                connect_to=server.uri)
            self.url = f"http://127.0.0.1:{options.web_port}/?url={server.uri}"
        self.rec.log("cloud", rr.ViewCoordinates.FLU, static=True)
        self.rec.log("description", rr.TextDocument(description), static=True)

    def _blueprint(self) -> Any:
        """Cloud left; range, SNR_XC and power images and the valid-pixel series right."""
        rrb = self.rr.blueprint
        return rrb.Blueprint(rrb.Horizontal(
            rrb.Vertical(rrb.Spatial3DView(origin="cloud", name="cloud"),
                         rrb.TextLogView(origin="log", name="frames"), row_shares=[4, 1]),
            rrb.Vertical(rrb.Spatial2DView(origin="range", name="range (m)"),
                         rrb.TensorView(origin="snr_xc", name="SNR_XC (dB)"),
                         rrb.TensorView(origin="power", name="power (of max)"),
                         rrb.TimeSeriesView(origin="valid_percent", name="valid (%)")),
            column_shares=[3, 2]),
            rrb.BlueprintPanel(state="collapsed"), rrb.SelectionPanel(state="collapsed"),
            rrb.TimePanel(timeline="frame"))

    def log_frame(self, index: int, cloud: PointCloud, power: NDArray[np.float64]) -> None:
        """Log one finished frame (the ``on_frame`` signature of ``run_scan``)."""
        rr, rec = self.rr, self.rec
        rec.set_time("frame", sequence=int(index))
        rec.set_time("time", timestamp=float(cloud.stamp_unix_s or time.time()))
        ok = cloud.has_range
        field, span = COLOR_BY[self.options.color_by]
        xyz = np.stack([cloud.x[ok], cloud.y[ok], cloud.z[ok]], axis=1).astype(np.float32)
        rec.log("cloud", rr.Points3D(
            xyz, colors=_colors(np.asarray(getattr(cloud, field), float)[ok], span),
            radii=rr.Radius.ui_points(2.0)),
            rr.AnyValues(range_m=cloud.range[ok].astype(np.float32),
                         snr_xc_db=cloud.snr_xc[ok].astype(np.float32),
                         ring=cloud.ring[ok].astype(np.uint16),
                         column=cloud.column[ok].astype(np.uint16)))
        rng = np.where(ok, cloud.range, 0.0).astype(np.float32)
        rec.log("range", rr.DepthImage(rng, meter=1.0, colormap="turbo"))
        snr = np.nan_to_num(cloud.snr_xc, nan=0.0).astype(np.float32)
        rec.log("snr_xc", rr.Tensor(snr, dim_names=("channel", "column")))
        rec.log("power", rr.Tensor(np.asarray(power, np.float32),
                                   dim_names=("channel", "column")))
        valid = 100.0 * float(np.mean(np.nan_to_num(cloud.snr_xc, nan=-np.inf)
                                      >= self.options.threshold_db))
        rec.log("valid_percent", rr.Scalars(valid))
        rec.log("log", rr.TextLog(
            f"frame {index}: {int(ok.sum())} points, {valid:.1f} % of pixels above "
            f"{self.options.threshold_db:g} dB, largest column power sum "
            f"{float(np.sum(power, axis=0).max()):.3g}"))
        self.frames += 1

    def close(self, wait: Callable[[], None] | None = None) -> None:
        """Flush the recording; while serving a web viewer, ``wait()`` first (Ctrl-C)."""
        if self.options.web and wait is not None:
            try:
                wait()
            except KeyboardInterrupt:
                pass
        self.rec.flush()
        self.rec.disconnect()


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


def add_view_options(p: argparse.ArgumentParser) -> None:
    """``--save``, ``--web``, ``--spawn``, ``--color-by`` and the viewer's ports."""
    g = p.add_argument_group("viewer (rerun; pip install 'cdma-lidar[view]')")
    g.add_argument("--save", metavar="FILE.rrd",
                   help="write the recording to an .rrd file (open it with `rerun FILE.rrd`)")
    g.add_argument("--web", action="store_true",
                   help="serve a web viewer from this process and print its URL; Ctrl-C "
                        "ends it (the default without a display)")
    g.add_argument("--spawn", action="store_true",
                   help="open rerun's native viewer (the default with a display)")
    g.add_argument("--color-by", choices=tuple(COLOR_BY), default="range",
                   help="colour the points by range (default) or SNR_XC")
    g.add_argument("--web-port", type=int, default=WEB_PORT, metavar="PORT",
                   help=f"HTTP port of the web viewer (default {WEB_PORT})")
    g.add_argument("--grpc-port", type=int, default=GRPC_PORT, metavar="PORT",
                   help=f"port the web viewer reads the frames from (default {GRPC_PORT})")


def view_options(args: argparse.Namespace, threshold_db: float) -> ViewOptions:
    """:class:`ViewOptions` from the parsed ``view`` arguments (the sink default applied)."""
    web, spawn = args.web, args.spawn
    if not (args.save or web or spawn):
        spawn, web = has_display(), not has_display()
    return ViewOptions(save=args.save, web=web, spawn=spawn, color_by=args.color_by,
                       threshold_db=threshold_db, grpc_port=args.grpc_port,
                       web_port=args.web_port)
