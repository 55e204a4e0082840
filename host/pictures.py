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
from typing import Any

import numpy as np
from matplotlib.axes import Axes
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure
from matplotlib.image import AxesImage
from numpy.typing import NDArray

from cdma_lidar.fileio import atomic_open
from cdma_lidar.host.pointcloud import PointCloud

__all__ = ["capture_plot", "depth_image", "snr_heatmap", "snr_heatmaps", "view_3d"]

log = logging.getLogger(__name__)


def _figure(width_in: float, height_in: float) -> Figure:
    """A figure on its own Agg canvas (no pyplot state, safe in threads and tests)."""
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
                 path: str | os.PathLike[str], titles: Sequence[str] | None = None) -> None:
    """Side-by-side SNR_XC heatmaps (dB, each (K, C)) on one colour scale, e.g. before/after."""
    maps = [np.asarray(s, dtype=np.float64) for s in snr_db]
    titles = list(titles) if titles is not None else [f"frame {i}" for i in range(len(maps))]
    vals = np.concatenate([m[np.isfinite(m)].ravel() for m in maps] + [np.zeros(1)])
    vmin, vmax = float(np.percentile(vals, 1)), float(np.percentile(vals, 99.5))
    fig = _figure(4.2 * len(maps) + 1, 3.6)
    axes = fig.subplots(1, len(maps), squeeze=False)
    im = None
    for ax, m, t in zip(axes[0], maps, titles, strict=True):
        im = _heat(ax, m, threshold_db, t, vmin, vmax)
    fig.colorbar(im, ax=axes[0].tolist(), label="SNR_XC (dB)")
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
    """3D scatter of the ranged points coloured by range (m)."""
    ok = cloud.has_range
    fig = _figure(7, 5)
    ax = fig.add_subplot(projection="3d")
    if np.any(ok):
        sc = ax.scatter(cloud.x[ok], cloud.y[ok], cloud.z[ok], c=cloud.range[ok], s=2,
                        cmap="turbo")
        fig.colorbar(sc, ax=ax, label="range (m)", shrink=0.7)
        span = np.array([np.ptp(v[ok]) for v in (cloud.x, cloud.y, cloud.z)])
        ax.set_box_aspect(np.maximum(span, 0.3 * span.max()) if span.max() > 0 else None)
    ax.set_xlabel("x forward (m)")
    ax.set_ylabel("y left (m)")
    ax.set_zlabel("z up (m)")
    ax.view_init(elev=12, azim=-160)
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
