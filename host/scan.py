"""Scans and calibrations on a device: orchestration, progress, resumable partial scans.

:func:`run_scan` scans ``frames`` frames column by column, turns each finished frame
into ranges (:mod:`cdma_lidar.host.ranging`), optionally closes the near-far loop between
frames (:mod:`cdma_lidar.host.nearfar`), and writes the last frame's point cloud (and pictures).

Resumable: while scanning, the frame in progress is saved every second to
``OUT.partial.npz`` (atomically; NPZ with every :class:`cdma_lidar.host.frame.FrameData` array,
the frame counter, the near-far history and a JSON header naming the device, its
configuration and the scan options). Ctrl-C or a lost link leaves that file behind;
``resume=True`` (``--resume``) reloads it, checks it belongs to the same device and
configuration, scans only the columns that never arrived, and removes it at the end.

:func:`calibrate_device` takes zeroth-order shots and builds a
:class:`cdma_lidar.host.calibration.Calibration` (Supplementary Note 6).
"""

from __future__ import annotations

import dataclasses
import json
import logging
import os
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray
from tqdm import tqdm

from cdma_lidar.errors import CalibrationError, ConfigError, DeviceError, LinkError, ScanAborted
from cdma_lidar.fileio import atomic_open, check_writable
from cdma_lidar.firmware_model.snr import snr_xc_db
from cdma_lidar.host import pictures
from cdma_lidar.host.calibration import Calibration, toml_safe
from cdma_lidar.host.cloud_formats import FORMATS, MULTI_FRAME_FORMATS, write_frames
from cdma_lidar.host.combine import COMBINE_MODES, combine, nan_median
from cdma_lidar.host.connection import Device
from cdma_lidar.host.frame import FrameData
from cdma_lidar.host.intensity import intensity
from cdma_lidar.host.nearfar import NearFarController, PowerLimits, apply_cap
from cdma_lidar.host.pointcloud import PointCloud, assemble
from cdma_lidar.host.ranging import RangeImage, estimate_ranges, sample_range_m
from cdma_lidar.host.uid_filter import ForeignReturns

__all__ = [
    "STATE_SUFFIX",
    "ScanOptions",
    "ScanResult",
    "ScanState",
    "calibrate_device",
    "image_from_cloud",
    "max_snr_xc_db",
    "multi_user_peaks",
    "picture_paths",
    "run_scan",
    "state_path",
    "summarise",
]

log = logging.getLogger(__name__)

STATE_SUFFIX = ".partial.npz"
_SAVE_EVERY_S = 1.0


def state_path(out: str | os.PathLike[str]) -> Path:
    """Where the partial scan for output ``out`` is kept: ``OUT.partial.npz``."""
    return Path(str(out) + STATE_SUFFIX)


def picture_paths(out: str | os.PathLike[str]) -> dict[str, Path]:
    """PNG files written beside ``out``: SNR heatmap(s), depth image, 3D view."""
    p = Path(out)
    stem = p.with_suffix("")
    return {"snr": Path(f"{stem}_snr.png"), "depth": Path(f"{stem}_depth.png"),
            "view": Path(f"{stem}_3d.png")}


