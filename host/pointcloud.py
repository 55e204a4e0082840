"""Point clouds: ranges plus grating geometry to 3D points, with the fields LiDAR tools read.

A :class:`PointCloud` is organised like the scan: ``(K channels, C columns)`` arrays,
one per point field, plus optional *extra* points (other users' returns kept with
``--keep-foreign``) that belong to no pixel. Every file format writes the same fields,
:data:`POINT_FIELDS`, under the same names:

==========  ======  ====================================================================
x y z       f4      m, sensor frame: x forward, y left, z up, origin at the grating
intensity   f4      reflectance estimate from peak, range and power
                    (:mod:`cdma_lidar.host.intensity`; about rho cos(theta) once calibrated)
t           f4      s from the frame's first column, from the device's column timestamps
ring        u2      channel k (the laser line; what odometry calls the ring)
range       f4      m, calibrated
snr_xc      f4      dB (eq. 44)
flags       u2      bitfield, :data:`FLAG_BITS` (0: valid measured point)
column      u2      grating column
user_id     i4      UID of the user whose code matched (ours, or a kept foreign return);
                    -1 where nothing matched
peak        i4      correlation peak (correlator units)
==========  ======  ====================================================================

Pixels without a range have NaN coordinates (organised formats keep them, the others
leave them out). The file formats are in :mod:`cdma_lidar.host.cloud_formats`.
"""

from __future__ import annotations

import importlib.metadata
import json
import logging
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from cdma_lidar.errors import ConfigError, MissingExtra
from cdma_lidar.host.ranging import (
    FLAG_FOREIGN,
    FLAG_GHOST,
    FLAG_INTERPOLATED,
    FLAG_REJECTED,
    FLAG_SATURATED,
    RangeImage,
    lag_to_range_m,
)
from cdma_lidar.optics.grating import GratingGeometry

__all__ = ["FIELD_UNITS", "FLAG_BITS", "POINT_FIELDS", "PointCloud", "assemble", "column_times_s",
           "empty_records", "file_metadata"]

log = logging.getLogger(__name__)

