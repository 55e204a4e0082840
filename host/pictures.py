"""Pictures of a scan as PNG: SNR_XC heatmap, depth image, 3D view (matplotlib, Agg canvas).

The heatmap is the paper's Fig. 4d: channels down, columns across, SNR_XC in dB with
the threshold drawn as a contour. The depth image shows range (m) with rejected pixels
blank. The 3D view scatters the ranged points (x forward, y left, z up, in m) coloured
by range. Every figure is written atomically.
"""

from __future__ import annotations

import logging
import os
from collections.abc import Mapping, Sequence
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import NDArray

from cdma_lidar.fileio import atomic_open
from cdma_lidar.host.pointcloud import PointCloud

if TYPE_CHECKING:
    from matplotlib.axes import Axes
    from matplotlib.figure import Figure
    from matplotlib.image import AxesImage

__all__ = ["capture_plot", "depth_image", "snr_heatmap", "snr_heatmaps", "view_3d"]

log = logging.getLogger(__name__)


def _figure(width_in: float, height_in: float) -> Figure:
    """A figure on its own Agg canvas (no pyplot state, safe in threads and tests)."""
    # deferred: matplotlib costs 0.4 s, which every command would pay at start-up
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure  # (deferred, as above)

    fig = Figure(figsize=(width_in, height_in), layout="constrained")
    FigureCanvasAgg(fig)
    return fig


def _save(fig: Figure, path: str | os.PathLike[str]) -> None:
    with atomic_open(path, "wb") as fh:
        fig.savefig(fh, format="png", dpi=110)
    log.info("wrote %s", path)


def _heat(ax: Axes, snr_db: NDArray, threshold_db: float, title: str,
          vmin: float, vmax: float) -> AxesImage:
    im = ax.imshow(snr_db, aspect="auto", cmap="viridis", vmin=vmin, vmax=vmax,
                   interpolation="nearest")
    finite = np.where(np.isfinite(snr_db), snr_db, vmin)
    if finite.min() < threshold_db < finite.max():
        ax.contour(finite, levels=[threshold_db], colors="w", linewidths=0.6)
    ax.set_title(title)
    ax.set_xlabel("column")
    ax.set_ylabel("channel")
    return im