@dataclass(frozen=True)
class ScanOptions:
    """What a scan does besides scanning (all recorded in the partial-scan file).

    Attributes:
        frames: frames to scan; the point cloud is made from them by ``combine``.
        near_far: adjust the per-pixel power between frames (Note 12).
        snr_threshold_db: SNR_XC threshold (dB); None: the default (16 dB).
        min_support: a pixel above the threshold is kept only if at least this many of
            its 8 neighbours are above it too at a lag within 1.5 samples
            (:attr:`cdma_lidar.host.ranging.RangingConfig.min_support`); 0: the threshold alone.
        interpolate: fill rejected pixels from their column neighbours (flag 1).
        ghost_windows: ``(start, length)`` lag windows (samples) of known ghosts.
        power_cap: eye-safety cap per column, in units of the per-pixel maximum power
            (None: only the device enforces its cap; refused matrices are scaled down).
        initial_power: near-far start power, as a fraction of the per-pixel maximum.
        offset_m: calibration offset (m).
        combine: how the frames become one cloud (:mod:`cdma_lidar.host.combine`):
            ``last``, ``mean`` (SNR-weighted) or ``median``.
        keep_foreign: keep other users' returns as extra points with their ``user_id``.
        intensity_gain: the calibrated intensity gain (:mod:`cdma_lidar.host.intensity`);
            None: relative intensity.
    """

    frames: int = 1
    near_far: bool = False
    snr_threshold_db: float | None = None
    min_support: int = 1
    interpolate: bool = False
    ghost_windows: tuple[tuple[int, int], ...] = ()
    power_cap: float | None = None
    initial_power: float = 0.25
    offset_m: float = 0.0
    combine: str = "last"
    keep_foreign: bool = False
    intensity_gain: float | None = None

    def __post_init__(self) -> None:
        if self.combine not in COMBINE_MODES:
            raise ConfigError(f"combine must be one of {', '.join(COMBINE_MODES)}, not "
                              f"{self.combine!r}", field="combine")
        if self.near_far and self.frames < 2:
            raise ConfigError(f"near_far needs at least 2 frames (the first one measures, "
                              f"the next ones are corrected), not {self.frames}",
                              field="frames")
        if not 1 <= self.frames <= 10000:
            raise ConfigError(f"frames must be from 1 to 10000, not {self.frames!r}",
                              field="frames")
        if not 0 <= self.min_support <= 8:
            raise ConfigError(f"min_support must be from 0 to 8 neighbours, not "
                              f"{self.min_support!r}", field="min_support")
        if not 0 < self.initial_power <= 1:
            raise ConfigError(f"initial_power must be in (0, 1], not {self.initial_power!r}",
                              field="initial_power")


@dataclass
class ScanState:
    """A scan in progress: enough to resume it (see the module docstring)."""

    header: dict[str, Any]
    frame_index: int
    frame_base: int
    data: FrameData
    powers: list[NDArray[np.float64]] = field(default_factory=list)
    snr_maps: list[NDArray[np.float64]] = field(default_factory=list)
    past: list[NDArray] = field(default_factory=list)
    stamps: list[float] = field(default_factory=list)

    def save(self, path: str | os.PathLike[str]) -> None:
        """Write the state atomically (NPZ)."""
        arrays = {f"frame_{k}": v for k, v in self.data.to_arrays().items()}
        arrays["header"] = np.array(json.dumps(self.header, sort_keys=True))
        arrays["frame_index"] = np.array(self.frame_index)
        arrays["frame_base"] = np.array(self.frame_base)
        if self.powers:
            arrays["powers"] = np.stack(self.powers)
        if self.snr_maps:
            arrays["snr_maps"] = np.stack(self.snr_maps)
        if self.past:
            arrays["past"] = np.stack(self.past)
            arrays["stamps"] = np.array(self.stamps, dtype=np.float64)
        with atomic_open(path, "wb") as fh:
            np.savez(fh, **arrays)

    @classmethod
    def load(cls, path: str | os.PathLike[str]) -> ScanState:
        """Read a state file; a missing or damaged file is a ConfigError."""
        p = Path(path)
        if not p.is_file():
            raise ConfigError(f"no partial scan to resume at {str(p)!r}; run the scan "
                              "without --resume", field="resume")
        try:
            with np.load(p, allow_pickle=False) as z:
                frame = FrameData.from_arrays({k[6:]: z[k] for k in z.files
                                               if k.startswith("frame_")})
                return cls(header=json.loads(str(z["header"])),
                           frame_index=int(z["frame_index"]), frame_base=int(z["frame_base"]),
                           data=frame,
                           powers=list(z["powers"]) if "powers" in z.files else [],
                           snr_maps=list(z["snr_maps"]) if "snr_maps" in z.files else [],
                           past=list(z["past"]) if "past" in z.files else [],
                           stamps=[float(v) for v in z["stamps"]] if "stamps" in z.files
                           else [])
        except (OSError, ValueError, KeyError) as exc:
            raise ConfigError(f"partial scan {str(p)!r} is damaged ({exc}); delete it and "
                              "scan again without --resume", field="resume") from exc


@dataclass
class ScanResult:
    """What a scan produced: the (combined) cloud and ranges, and the per-frame history.

    ``image`` and ``cloud`` are the combination of the frames (``--combine``; the last
    frame for ``last``), ``clouds`` every frame's cloud, ``data`` the last frame's
    receiver results.
    """

    cloud: PointCloud
    image: RangeImage
    data: FrameData
    snr_maps: list[NDArray[np.float64]]
    powers: list[NDArray[np.float64]]
    columns_scanned: int
    files: list[Path]
    clouds: list[PointCloud] = field(default_factory=list)


