"""Pictures of a scan as PNG, after the paper's Fig. 3 and 4d (matplotlib, Agg canvas).

Shen, Lim and Zhou, "Identity-enabled CDMA LiDAR for massively parallel ranging with a
single-element receiver": Fig. 3a is the cloud, 3c range and SNR_XC along one column,
3d a correlation trace (:func:`capture_plot`), 3e the range histogram, 4d the SNR_XC
maps of the near-far loop. :func:`scan_pictures` draws a scan's set:

=============  ===========================================================================
``_snr``       SNR_XC heatmap(s), dB, with the threshold contour (in the legend); one per
               frame with near-far (Fig. 4d)
``_depth``     range (m) per pixel, rejected pixels blank
``_3d``        the ranged points in 3D (equal scale) and seen from the sensor (Fig. 3a)
``_column``    range and SNR_XC of every channel along one column, threshold marked (3c)
``_hist``      histogram of the valid ranges (3e)
``_power``     near-far only: the power matrix of every frame (the loop's control variable)
=============  ===========================================================================

Images have angles on their axes when the beams' angles are known: elevation (deg, up)
from the grating and the channel's wavelength down the side (ring 0, the shortest
wavelength, is the top beam), azimuth (deg, left positive) from the column's grating
rotation across, drawn as the sensor sees the scene (left is left). Titles name the
scene (or device) and the frame. Every figure is written atomically.

Many channels (more than :data:`DENSE_ROWS`, e.g. paper-massive's 1,200): an image has
more rows than the picture has pixels, so it is antialiased (a one-channel feature shows
as a fainter line instead of vanishing between sampled rows), the SNR_XC map names its
threshold in the title instead of drawing a contour around every noisy pixel, the
column profile draws dots without joining lines, and the 3D view draws the far points
first so near objects stay visible in front of a wall. Ticks are matplotlib's few.
"""

from __future__ import annotations

import logging
import os
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import NDArray

from cdma_lidar.fileio import atomic_open
from cdma_lidar.host.pointcloud import PointCloud

if TYPE_CHECKING:
    from matplotlib.axes import Axes
    from matplotlib.figure import Figure
    from matplotlib.image import AxesImage

__all__ = ["Angles", "capture_plot", "column_profile", "depth_image", "power_maps",
           "range_histogram", "scan_pictures", "snr_heatmap", "snr_heatmaps", "view_3d"]

log = logging.getLogger(__name__)

#: Images with more rows than this are drawn as described in the module docstring.
DENSE_ROWS = 200


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