#: Per-point fields in file order with their numpy type (every format writes these).
POINT_FIELDS: tuple[tuple[str, str], ...] = (
    ("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("intensity", "<f4"), ("t", "<f4"),
    ("ring", "<u2"), ("range", "<f4"), ("snr_xc", "<f4"), ("flags", "<u2"),
    ("column", "<u2"), ("user_id", "<i4"), ("peak", "<i4"),
)

#: Unit and a short description (at most 32 characters: LAS extra-bytes descriptions) of
#: every field of :data:`POINT_FIELDS`, as the files say it (module docstring's table).
FIELD_UNITS: dict[str, tuple[str, str]] = {
    "x": ("m", "forward, sensor frame"),
    "y": ("m", "left, sensor frame"),
    "z": ("m", "up, sensor frame"),
    "intensity": ("intensity_unit", "reflectance estimate"),
    "t": ("s", "time from the frame's start"),
    "ring": ("channel", "channel k (laser line)"),
    "range": ("m", "calibrated range"),
    "snr_xc": ("dB", "SNR_XC of the peak (eq. 44)"),
    "flags": ("bitfield", "1int 2rej 4for 8gh 16sat, 0 ok"),
    "column": ("column", "grating column"),
    "user_id": ("UID", "matched user's UID, -1 none"),
    "peak": ("correlator units", "correlation peak"),
}

#: The ``flags`` bitfield (a point with flags 0 is a valid measured point).
FLAG_BITS: dict[str, int] = {
    "interpolated": FLAG_INTERPOLATED,   # 1: range filled from the column's neighbours
    "rejected": FLAG_REJECTED,           # 2: below the threshold or unsupported: no range
    "foreign": FLAG_FOREIGN,             # 4: another user's return (UID not ours)
    "ghost": FLAG_GHOST,                 # 8: inside a known grating-ghost lag window
    "saturated": FLAG_SATURATED,         # 16: the peak's out word at a rail: lag may be early
}

_WRAP = 2**32


def file_metadata(snr_threshold_db: float, intensity_unit: str) -> dict[str, str]:
    """What every recording says about its points (string keys to JSON text).

    ``cdma_lidar_version``; ``snr_threshold_db``, the SNR_XC threshold (dB) the ranges
    were accepted with; ``intensity_unit``; ``field_units``, each field of
    :data:`POINT_FIELDS` to its unit (:data:`FIELD_UNITS`; ``intensity`` in
    ``intensity_unit``).
    """
    units = {n: (intensity_unit if u == "intensity_unit" else u)
             for n, (u, _) in FIELD_UNITS.items()}
    doc = {"cdma_lidar_version": importlib.metadata.version("cdma-lidar"),
           "snr_threshold_db": float(snr_threshold_db),
           "intensity_unit": intensity_unit, "field_units": units}
    return {k: json.dumps(v) for k, v in doc.items()}


def column_times_s(timestamp_us: ArrayLike, done: ArrayLike) -> NDArray[np.float64]:
    """Seconds of each column after the frame's earliest column (device clock, u32 us).

    The device clock wraps every 2^32 us; differences are taken modulo 2^32 around the
    first column that arrived, so a frame that spans a wrap keeps increasing times.
    Columns that never arrived get NaN.
    """
    ts = np.asarray(timestamp_us, dtype=np.int64)
    ok = np.asarray(done, dtype=bool)
    out = np.full(ts.shape, np.nan)
    if not np.any(ok):
        return out
    ref = ts[np.flatnonzero(ok)[0]]
    d = ((ts - ref + _WRAP // 2) % _WRAP) - _WRAP // 2
    out[ok] = (d[ok] - d[ok].min()) * 1e-6
    return out


def empty_records(n: int = 0) -> NDArray:
    """A structured array of ``n`` points with :data:`POINT_FIELDS` (zeros)."""
    return np.zeros(n, dtype=list(POINT_FIELDS))


@dataclass
class PointCloud:
    """An organised point cloud: every point field (K, C), plus per-channel and per-column data.

    ``extra`` holds points that belong to no pixel (kept foreign returns), as records
    with :data:`POINT_FIELDS`. ``stamp_unix_s`` is the host's clock (UTC, s) when the
    frame's first column arrived: ``t`` counts from there.
    """

    x: NDArray[np.float64]
    y: NDArray[np.float64]
    z: NDArray[np.float64]
    intensity: NDArray[np.float64]
    t: NDArray[np.float64]
    ring: NDArray[np.int64]
    range: NDArray[np.float64]
    snr_xc: NDArray[np.float64]
    flags: NDArray[np.uint16]
    column: NDArray[np.int64]
    user_id: NDArray[np.int64]
    peak: NDArray[np.int64]
    wavelengths_m: NDArray[np.float64]
    angles_deg: NDArray[np.float64]
    stamp_unix_s: float = 0.0
    extra: NDArray = field(default_factory=empty_records)

    @property
    def shape(self) -> tuple[int, int]:
        """(K channels, C columns)."""
        return self.range.shape  # type: ignore[return-value]

    @property
    def has_range(self) -> NDArray[np.bool_]:
        """Pixels with finite coordinates (valid or interpolated)."""
        return np.isfinite(self.range) & np.isfinite(self.x)

    def grid_records(self) -> NDArray:
        """All K*C pixels as records, row-major (channel, then column); NaN x y z where no range."""
        rec = empty_records(self.range.size)
        for name, _ in POINT_FIELDS:
            rec[name] = np.asarray(getattr(self, name)).ravel()
        return rec

    def records(self, keep_rejected: bool = False) -> NDArray:
        """Structured array of points: the pixels (row-major), then the extra points.

        Pixels without a range are left out unless ``keep_rejected`` (then x y z are NaN).
        """
        rec = self.grid_records()
        if not keep_rejected:
            rec = rec[self.has_range.ravel()]
        if self.extra.size:
            rec = np.concatenate([rec, self.extra.astype(rec.dtype)])
        return rec

    def to_numpy(self, fields: tuple[str, ...] = ("x", "y", "z"),
                 keep_rejected: bool = False) -> NDArray[np.float64]:
        """``(N, len(fields))`` float64 array of the points :meth:`records` holds.

        Default: x y z in m of every point with a range (N rows, one per point, pixels
        row-major then the extra points), as Open3D, numpy and most LiDAR code take them.
        Any of :data:`POINT_FIELDS` may be named (``("x", "y", "z", "intensity")``).
        """
        names = [name for name, _ in POINT_FIELDS]
        unknown = [f for f in fields if f not in names]
        if unknown or not fields:
            raise ConfigError(f"fields must be some of {', '.join(names)}, not "
                              f"{list(fields)!r}", field="fields")
        rec = self.records(keep_rejected)
        return np.stack([rec[f].astype(np.float64) for f in fields], axis=1)

    def to_open3d(self) -> Any:
        """The points with a range as an ``open3d.t.geometry.PointCloud`` (tensor API).

        ``positions`` are x y z (m, float32); every other field of :data:`POINT_FIELDS`
        is an attribute of shape (N, 1) under its own name (``pcd.point.intensity``,
        ``pcd.point.ring``, ...), as Open3D's own PCD and PLY readers name them.
        ``.to_legacy()`` gives the ``open3d.geometry.PointCloud`` that
        ``draw_geometries`` shows. Needs the extra ``open3d``.
        """
        try:
            import open3d as o3d  # optional extra `open3d`: loaded only on the first call
        except ImportError as exc:
            raise MissingExtra("PointCloud.to_open3d()", "open3d", "open3d") from exc
        rec = self.records()
        pcd = o3d.t.geometry.PointCloud()
        pcd.point.positions = o3d.core.Tensor(
            np.stack([rec["x"], rec["y"], rec["z"]], axis=1).astype(np.float32))
        for name, dtype in POINT_FIELDS[3:]:
            column = np.ascontiguousarray(rec[name].astype(np.dtype(dtype).newbyteorder("=")))
            pcd.point[name] = o3d.core.Tensor(column.reshape(-1, 1))
        return pcd


def assemble(image: RangeImage, geometry: GratingGeometry, wavelengths_m: ArrayLike,
             angles_deg: ArrayLike, *, timestamps_us: ArrayLike | None = None,
             done: ArrayLike | None = None, intensity: ArrayLike | None = None,
             keep_foreign: bool = False, stamp_unix_s: float = 0.0) -> PointCloud:
    """Place every ranged pixel in 3D: ``range * direction(wavelength, rotation)`` (eqs. 45-49).

    ``timestamps_us`` (C,) are the device's column timestamps (``t`` is 0 without them),
    ``done`` (C,) which columns arrived, ``intensity`` (K, C) the reflectance estimate
    (NaN without it). With ``keep_foreign`` other users' returns become extra points
    with their ``user_id`` and flag 4 (their ranges use our calibration).
    """
    wl = np.asarray(wavelengths_m, dtype=np.float64)
    ang = np.asarray(angles_deg, dtype=np.float64)
    k, c = image.range_m.shape
    if wl.shape != (k,):
        raise ConfigError(f"wavelengths_m must have {k} entries (one per channel), not {wl.size}",
                          field="wavelengths_m")
    if ang.shape != (c,):
        raise ConfigError(f"angles_deg must have {c} entries (one per column), not {ang.size}",
                          field="angles_deg")
    rng = image.range_m
    known = np.isfinite(ang)
    pts = np.full((k, c, 3), np.nan)
    if np.any(known):
        dirs = geometry.directions(wl[:, None], ang[None, known])
        pts[:, known] = dirs * rng[:, known, None]
    chan, col = np.meshgrid(np.arange(k), np.arange(c), indexing="ij")
    flags = image.flags.astype(np.uint16)
    flags[~np.isfinite(rng)] |= FLAG_REJECTED
    arrived = np.ones(c, bool) if done is None else np.asarray(done, bool)
    t_col = (np.zeros(c) if timestamps_us is None
             else np.nan_to_num(column_times_s(timestamps_us, arrived)))
    t = np.broadcast_to(t_col[None, :], (k, c)).copy()
    inten = np.full((k, c), np.nan) if intensity is None else np.asarray(intensity, float)
    own = (flags & FLAG_FOREIGN) == 0
    user = np.where(own & (image.peak != 0), image.config.uid, -1).astype(np.int64)
    cloud = PointCloud(x=pts[..., 0], y=pts[..., 1], z=pts[..., 2], intensity=inten, t=t,
                       ring=chan, range=rng.copy(), snr_xc=image.snr_xc_db.copy(),
                       flags=flags, column=col, user_id=user, peak=image.peak.copy(),
                       wavelengths_m=wl, angles_deg=ang, stamp_unix_s=float(stamp_unix_s))
    if keep_foreign and len(image.foreign):
        cloud.extra = _foreign_points(image, geometry, wl, ang, t_col)
    return cloud


def _foreign_points(image: RangeImage, geometry: GratingGeometry, wl: NDArray[np.float64],
                    ang: NDArray[np.float64], t_col: NDArray[np.float64]) -> NDArray:
    """Other users' returns as extra points (flag 4, their UID in ``user_id``)."""
    f = image.foreign
    cfg = image.config
    ok = np.isfinite(ang[f.column])
    ch, co = f.channel[ok], f.column[ok]
    r = lag_to_range_m(f.lag[ok], cfg.samples_per_chip, cfg.chip_rate_hz, cfg.offset_m)
    rec = empty_records(int(ok.sum()))
    if rec.size:
        d = geometry.directions(wl[ch], ang[co])
        xyz = d * r[:, None]
        rec["x"], rec["y"], rec["z"] = xyz[:, 0], xyz[:, 1], xyz[:, 2]
    rec["intensity"] = np.nan
    rec["t"] = t_col[co]
    rec["ring"], rec["column"] = ch, co
    rec["range"], rec["snr_xc"] = r, f.snr_xc_db[ok]
    rec["flags"] = FLAG_FOREIGN
    rec["user_id"] = f.user[ok]
    rec["peak"] = f.peak[ok]
    return rec