def _header(device: Device, options: ScanOptions, out: Path) -> dict[str, Any]:
    return {"device": toml_safe(device.identity()),
            "configuration": toml_safe(device.calibration_config()),
            "options": toml_safe(dataclasses.asdict(options)), "out": str(out)}


def _runs(missing: NDArray[np.bool_]) -> list[tuple[int, int]]:
    """Contiguous runs ``(first, count)`` of True in a 1-D mask."""
    idx = np.flatnonzero(missing)
    if idx.size == 0:
        return []
    breaks = np.flatnonzero(np.diff(idx) > 1)
    starts = np.concatenate([[idx[0]], idx[breaks + 1]])
    ends = np.concatenate([idx[breaks], [idx[-1]]])
    return [(int(a), int(b - a + 1)) for a, b in zip(starts, ends, strict=True)]


def max_snr_xc_db(config: dict[str, Any]) -> float:
    """The largest SNR_XC (dB) a configuration can report: ``10 log10(12 peak_max^2)``.

    The peak is a signed ``out_bits`` value and the noise variance is floored at 1/12
    LSB^2 (:mod:`cdma_lidar.firmware_model.snr`), so no threshold above this can ever pass.
    """
    bits = int(config.get("out_bits", 32))
    return float(snr_xc_db(1 << (bits - 1), 0, 0, 0))


#: Peaks per channel asked for when a UID is configured (see :func:`multi_user_peaks`).
MULTI_USER_PEAKS = 4


def multi_user_peaks(device: Device, user_set: set[str] | frozenset[str] = frozenset()
                     ) -> int:
    """Ask for enough peaks to find our own return among other users'; returns the new P.

    With a UID configured (``uid_bits > 1``) another user on the same code can be
    stronger than us and take the single peak a channel reports; then our pixel is lost.
    When the configuration has ``peaks = 1`` and the user did not set ``peaks``
    (``user_set``), the device is asked for :data:`MULTI_USER_PEAKS` (at most its
    ``max_peaks``). Returns 0 when nothing was changed.
    """
    cfg = device.config
    if int(cfg.get("uid_bits", 1)) <= 1 or int(cfg.get("peaks", 1)) != 1 or "peaks" in user_set:
        return 0
    want = min(MULTI_USER_PEAKS, int(getattr(device.info, "max_peaks", MULTI_USER_PEAKS)))
    if want <= 1:
        return 0
    device.link.set_config(peaks=want)
    device.refresh_config()
    log.info("UID configured: asked the device for %d peaks per channel", want)
    return want


def _set_power(device: Device, matrix: NDArray[np.float64],
               previous: NDArray[np.float64] | None = None,
               raised: NDArray[np.bool_] | None = None
               ) -> tuple[NDArray[np.float64], float | None]:
    """Send a power matrix (fractions of the per-pixel maximum); returns (applied, cap).

    The matrix is rounded down to the device's 1/65535 grid (rounding up could push a
    column over its cap by one LSB). The device checks its eye-safety cap after every
    rectangle of a chunked POWER_SET, so ``min(previous, matrix)`` goes first: every
    intermediate state is then at most the final one, element by element. When the
    device refuses anyway (its cap is lower than ours), the cap is learned as 0.8 of
    the largest column sum just refused and applied as the controller would (raised
    pixels give way first); ``cap`` is that learned cap, or None.
    """
    m = np.floor(np.clip(matrix, 0.0, 1.0) * 65535.0)
    prev = None if previous is None else np.floor(np.clip(previous, 0.0, 1.0) * 65535.0)
    up = np.zeros(m.shape, bool) if raised is None else raised
    learned: float | None = None
    for _ in range(20):
        try:
            if prev is not None and prev.shape == m.shape and np.any(prev > m):
                device.link.set_power(np.minimum(prev, m).astype(np.int64))
            device.link.set_power(m.astype(np.int64))
            return m / 65535.0, learned
        except DeviceError as exc:
            if getattr(exc, "field", None) != "power":
                raise
            log_ = log.warning if learned is None else log.debug
            learned = 0.8 * float(m.sum(axis=0).max()) / 65535.0
            log_("device refused the power matrix (%s); capping columns at %.4g of the "
                 "per-pixel maximum", exc, learned)
            m = np.floor(apply_cap(m / 65535.0, learned, previous, (up,)) * 65535.0)
            prev = None
    raise LinkError("the device refuses every power matrix; check its eye-safety settings")