@dataclass(frozen=True)
class Angles:
    """Beam angles of the pixels, each (K, C) deg: elevation (up) and azimuth (left)."""

    elevation_deg: NDArray
    azimuth_deg: NDArray

    def extent(self) -> tuple[float, float, float, float] | None:
        """imshow extent (left, right, bottom, top) in deg: the middle channel's azimuths
        across, the middle column's elevations down; None when an angle is unknown."""
        el = np.asarray(self.elevation_deg)[:, self.elevation_deg.shape[1] // 2]
        az = np.asarray(self.azimuth_deg)[self.azimuth_deg.shape[0] // 2, :]
        if el.size < 2 or az.size < 2 or not (np.all(np.isfinite(el))
                                              and np.all(np.isfinite(az))):
            return None
        de, da = (el[-1] - el[0]) / (el.size - 1), (az[-1] - az[0]) / (az.size - 1)
        return (float(az[0] - da / 2), float(az[-1] + da / 2), float(el[-1] + de / 2),
                float(el[0] - de / 2))


def _image(ax: Axes, values: NDArray, angles: Angles | None, **kw: Any) -> AxesImage:
    """A (K, C) image with angle axes when known (module docstring), else indices."""
    ext = angles.extent() if angles is not None else None
    smooth = values.shape[0] > DENSE_ROWS   # more rows than pixels: average, do not skip
    im = ax.imshow(values, aspect="auto", interpolation="antialiased" if smooth else "nearest",
                   extent=ext, **kw)
    if ext is None:
        ax.set_xlabel("column")
        ax.set_ylabel("channel (ring 0 = top beam)")
    else:
        ax.set_xlabel("azimuth (deg, from the column; left +)")
        ax.set_ylabel("elevation (deg, from the grating)")
    return im


def _heat(ax: Axes, snr_db: NDArray, threshold_db: float, title: str,
          vmin: float, vmax: float, angles: Angles | None = None) -> AxesImage:
    im = _image(ax, snr_db, angles, cmap="viridis", vmin=vmin, vmax=vmax)
    finite = np.where(np.isfinite(snr_db), snr_db, vmin)
    if snr_db.shape[0] > DENSE_ROWS:
        title = f"{title}\nthreshold {threshold_db:.1f} dB"
    elif finite.min() < threshold_db < finite.max():
        ax.contour(finite, levels=[threshold_db], colors="w", linewidths=0.8,
                   extent=im.get_extent(), origin="upper")
        from matplotlib.lines import Line2D  # deferred with the rest of matplotlib (see _figure)

        ax.legend(handles=[Line2D([], [], color="w", lw=0.8,
                                  label=f"threshold {threshold_db:.1f} dB: pixels inside "
                                        "are kept")],
                  loc="lower left", fontsize=6, facecolor="0.3", labelcolor="w",
                  framealpha=0.8)
    ax.set_title(title, fontsize=9)
    return im


def snr_heatmaps(snr_db: Sequence[NDArray], threshold_db: float,
                 path: str | os.PathLike[str], titles: Sequence[str] | None = None,
                 per_row: int = 5, most: int = 10, angles: Angles | None = None,
                 suptitle: str = "") -> None:
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
        im = _heat(ax, maps[i], threshold_db, titles[i], vmin, vmax, angles)
        if i % cols:
            ax.set_ylabel("")
        if i < len(maps) - cols:
            ax.set_xlabel("")
    fig.colorbar(im, ax=axes.ravel().tolist(), label="SNR_XC (dB)", shrink=0.9)
    if suptitle:
        fig.suptitle(suptitle, fontsize=10)
    _save(fig, path)


def snr_heatmap(snr_db: NDArray, threshold_db: float, path: str | os.PathLike[str],
                title: str = "SNR_XC") -> None:
    """One SNR_XC heatmap (dB, (K, C)) with the threshold contour."""
    snr_heatmaps([snr_db], threshold_db, path, [title])


def depth_image(cloud: PointCloud, path: str | os.PathLike[str], title: str = "depth",
                angles: Angles | None = None) -> None:
    """Range (m) per pixel, channels down and columns across; pixels without a range blank."""
    fig = _figure(7, 3.6)
    ax = fig.subplots()
    im = _image(ax, np.where(cloud.has_range, cloud.range, np.nan), angles, cmap="turbo")
    ax.set_title(title, fontsize=10)
    fig.colorbar(im, ax=ax, label="range (m)")
    _save(fig, path)


def busiest_column(cloud: PointCloud) -> int:
    """The column with the most ranged pixels (ties: the one nearest the middle)."""
    count = cloud.has_range.sum(axis=0)
    c = count.size
    order = np.lexsort((np.abs(np.arange(c) - (c - 1) / 2), -count))
    return int(order[0])


def column_profile(cloud: PointCloud, column: int, threshold_db: float,
                   path: str | os.PathLike[str], title: str = "",
                   angles: Angles | None = None) -> None:
    """Fig. 3c: range (m) and SNR_XC (dB) of every channel along one column.

    Valid pixels are filled dots, rejected ones (below the threshold, ghosts) open
    circles at their measured range; the threshold is a dashed line on the SNR_XC axis.
    The x axis is the beam's elevation when known, else the channel.
    """
    k = cloud.shape[0]
    el = (np.asarray(angles.elevation_deg)[:, column] if angles is not None else None)
    use_el = el is not None and bool(np.all(np.isfinite(el)))
    x = el if use_el else np.arange(k)
    valid = (cloud.flags[:, column] == 0) & cloud.has_range[:, column]
    rng, snr = cloud.range[:, column], cloud.snr_xc[:, column]
    dense = k > DENSE_ROWS
    ms = 1.5 if dense else 3.5
    fig = _figure(7.5, 4.6)
    top, bottom = fig.subplots(2, 1, sharex=True)
    top.plot(x[valid], rng[valid], "o", ms=ms, color="tab:blue", label="valid")
    top.plot(x[~valid], rng[~valid], "o", ms=ms, mfc="none", color="tab:gray",
             label="rejected")
    top.set_ylabel("range (m)")
    top.legend(fontsize=7, loc="best")
    bottom.plot(x, snr, "." if dense else "-o", ms=2 if dense else 2.5, lw=0.8,
                color="tab:purple", label="SNR_XC")
    bottom.axhline(threshold_db, ls="--", color="tab:red", lw=0.9,
                   label=f"threshold {threshold_db:g} dB")
    bottom.set_ylabel("SNR_XC (dB)")
    bottom.legend(fontsize=7, loc="best")
    if use_el:
        bottom.set_xlabel("elevation (deg, from the grating; ring 0 at the right is the top)")
    else:
        bottom.set_xlabel("channel (ring 0 = top beam)")
    az = ""
    if angles is not None and np.isfinite(angles.azimuth_deg[k // 2, column]):
        az = f", azimuth {float(angles.azimuth_deg[k // 2, column]):.2f} deg"
    top.set_title(f"{title}{': ' if title else ''}column {column}{az} "
                  f"({int(valid.sum())} of {k} channels valid)", fontsize=10)
    _save(fig, path)


def range_histogram(cloud: PointCloud, path: str | os.PathLike[str], title: str = "",
                    bin_m: float = 0.02) -> None:
    """Fig. 3e: histogram of the valid ranges (bins of ``bin_m`` m)."""
    r = cloud.range[(cloud.flags == 0) & cloud.has_range]
    fig = _figure(6.5, 3.4)
    ax = fig.subplots()
    if r.size:
        lo, hi = float(r.min()), float(r.max())
        bins = np.arange(lo - bin_m, hi + 2 * bin_m, bin_m)
        ax.hist(r, bins=bins, color="tab:blue")
    ax.set_xlabel(f"range (m), {bin_m * 100:g} cm bins")
    ax.set_ylabel("pixels")
    ax.set_title(f"{title}{': ' if title else ''}range histogram of {r.size} valid pixels",
                 fontsize=10)
    _save(fig, path)


def power_maps(powers: Sequence[NDArray], path: str | os.PathLike[str],
               titles: Sequence[str], angles: Angles | None = None,
               per_row: int = 5, suptitle: str = "") -> None:
    """The near-far power matrix of every frame (fraction of the per-pixel maximum)."""
    maps = [np.asarray(p, dtype=np.float64) for p in powers]
    rows = -(-len(maps) // per_row)
    cols = -(-len(maps) // rows)
    fig = _figure(3.3 * cols + 1.2, 2.9 * rows + 0.3)
    axes = fig.subplots(rows, cols, squeeze=False, sharex=True, sharey=True)
    vmax = max(float(np.nanmax(m)) for m in maps) if maps else 1.0
    im = None
    for i, ax in enumerate(axes.ravel()):
        if i >= len(maps):
            ax.set_axis_off()
            continue
        im = _image(ax, maps[i], angles, cmap="magma", vmin=0.0, vmax=vmax)
        ax.set_title(f"{titles[i]}: column sum <= {float(maps[i].sum(axis=0).max()):.2f}",
                     fontsize=9)
        if i % cols:
            ax.set_ylabel("")
        if i < len(maps) - cols:
            ax.set_xlabel("")
    if im is not None:
        fig.colorbar(im, ax=axes.ravel().tolist(), label="power (of the per-pixel maximum)",
                     shrink=0.9)
    fig.suptitle(f"{suptitle}{': ' if suptitle else ''}near-far power matrix per frame",
                 fontsize=10)
    _save(fig, path)


def scan_pictures(paths: Mapping[str, Path], cloud: PointCloud,
                  snr_maps: Sequence[NDArray], threshold_db: float, *, title: str,
                  frame_titles: Sequence[str], angles: Angles | None = None,
                  powers: Sequence[NDArray] | None = None) -> list[Path]:
    """Draw a scan's pictures (module docstring) to ``paths``; returns the files written.

    ``cloud`` is the scan's (combined) cloud, ``snr_maps`` one SNR_XC map per frame
    drawn (titled ``frame_titles``), ``powers`` the near-far power matrix per frame (drawn
    and also saved as ``paths["power_npz"]``, with the SNR_XC maps), ``title`` names the
    scene and frame.
    """
    snr_heatmaps(snr_maps, threshold_db, paths["snr"],
                 [title] if len(snr_maps) == 1 else list(frame_titles),
                 angles=angles, suptitle="" if len(snr_maps) == 1 else title)
    depth_image(cloud, paths["depth"], f"{title}: range", angles)
    view_3d(cloud, paths["view"], title)
    col = busiest_column(cloud)
    column_profile(cloud, col, threshold_db, paths["column"], title, angles)
    range_histogram(cloud, paths["histogram"], title)
    files = [paths[k] for k in ("snr", "depth", "view", "column", "histogram")]
    if powers:
        power_maps(powers, paths["power"], frame_titles, angles, suptitle=title)
        with atomic_open(paths["power_npz"], "wb") as fh:
            np.savez(fh, power=np.stack([np.asarray(p) for p in powers]),
                     snr_xc_db=np.stack([np.asarray(m) for m in snr_maps]))
        files += [paths["power"], paths["power_npz"]]
    return files


#: Smallest share of the longest side the 3D view gives y and z (see :func:`view_3d`).
MIN_LATERAL = 0.3


def view_3d(cloud: PointCloud, path: str | os.PathLike[str], title: str = "") -> None:
    """3D scatter of the ranged points with equal axis scaling, and the front view beside it.

    Both coloured by range (m). The 3D box has the data's own proportions (1 m is as
    long on every axis), except that y and z are stretched to at least
    :data:`MIN_LATERAL` of the longest side when the scene is much deeper than wide
    (near-far: a near target and a far one would otherwise collapse to a line); the
    title then says so. The front view looks along x (y to the left, z up), as the
    sensor sees the scene.
    """
    from matplotlib import ticker  # deferred with the rest of matplotlib (see _figure)

    ok = cloud.has_range
    fig = _figure(11, 4.8)
    ax = fig.add_subplot(1, 2, 1, projection="3d")
    front = fig.add_subplot(1, 2, 2)
    if np.any(ok):
        far_first = np.argsort(-cloud.range[ok], kind="stable")  # near points drawn on top
        x, y, z, r = (v[ok][far_first] for v in (cloud.x, cloud.y, cloud.z, cloud.range))
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
        aspect = box / side
        stretched = np.array([False, *(aspect[1:] < MIN_LATERAL)])
        aspect[stretched] = MIN_LATERAL
        ax.set_box_aspect(aspect)
        short = aspect < 0.15   # too thin for tick labels: the span goes in the label
        front.scatter(y, z, c=r, s=3, cmap="turbo")
        front.set_aspect("equal", adjustable="box")
        front.invert_xaxis()    # y points left: looking from the sensor, left is left
        fig.colorbar(sc, ax=[ax, front], label="range (m)", shrink=0.8)
    else:
        span, short, centre, box = np.zeros(3), np.zeros(3, bool), np.zeros(3), np.ones(3)
        stretched = np.zeros(3, bool)
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
    scale = ("3D, equal scale: " if not stretched.any() else
             " and ".join(n.split()[0] for n, st in zip(names, stretched, strict=True) if st)
             + " stretched (not to scale): ")
    ax.set_title((f"{title}\n" if title else "") + scale + " x ".join(
        f"{n.split()[0]} {v:.2f} m" for n, v in zip(names, span, strict=True)), fontsize=10)
    front.set_xlabel("y left (m)")
    front.set_ylabel("z up (m)")
    front.set_title("front view (from the sensor)")
    _save(fig, path)


def capture_plot(cap: Mapping[str, Any], path: str | os.PathLike[str]) -> None:
    """A capture (:mod:`cdma_lidar.host.capture`) as a PNG.

    ``corr``: the correlation trace against range (m, lag in samples on top) with the
    reported peak marked, like the paper's Fig. 3d; the axis says whether the range is
    calibrated (``cap["calibrated"]``) or raw (the system delay still in it). ``raw``:
    the ADC codes against time (us), the first 2000 samples and the whole column's
    histogram beside them.
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
        if bool(cap.get("calibrated", False)):
            ax.set_xlabel("range (m, calibrated)")
        else:
            ax.set_xlabel("raw range (m, uncalibrated: includes the system delay; "
                          "--calibration removes it)")
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