def snr_heatmaps(snr_db: Sequence[NDArray], threshold_db: float,
                 path: str | os.PathLike[str], titles: Sequence[str] | None = None,
                 per_row: int = 5, most: int = 10) -> None:
    """SNR_XC heatmaps (dB, each (K, C)) side by side on one colour scale (Fig. 4d).

    ``per_row`` maps per row; with more than ``most`` maps, ``most`` evenly spaced
    ones (the first and the last among them) are drawn.
    """
    maps = [np.asarray(s, dtype=np.float64) for s in snr_db]
    titles = list(titles) if titles is not None else [f"frame {i}" for i in range(len(maps))]
    if len(maps) > most:
        pick = np.unique(np.linspace(0, len(maps) - 1, most).round().astype(int))
        maps, titles = [maps[i] for i in pick], [titles[i] for i in pick]
    vals = np.concatenate([m[np.isfinite(m)].ravel() for m in maps] + [np.zeros(1)])
    vmin, vmax = float(np.percentile(vals, 1)), float(np.percentile(vals, 99.5))
    rows = -(-len(maps) // per_row)
    cols = -(-len(maps) // rows)
    fig = _figure(3.3 * cols + 1.2, 2.9 * rows + 0.3)
    axes = fig.subplots(rows, cols, squeeze=False, sharex=True, sharey=True)
    im = None
    for i, ax in enumerate(axes.ravel()):
        if i >= len(maps):
            ax.set_axis_off()
            continue
        im = _heat(ax, maps[i], threshold_db, titles[i], vmin, vmax)
        if i % cols:
            ax.set_ylabel("")
        if i < len(maps) - cols:
            ax.set_xlabel("")
    fig.colorbar(im, ax=axes.ravel().tolist(), label="SNR_XC (dB)", shrink=0.9)
    _save(fig, path)


def snr_heatmap(snr_db: NDArray, threshold_db: float, path: str | os.PathLike[str],
                title: str = "SNR_XC") -> None:
    """One SNR_XC heatmap (dB, (K, C)) with the threshold contour."""
    snr_heatmaps([snr_db], threshold_db, path, [title])


def depth_image(cloud: PointCloud, path: str | os.PathLike[str]) -> None:
    """Range (m) per pixel, channels down and columns across; pixels without a range blank."""
    fig = _figure(7, 3.6)
    ax = fig.subplots()
    im = ax.imshow(np.where(cloud.has_range, cloud.range, np.nan), aspect="auto",
                   cmap="turbo", interpolation="nearest")
    ax.set_xlabel("column")
    ax.set_ylabel("channel")
    ax.set_title("depth")
    fig.colorbar(im, ax=ax, label="range (m)")
    _save(fig, path)


def view_3d(cloud: PointCloud, path: str | os.PathLike[str]) -> None:
    """3D scatter of the ranged points with equal axis scaling, and the front view beside it.

    Both coloured by range (m). The 3D box has the data's own proportions (1 m is as
    long on every axis); the front view looks along x (y to the left, z up), as the
    sensor sees the scene.
    """
    from matplotlib import ticker  # deferred with the rest of matplotlib (see _figure)

    ok = cloud.has_range
    fig = _figure(11, 4.8)
    ax = fig.add_subplot(1, 2, 1, projection="3d")
    front = fig.add_subplot(1, 2, 2)
    if np.any(ok):
        x, y, z, r = cloud.x[ok], cloud.y[ok], cloud.z[ok], cloud.range[ok]
        sc = ax.scatter(x, y, z, c=r, s=2, cmap="turbo")
        lo = np.array([x.min(), y.min(), z.min()])
        span = np.array([np.ptp(v) for v in (x, y, z)])
        side = max(float(span.max()), 1e-3)
        # Equal scaling: every axis gets the same length per metre; a flat scene stays flat.
        box = np.maximum(span, 0.02 * side)
        centre = lo + span / 2
        for setter, c0, b0 in zip((ax.set_xlim, ax.set_ylim, ax.set_zlim), centre, box,
                                  strict=True):
            setter(c0 - b0 / 2, c0 + b0 / 2)
        ax.set_box_aspect(box / side)
        short = box / side < 0.15   # too thin for tick labels: the span goes in the label
        front.scatter(y, z, c=r, s=3, cmap="turbo")
        front.set_aspect("equal", adjustable="box")
        front.invert_xaxis()    # y points left: looking from the sensor, left is left
        fig.colorbar(sc, ax=[ax, front], label="range (m)", shrink=0.8)
    else:
        span, short, centre, box = np.zeros(3), np.zeros(3, bool), np.zeros(3), np.ones(3)
    names = ("x forward", "y left", "z up")
    for i, (axis, setter) in enumerate(zip((ax.xaxis, ax.yaxis, ax.zaxis),
                                           (ax.set_xlabel, ax.set_ylabel, ax.set_zlabel),
                                           strict=True)):
        axis.set_major_locator(ticker.MaxNLocator(3))
        if np.any(ok) and not short[i]:
            # Two ticks near the ends: the label in the middle never sits on one.
            axis.set_ticks(np.round(centre[i] + np.array([-0.3, 0.3]) * box[i], 2))
        if short[i]:
            axis.set_ticks([])   # the span is in the title instead of crowded ticks
        else:
            setter(f"{names[i]} (m)", labelpad=4)
    ax.tick_params(labelsize=7)
    ax.view_init(elev=18, azim=-150)
    ax.set_title("3D, equal scale: " + " x ".join(
        f"{n.split()[0]} {v:.2f} m" for n, v in zip(names, span, strict=True)), fontsize=10)
    front.set_xlabel("y left (m)")
    front.set_ylabel("z up (m)")
    front.set_title("front view (from the sensor)")
    _save(fig, path)


def capture_plot(cap: Mapping[str, Any], path: str | os.PathLike[str]) -> None:
    """A capture (:mod:`cdma_lidar.host.capture`) as a PNG.

    ``corr``: the correlation trace against range (m, lag in samples on top) with the
    reported peak marked, like the paper's Fig. 3d. ``raw``: the ADC codes against time
    (us), the first 2000 samples and the whole column's histogram beside them.
    """
    data = np.asarray(cap["data"])
    kind = str(cap["kind"])
    title = f"column {int(cap['column'])}"
    if kind == "corr":
        fig = _figure(7.5, 3.6)
        ax = fig.subplots()
        r = np.asarray(cap["range_m"])
        ax.plot(r, data, lw=0.7, color="tab:blue")
        pk = int(cap.get("peak_lag", -1))
        lag = np.asarray(cap["lag"])
        if pk >= 0 and lag[0] <= pk <= lag[-1]:
            i = pk - int(lag[0])
            ax.plot(r[i], data[i], "v", color="tab:red", ms=7)
            ax.annotate(f"peak: lag {pk}, {r[i]:.3f} m", (r[i], data[i]),
                        xytext=(8, -14), textcoords="offset points", fontsize=8)
        ax.set_xlabel("range (m)")
        ax.set_ylabel("correlation out (LSB)")
        ax.set_title(f"cross-correlation, {title} channel {int(cap['channel'])}")
        sec = ax.secondary_xaxis("top", functions=_lag_axis(r, lag))
        sec.set_xlabel("lag (samples)")
    else:
        fig = _figure(9, 3.4)
        ax, hx = fig.subplots(1, 2, width_ratios=[3, 1])
        n = min(data.size, 2000)
        t = np.arange(n) / float(cap["sample_rate_hz"]) * 1e6
        ax.plot(t, data[:n], lw=0.5, color="tab:blue")
        ax.set_xlabel("time (us)")
        ax.set_ylabel("ADC code")
        ax.set_title(f"raw ADC, {title} (first {n} of {data.size} samples)")
        hx.hist(data, bins=64, orientation="horizontal", color="tab:gray")
        hx.set_xlabel("samples")
        hx.set_title("all samples")
    _save(fig, path)


def _lag_axis(r: NDArray, lag: NDArray):
    """Forward and inverse maps between range (m) and lag (samples), both linear."""
    if r.size < 2:
        return (lambda x: x), (lambda x: x)
    a = (lag[-1] - lag[0]) / (r[-1] - r[0])
    return (lambda x: lag[0] + a * (np.asarray(x) - r[0]),
            lambda x: r[0] + (np.asarray(x) - lag[0]) / a)