def _apply_power(device: Device, controller: NearFarController,
                 previous: NDArray[np.float64] | None) -> NDArray[np.float64]:
    """Send the controller's next matrix; a cap learned from a refusal becomes its cap."""
    raised = None if previous is None else controller.power > previous
    applied, cap = _set_power(device, controller.power, previous, raised)
    if cap is not None:
        controller.limits = dataclasses.replace(controller.limits, total_cap=cap)
    return applied


def run_scan(device: Device, out: str | os.PathLike[str], options: ScanOptions = ScanOptions(),
             *, resume: bool = False, force: bool = False, progress: bool = True,
             pictures_too: bool = False,
             frame_id: int | None = None,
             on_column: Callable[[int, int], None] | None = None) -> ScanResult:
    """Scan, build the point cloud of the last frame and write it to ``out``.

    Frame n is requested with frame id ``frame_id + n`` (default: random), which seeds
    the virtual device's noise. ``on_column(frame_index, column)`` is called after each
    stored column. Raises ScanAborted (after saving the partial scan) when the link is
    lost or the device ends the frame early; re-raises KeyboardInterrupt after saving.
    An existing partial scan is resumed (``resume``), overwritten (``force``) or, with
    neither, left alone with a ConfigError: nothing is deleted without being asked.
    """
    out = Path(out)
    if out.suffix.lower() not in FORMATS:
        raise ConfigError(f"output file extension must be one of {', '.join(FORMATS)}, "
                          f"not {out.suffix or '(none)'!r}", field="out")
    check_writable(out)
    if device.config.get("mode") == "calibration":
        raise ConfigError("the device is in calibration mode: its columns see the "
                          "zeroth-order target at a 90 deg grating angle, not the scene; scan "
                          "with --set mode=ranging (or use 'cdma-lidar calibrate')", field="mode")
    spath = state_path(out)
    if not resume and not force and spath.exists():
        raise ConfigError(f"{str(spath)!r} holds an interrupted scan; finish it with --resume "
                          "or start afresh with --force (which overwrites it)", field="resume")
    if options.power_cap is not None and options.power_cap > device.channels:
        raise ConfigError(f"power_cap must be at most {device.channels} (every pixel of a "
                          f"column at its maximum), not {options.power_cap:g}",
                          field="power_cap")
    threshold = options.snr_threshold_db
    ranging = device.ranging_config(offset_m=options.offset_m, interpolate=options.interpolate,
                                    ghost_windows=options.ghost_windows,
                                    min_support=options.min_support)
    if threshold is not None:
        ranging = dataclasses.replace(ranging, snr_threshold_db=threshold)
    k, c = device.channels, device.columns
    uid_bits, peaks = int(device.config.get("uid_bits", 1)), int(device.config.get("peaks", 1))
    header = _header(device, options, out)
    if resume:
        state = ScanState.load(spath)
        for key in ("device", "configuration", "options"):
            if state.header.get(key) != header[key]:
                raise ConfigError(
                    f"the partial scan at {str(spath)!r} does not match this scan's {key}; "
                    "resume it with the same device and options, or scan again without "
                    "--resume", field="resume")
        log.info("resuming frame %d of %d: %d of %d columns already done",
                 state.frame_index + 1, options.frames, int(state.data.done.sum()), c)
    else:
        base = (int(np.random.default_rng().integers(0, 2**31 - options.frames - 1))
                if frame_id is None else int(frame_id))
        state = ScanState(header=header, frame_index=0, frame_base=base,
                          data=FrameData.empty(k, c, uid_bits, peaks))
    controller = None
    if options.near_far:
        # Default cap: the starting column sum, so the loop moves power between pixels
        # and never raises a column's total (the paper's "without increasing overall power").
        cap = options.power_cap if options.power_cap is not None else k * options.initial_power
        limits = PowerLimits(max_power=1.0, total_cap=cap)
        controller = NearFarController((k, c), ranging.snr_threshold_db, limits,
                                       initial_power=options.initial_power)
        if state.powers:
            controller.powers[:] = [np.asarray(p) for p in state.powers]
            controller.snr_maps[:] = [np.asarray(s) for s in state.snr_maps]
        controller.powers[-1] = _apply_power(device, controller, None)
    else:
        # A known, uniform power: the intensity needs it (the device default may differ).
        _set_power(device, np.full((k, c), options.initial_power))

    geometry, wavelengths = device.geometry(), device.wavelengths_m
    device_cfg = dict(device.config)
    clouds: list[PointCloud] = [_cloud_from_records(r, st, wavelengths, state.data.angle_deg)
                                for r, st in zip(state.past, state.stamps, strict=True)]
    images: list[RangeImage] = [image_from_cloud(cl, ranging) for cl in clouds]
    stamp = time.time()
    total = options.frames * c
    done_before = state.frame_index * c + int(state.data.done.sum())
    bar = None
    if progress:
        bar = tqdm(total=total, initial=done_before, unit="col", desc="scan", leave=False,
                   dynamic_ncols=True)
    scanned = 0
    image: RangeImage | None = None
    last_save = time.monotonic()
    try:
        while state.frame_index < options.frames:
            fid = state.frame_base + state.frame_index
            data = state.data
            if not data.done.any():
                stamp = time.time()
            for first, count in _runs(~data.done):
                for col in device.link.scan(first_column=first, columns=count, frames=1,
                                            frame=fid):
                    data.set_column(int(col.column), col)
                    scanned += 1
                    if bar is not None:
                        bar.update(1)
                    if on_column is not None:
                        on_column(state.frame_index, int(col.column))
                    if time.monotonic() - last_save > _SAVE_EVERY_S:
                        state.save(spath)
                        last_save = time.monotonic()
            data.angle_deg = np.where(np.isfinite(data.angle_deg), data.angle_deg,
                                      device.column_angles_deg)
            image = estimate_ranges(data, ranging)
            state.snr_maps.append(image.snr_xc_db)
            last = state.frame_index + 1 >= options.frames
            power = controller.power if controller is not None else options.initial_power
            inten = intensity(image.peak, image.range_m, power, device_cfg,
                              options.intensity_gain)
            cloud = assemble(image, geometry, wavelengths, data.angle_deg,
                             timestamps_us=data.timestamp_us, done=data.done, intensity=inten,
                             keep_foreign=options.keep_foreign, stamp_unix_s=stamp)
            clouds.append(cloud)
            images.append(image)
            state.past.append(cloud.grid_records())
            state.stamps.append(stamp)
            if controller is not None:
                controller.snr_maps[:] = state.snr_maps[:-1]
                controller.update(image.snr_xc_db, image.peak)
                if not last:
                    controller.powers[-1] = _apply_power(device, controller,
                                                         controller.powers[-2])
                state.powers = list(controller.powers)
            state.frame_index += 1
            if not last:
                state.data = FrameData.empty(k, c, uid_bits, peaks, frame=state.frame_index)
                state.save(spath)
                last_save = time.monotonic()
    except KeyboardInterrupt:
        state.save(spath)
        log.info("scan interrupted; partial scan saved to %s (resume=True finishes it)", spath)
        raise
    except (LinkError, ScanAborted) as exc:
        state.save(spath)
        raise ScanAborted(f"scan stopped: {exc}; partial scan saved to {spath}, run the same "
                          "command with --resume to finish it") from exc
    finally:
        if bar is not None:
            bar.close()
    assert image is not None and clouds
    image, cloud = images[-1], clouds[-1]
    if options.combine != "last" and len(images) > 1:
        image = combine(images, options.combine)
        cloud = assemble(image, geometry, wavelengths, state.data.angle_deg,
                         timestamps_us=state.data.timestamp_us, done=state.data.done,
                         keep_foreign=options.keep_foreign, stamp_unix_s=clouds[-1].stamp_unix_s)
        per_frame = np.stack([cl.intensity for cl in clouds])
        cloud.intensity = np.where(cloud.has_range, nan_median(per_frame), np.nan)
    if out.suffix.lower() in MULTI_FRAME_FORMATS and options.combine == "last":
        write_frames(clouds, out)
    else:
        write_frames([cloud], out)
    files = [out]
    if pictures_too:
        paths = picture_paths(out)
        maps = (state.snr_maps if options.near_far and len(state.snr_maps) > 1
                else [image.snr_xc_db])
        titles = ([f"frame {i}" for i in range(len(maps))] if len(maps) > 1 else ["SNR_XC"])
        pictures.snr_heatmaps(maps, ranging.snr_threshold_db, paths["snr"], titles)
        pictures.depth_image(cloud, paths["depth"])
        pictures.view_3d(cloud, paths["view"])
        files += list(paths.values())
    spath.unlink(missing_ok=True)
    return ScanResult(cloud=cloud, image=image, data=state.data,
                      snr_maps=list(state.snr_maps),
                      powers=list(state.powers), columns_scanned=scanned, files=files,
                      clouds=clouds)


def _cloud_from_records(rec: NDArray, stamp: float, wavelengths_m: NDArray[np.float64],
                        angles_deg: NDArray[np.float64]) -> PointCloud:
    """A finished frame's cloud back from the grid records a partial scan keeps."""
    k, c = wavelengths_m.size, angles_deg.size
    grid = {name: np.asarray(rec[name]).reshape(k, c) for name in rec.dtype.names}
    return PointCloud(**{n: grid[n].astype(np.float64) if grid[n].dtype.kind == "f"
                         else grid[n].astype(np.int64) for n in grid},
                      wavelengths_m=wavelengths_m, angles_deg=np.asarray(angles_deg),
                      stamp_unix_s=float(stamp))


def image_from_cloud(cloud: PointCloud, config: Any) -> RangeImage:
    """The ranges of a finished frame from its cloud (to combine frames, also after --resume)."""
    empty = np.zeros(0, np.int64)
    return RangeImage(range_m=np.where(cloud.flags == 0, cloud.range, np.nan),
                      lag=np.zeros(cloud.shape), snr_xc_db=cloud.snr_xc,
                      peak=cloud.peak, flags=cloud.flags.astype(np.uint8),
                      foreign=ForeignReturns(empty, empty, empty, empty, empty, empty,
                                             np.zeros(0)), config=config)


def calibrate_device(device: Device, target_distance_m: float, *, shots: int = 20,
                     snr_threshold_db: float | None = None, max_spread_m: float | None = None,
                     frame_id: int | None = None) -> Calibration:
    """Zeroth-order calibration (Note 6): ``shots`` shots, every channel, one histogram.

    The uncalibrated range of every channel of every shot above the SNR_XC threshold
    goes into the histogram (sub-sample refined); its one mode minus
    ``target_distance_m`` is the offset. Histogram modes further apart than one lag
    sample count as separate; ``max_spread_m`` defaults to a quarter of a sample.
    ``frame_id`` seeds a virtual device's noise (default: the link's next id).
    """
    if not 1 <= shots <= 65535:
        raise ConfigError(f"shots must be from 1 to 65535, not {shots!r}", field="shots")
    ranging = device.ranging_config(offset_m=0.0, min_support=0)
    if snr_threshold_db is not None:
        ranging = dataclasses.replace(ranging, snr_threshold_db=snr_threshold_db)
    results = device.link.calibrate(shots, frame=frame_id)
    if len(results) != shots:
        raise CalibrationError(f"device sent {len(results)} of {shots} calibration shots")
    data = FrameData.from_columns(results, device.channels, shots,
                                  uid_bits=int(device.config.get("uid_bits", 1)),
                                  peaks=int(device.config.get("peaks", 1)))
    image = estimate_ranges(data, ranging)
    one_sample = sample_range_m(ranging.samples_per_chip, ranging.chip_rate_hz)
    spread = 0.25 * one_sample if max_spread_m is None else max_spread_m
    return Calibration.from_ranges(image.range_m[image.valid], target_distance_m, shots=shots,
                                   gap_m=one_sample, max_spread_m=spread,
                                   device=device.identity(),
                                   configuration=device.calibration_config())


def summarise(image: RangeImage, truth_range_m: NDArray[np.float64] | None = None
              ) -> dict[str, float]:
    """Figures of a frame: pixels, valid fraction and, with truth, range errors (m)."""
    out: dict[str, float] = {"pixels": float(image.range_m.size),
                             "valid_fraction": float(np.mean(image.valid))}
    if truth_range_m is not None:
        obj = np.isfinite(truth_range_m)
        v = image.valid
        err = np.abs(image.range_m - truth_range_m)[v & obj]
        out["object_pixels"] = float(obj.sum())
        out["object_valid_fraction"] = float(np.mean(v[obj])) if obj.any() else float("nan")
        out["false_valid"] = float(np.count_nonzero(v & ~obj))
        out["median_error_m"] = float(np.median(err)) if err.size else float("nan")
        out["p95_error_m"] = float(np.percentile(err, 95)) if err.size else float("nan")
    return out
