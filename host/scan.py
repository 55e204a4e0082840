"""Scans and calibrations on a device: orchestration, progress, resumable partial scans.

A scan is three visible steps, the shape of ouster-sdk's ``ScanSource``::

    scan = open_scan(device, "scan.ply", ScanOptions(frames=4))   # checks, power set
    for frame in scan.frames():     # ScanFrame: cloud, range image, power, per frame
        ...                         # a viewer or recorder consumes the same iterator
    result = scan.finish()          # combine, write the cloud (and pictures)

:func:`run_scan` is that composition. Each finished frame is turned into ranges
(:mod:`cdma_lidar.host.ranging`), the near-far loop is closed between frames
(:mod:`cdma_lidar.host.nearfar`), and the frames are combined and written.

Resumable: the frame in progress is saved every second to ``OUT.partial.npz``
(atomically; NPZ with every :class:`cdma_lidar.host.frame.FrameData` array, the frame
counter, the frame's power matrix and a JSON header naming the device, its configuration
and the scan options), and each finished frame once to ``OUT.partial.frames/frame-NNNNN.npz``
(so a long scan writes each frame once, not every past frame every second). Ctrl-C, a
lost link or a frame the device ends early leaves both behind; ``resume=True``
(``--resume``) reloads them, checks they belong to the same device, configuration and
options, scans only the columns that never arrived, and removes them at the end. A new
scan never overwrites them unless asked (``force=True``, ``--force``).

:func:`calibrate_device` takes zeroth-order shots and builds a
:class:`cdma_lidar.host.calibration.Calibration` (Supplementary Note 6).
"""

from __future__ import annotations

import dataclasses
import json
import logging
import math
import os
import shutil
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from cdma_lidar.checks import is_int
from cdma_lidar.errors import CalibrationError, ConfigError, DeviceError, LinkError, ScanAborted
from cdma_lidar.fileio import atomic_open
from cdma_lidar.firmware_model.snr import snr_xc_db
from cdma_lidar.host import pictures
from cdma_lidar.host.calibration import Calibration, toml_safe
from cdma_lidar.host.cloud_formats import MULTI_FRAME_FORMATS, check_output, write_frames
from cdma_lidar.host.combine import COMBINE_MODES, combine, nan_median
from cdma_lidar.host.connection import Device
from cdma_lidar.host.frame import FrameData
from cdma_lidar.host.intensity import RAW_UNIT, intensity
from cdma_lidar.host.nearfar import NearFarController, PowerLimits, apply_cap
from cdma_lidar.host.pointcloud import PointCloud, assemble, file_metadata
from cdma_lidar.host.ranging import RangeImage, estimate_ranges, in_windows, sample_range_m
from cdma_lidar.host.uid_filter import ForeignReturns

__all__ = [
    "FRAMES_SUFFIX",
    "STATE_SUFFIX",
    "Scan",
    "ScanFrame",
    "ScanOptions",
    "ScanResult",
    "ScanState",
    "calibrate_device",
    "default_power_level",
    "frames_path",
    "image_from_cloud",
    "max_snr_xc_db",
    "multi_user_peaks",
    "open_scan",
    "picture_paths",
    "run_scan",
    "scan_metadata",
    "scene_name",
    "state_path",
    "summarise",
]

log = logging.getLogger(__name__)

STATE_SUFFIX = ".partial.npz"
FRAMES_SUFFIX = ".partial.frames"
_SAVE_EVERY_S = 1.0


def state_path(out: str | os.PathLike[str]) -> Path:
    """Where the partial scan for output ``out`` is kept: ``OUT.partial.npz``."""
    return Path(str(out) + STATE_SUFFIX)


def picture_paths(out: str | os.PathLike[str]) -> dict[str, Path]:
    """Files written beside ``out`` by ``--pictures`` (:func:`pictures.scan_pictures`):
    SNR heatmap(s), depth image, 3D view, column profile (Fig. 3c), range histogram
    (Fig. 3e) and, with near-far, the power matrices (PNG and NPZ)."""
    stem = Path(out).with_suffix("")
    return {"snr": Path(f"{stem}_snr.png"), "depth": Path(f"{stem}_depth.png"),
            "view": Path(f"{stem}_3d.png"), "column": Path(f"{stem}_column.png"),
            "histogram": Path(f"{stem}_hist.png"), "power": Path(f"{stem}_power.png"),
            "power_npz": Path(f"{stem}_power.npz")}


def scene_name(device: Device) -> str:
    """What a picture's title calls the scene: a virtual device's scene, else the serial."""
    url = getattr(device, "url", "") or ""
    if url.lower().startswith("virtual://"):
        return url[len("virtual://"):].split("?", 1)[0]
    return str(device.info.serial)


@dataclass(frozen=True)
class ScanOptions:
    """What a scan does besides scanning (all recorded in the partial-scan file).

    Every field is checked here, once, at construction (a ConfigError naming the field);
    only the limits that depend on the device (``power_cap`` at most K, the SNR_XC
    threshold at most what ``out_bits`` can report) are checked by :func:`open_scan`.

    Attributes:
        frames: frames to scan (1..10000); the point cloud is made from them by ``combine``.
        near_far: adjust the per-pixel power between frames (Note 12); needs 2 frames.
        snr_threshold_db: SNR_XC threshold (dB, >= 0); None: the default (16 dB).
        min_support: a pixel above the threshold is kept only if at least this many of
            its 8 neighbours are above it too at a lag within 1.5 samples
            (:attr:`cdma_lidar.host.ranging.RangingConfig.min_support`); 0: the threshold alone.
        interpolate: fill rejected pixels from their column neighbours (flag 1).
        ghost_windows: ``(start, length)`` lag windows (samples) of known ghosts.
        power_cap: eye-safety cap per column, in units of the per-pixel maximum power
            (> 0; None: the starting column sum); used by ``near_far`` only.
        initial_power: the scan's (and near-far's starting) power, as a fraction of the
            per-pixel maximum (0, 1]; lowered to fit the column cap the device states
            (:func:`default_power_level`).
        offset_m: calibration offset (m, |offset| <= 1000).
        combine: how the frames become one cloud (:mod:`cdma_lidar.host.combine`):
            ``last``, ``mean`` (SNR-weighted) or ``median``; the last two need 2 frames.
        keep_foreign: keep other users' returns as extra points with their ``user_id``.
        intensity_gain: the calibrated intensity gain (:mod:`cdma_lidar.host.intensity`,
            > 0); None: the gain predicted from the instrument's link budget.
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
        def bad(name: str, allowed: str) -> ConfigError:
            return ConfigError(f"{name} must be {allowed}, not {getattr(self, name)!r}",
                               field=name)

        if not (is_int(self.frames) and 1 <= self.frames <= 10000):
            raise bad("frames", "from 1 to 10000")
        if self.near_far and self.frames < 2:
            raise bad("frames", "at least 2 with near_far (the first frame measures, the next "
                      "ones are corrected)")
        if self.combine not in COMBINE_MODES:
            raise bad("combine", f"one of {', '.join(COMBINE_MODES)}")
        if self.combine != "last" and self.frames < 2:
            raise bad("frames", f"at least 2 with combine {self.combine!r}")
        if not (is_int(self.min_support) and 0 <= self.min_support <= 8):
            raise bad("min_support", "from 0 to 8 neighbours")
        if not 0 < self.initial_power <= 1:
            raise bad("initial_power", "in (0, 1] of the per-pixel maximum")
        if self.power_cap is not None and not (math.isfinite(self.power_cap)
                                               and self.power_cap > 0):
            raise bad("power_cap", "a positive number of per-pixel maxima")
        if self.snr_threshold_db is not None and not (math.isfinite(self.snr_threshold_db)
                                                      and self.snr_threshold_db >= 0):
            raise bad("snr_threshold_db", "from 0 dB (to what the configuration can report)")
        if not (math.isfinite(self.offset_m) and abs(self.offset_m) <= 1000):
            raise bad("offset_m", "from -1000 to 1000 m")
        if self.intensity_gain is not None and not (math.isfinite(self.intensity_gain)
                                                    and self.intensity_gain > 0):
            raise bad("intensity_gain", "a positive number")
        if any(a < 0 or b < 1 for a, b in self.ghost_windows):
            raise bad("ghost_windows", "(start >= 0, length >= 1) lag windows")


@dataclass
class ScanState:
    """The frame in progress of a scan: enough, with the finished frames, to resume it.

    ``power`` is the power matrix this frame is scanned with (near-far only).
    """

    header: dict[str, Any]
    frame_index: int
    frame_base: int
    data: FrameData
    power: NDArray[np.float64] | None = None

    def save(self, path: str | os.PathLike[str]) -> None:
        """Write the state atomically (NPZ)."""
        arrays = {f"frame_{k}": v for k, v in self.data.to_arrays().items()}
        arrays["header"] = np.array(json.dumps(self.header, sort_keys=True))
        arrays["frame_index"] = np.array(self.frame_index)
        arrays["frame_base"] = np.array(self.frame_base)
        if self.power is not None:
            arrays["power"] = np.asarray(self.power)
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
                           data=frame, power=z["power"] if "power" in z.files else None)
        except (OSError, ValueError, KeyError) as exc:
            raise ConfigError(f"partial scan {str(p)!r} is damaged ({exc}); delete it and "
                              "scan again without --resume", field="resume") from exc


@dataclass
class ScanFrame:
    """One finished frame of a scan, as :meth:`Scan.frames` yields it.

    ``power`` is the (K, C) power matrix it was scanned with (fractions of the per-pixel
    maximum), ``stamp_unix_s`` the host's clock when its first column arrived.
    """

    index: int
    cloud: PointCloud
    image: RangeImage
    power: NDArray[np.float64]

    def save(self, folder: Path) -> None:
        """Keep the frame for a resume: ``folder/frame-NNNNN.npz``, written once (atomic)."""
        with atomic_open(folder / f"frame-{self.index:05d}.npz", "wb") as fh:
            np.savez(fh, records=self.cloud.grid_records(), snr=self.image.snr_xc_db,
                     stamp=np.array(self.cloud.stamp_unix_s), power=self.power)


@dataclass
class ScanResult:
    """What a scan produced: the (combined) cloud and ranges, and the per-frame history.

    ``image`` and ``cloud`` are the combination of the frames (``--combine``; the last
    frame for ``last``), ``clouds`` every frame's cloud, ``data`` the last frame's
    receiver results, ``powers`` the power matrices of every frame and the next one
    (near-far: the matrix the loop would apply after the last frame).
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


def default_power_level(device: Device, fraction: float) -> float:
    """The uniform power (fraction of the per-pixel maximum) a scan starts with.

    ``fraction`` (at most 1: the per-pixel cap), lowered where K pixels at it would sum
    over the column cap the device states in INFO (``column_power_cap_uw`` over
    ``pixel_power_max_uw``; 0 means none): the largest level on the device's 1/65535 grid
    whose column sum it accepts, in integers as the device checks it. A 1,200-channel
    device with a 0.1 W pixel maximum and a 6 W column cap starts at 0.05, not 0.25.
    """
    code = math.floor(min(fraction, 1.0) * 65535)
    pixel_uw = int(getattr(device.info, "pixel_power_max_uw", 0))
    cap_uw = int(getattr(device.info, "column_power_cap_uw", 0))
    if pixel_uw > 0 and cap_uw > 0:
        code = min(code, cap_uw * 65535 // (device.channels * pixel_uw))
    return code / 65535


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


def frames_path(out: str | os.PathLike[str]) -> Path:
    """Where the finished frames of a partial scan are kept: ``OUT.partial.frames/``."""
    return Path(str(out) + FRAMES_SUFFIX)


class Scan:
    """An open scan: :func:`open_scan` makes it, :meth:`frames` scans, :meth:`finish` writes.

    The three steps of ouster-sdk's ``ScanSource`` shape: a viewer, a recorder and
    :func:`run_scan` consume the same iterator of :class:`ScanFrame`. Attributes a
    consumer may read: ``device``, ``out``, ``options``, ``ranging`` (the
    :class:`cdma_lidar.host.ranging.RangingConfig`), ``frame_ids`` (the first frame's id
    and the count) and ``done`` (the finished frames, resumed ones included).
    """

    def __init__(self, device: Device, out: Path, options: ScanOptions, state: ScanState,
                 done: list[ScanFrame]) -> None:
        self.device, self.out, self.options = device, out, options
        self.ranging = _ranging(device, options)
        self.done = done
        self.data = state.data   # the receiver results of the frame in progress (or last)
        self.columns_scanned = 0
        self._state = state
        self._controller = None
        k, c = device.channels, device.columns
        # the starting power within the caps the device states (per pixel, per column)
        self._level = default_power_level(device, options.initial_power)
        if options.near_far:
            # Default cap: the starting column sum, so the loop moves power between pixels
            # and never raises a column's total (the paper's "without increasing overall
            # power").
            cap = options.power_cap if options.power_cap is not None else k * self._level
            self._controller = NearFarController((k, c), self.ranging.snr_threshold_db,
                                                 PowerLimits(max_power=1.0, total_cap=cap),
                                                 initial_power=self._level)
            if done:
                now = state.power if state.power is not None else done[-1].power
                self._controller.powers[:] = [f.power for f in done] + [now]
                self._controller.snr_maps[:] = [f.image.snr_xc_db for f in done]
            self._controller.powers[-1] = _apply_power(device, self._controller, None)
        else:
            # A known, uniform power: the intensity needs it (the device default may differ).
            _set_power(device, np.full((k, c), self._level))

    @property
    def frame_ids(self) -> tuple[int, int]:
        """(id of frame 0, frames): frame n is requested with id ``first + n``."""
        return self._state.frame_base, self.options.frames

    def _power(self) -> NDArray[np.float64]:
        if self._controller is not None:
            return np.array(self._controller.power)
        return np.full((self.device.channels, self.device.columns), self._level)

    def frames(self, *, progress: bool = True,
               on_column: Callable[[int, int], None] | None = None) -> Iterator[ScanFrame]:
        """Scan the frames still to do, yielding each as it is finished.

        ``on_column(frame_index, column)`` is called after each stored column. The frame
        in progress is saved every second (``OUT.partial.npz``) and each finished frame
        once (``OUT.partial.frames/``). Ctrl-C, a lost link, an early end on the device
        or a consumer that stops iterating leaves a partial scan that ``resume`` finishes:
        KeyboardInterrupt is re-raised, the link failures become ScanAborted.
        """
        dev, options, state = self.device, self.options, self._state
        k, c = dev.channels, dev.columns
        uid_bits, peaks = int(dev.config.get("uid_bits", 1)), int(dev.config.get("peaks", 1))
        spath, folder = state_path(self.out), frames_path(self.out)
        folder.mkdir(exist_ok=True)
        geometry, wavelengths, device_cfg = dev.geometry(), dev.wavelengths_m, dict(dev.config)
        bar = None
        if progress:
            from tqdm import tqdm  # deferred: 60 ms at start-up for a bar only a scan shows

            bar = tqdm(total=options.frames * c,
                       initial=state.frame_index * c + int(state.data.done.sum()),
                       unit="col", desc="scan", leave=False, dynamic_ncols=True)
        last_save = time.monotonic()
        stamp = time.time()
        finished = True
        try:
            while state.frame_index < options.frames:
                finished = False
                data = state.data
                if not data.done.any():
                    stamp = time.time()
                for first, count in _runs(~data.done):
                    for col in dev.link.scan(first_column=first, columns=count, frames=1,
                                             frame=state.frame_base + state.frame_index):
                        data.set_column(int(col.column), col)
                        self.columns_scanned += 1
                        if bar is not None:
                            bar.update(1)
                        if on_column is not None:
                            on_column(state.frame_index, int(col.column))
                        if time.monotonic() - last_save > _SAVE_EVERY_S:
                            state.save(spath)
                            last_save = time.monotonic()
                data.angle_deg = np.where(np.isfinite(data.angle_deg), data.angle_deg,
                                          dev.column_angles_deg)
                image = estimate_ranges(data, self.ranging)
                power = self._power()
                inten = intensity(image.peak, image.range_m, power, device_cfg,
                                  options.intensity_gain)
                cloud = assemble(image, geometry, wavelengths, data.angle_deg,
                                 timestamps_us=data.timestamp_us, done=data.done,
                                 intensity=inten, keep_foreign=options.keep_foreign,
                                 stamp_unix_s=stamp)
                frame = ScanFrame(index=state.frame_index, cloud=cloud, image=image,
                                  power=power)
                frame.save(folder)
                self.done.append(frame)
                state.frame_index += 1
                if self._controller is not None:
                    ctl = self._controller
                    ctl.snr_maps[:] = [f.image.snr_xc_db for f in self.done[:-1]]
                    ctl.update(image.snr_xc_db, image.peak)
                    if state.frame_index < options.frames:
                        ctl.powers[-1] = _apply_power(dev, ctl, ctl.powers[-2])
                    state.power = np.array(ctl.power)
                self.data = data
                if state.frame_index < options.frames:
                    state.data = FrameData.empty(k, c, uid_bits, peaks, frame=state.frame_index)
                state.save(spath)
                last_save = time.monotonic()
                finished = state.frame_index >= options.frames
                yield frame
        except KeyboardInterrupt:
            state.save(spath)
            log.info("scan interrupted; partial scan saved to %s (resume=True finishes it)",
                     spath)
            raise
        except (LinkError, ScanAborted) as exc:
            state.save(spath)
            raise ScanAborted(f"scan stopped: {exc}; partial scan saved to {spath}, run the "
                              "same command with --resume to finish it") from exc
        finally:
            if bar is not None:
                bar.close()
            if not finished:  # the consumer stopped iterating: keep what was scanned
                state.save(spath)

    def finish(self, *, pictures_too: bool = False) -> ScanResult:
        """Combine the frames, write the cloud (and pictures), remove the partial scan."""
        options, dev, out = self.options, self.device, self.out
        if len(self.done) < options.frames:
            raise ScanAborted(f"{len(self.done)} of {options.frames} frames scanned; iterate "
                              "frames() to the end first")
        images, clouds = [f.image for f in self.done], [f.cloud for f in self.done]
        image, cloud = images[-1], clouds[-1]
        data = self.data
        if options.combine != "last":
            image = combine(images, options.combine)
            cloud = assemble(image, dev.geometry(), dev.wavelengths_m, data.angle_deg,
                             timestamps_us=data.timestamp_us, done=data.done,
                             keep_foreign=options.keep_foreign,
                             stamp_unix_s=clouds[-1].stamp_unix_s)
            per_frame = np.stack([cl.intensity for cl in clouds])
            cloud.intensity = np.where(cloud.has_range, nan_median(per_frame), np.nan)
        meta = scan_metadata(dev, options)
        if out.suffix.lower() in MULTI_FRAME_FORMATS and options.combine == "last":
            write_frames(clouds, out, meta)
        else:
            write_frames([cloud], out, meta)
        files = [out]
        snr_maps = [f.image.snr_xc_db for f in self.done]
        if pictures_too:
            base, n = self.frame_ids
            last = f"frame {n - 1} of {n} (id {base + n - 1})"
            if options.near_far:
                maps, titles = snr_maps, [f"frame {i}" for i in range(n)]
            else:
                maps = [image.snr_xc_db]
                titles = [last if options.combine == "last" else f"{n} frames, {options.combine}"]
            el, az = dev.beam_angles_deg()
            files += pictures.scan_pictures(
                picture_paths(out), cloud, maps, self.ranging.snr_threshold_db,
                title=f"{scene_name(dev)}, {titles[-1] if not options.near_far else last}",
                frame_titles=titles, angles=pictures.Angles(el, az),
                powers=[f.power for f in self.done] if options.near_far else None)
        state_path(out).unlink(missing_ok=True)
        shutil.rmtree(frames_path(out), ignore_errors=True)
        powers = (list(self._controller.powers) if self._controller is not None
                  else [f.power for f in self.done])
        return ScanResult(cloud=cloud, image=image, data=data, snr_maps=snr_maps,
                          powers=powers, columns_scanned=self.columns_scanned, files=files,
                          clouds=clouds)


def scan_metadata(device: Device, options: ScanOptions) -> dict[str, str]:
    """What a recording should say about its instrument (string keys to JSON text).

    ``wavelengths_m`` (K), ``angles_deg`` (C, grating rotations), ``beam_elevation_deg``
    and ``beam_azimuth_deg`` (K x C, from the nominal grating; ring 0 is the top beam,
    column 0 the leftmost), ``device``, ``configuration``, ``scan_options`` and what
    :func:`cdma_lidar.host.pointcloud.file_metadata` gives: the toolkit's version, the
    SNR_XC threshold used, ``intensity_unit`` (``reflectance`` with a calibrated gain,
    else :data:`cdma_lidar.host.intensity.RAW_UNIT`) and every field's unit.
    """
    el, az = device.beam_angles_deg()
    doc = {"wavelengths_m": device.wavelengths_m.tolist(),
           "angles_deg": device.column_angles_deg.tolist(),
           "beam_elevation_deg": np.round(el, 6).tolist(),
           "beam_azimuth_deg": np.round(az, 6).tolist(),
           "device": toml_safe(device.identity()),
           "configuration": toml_safe(device.calibration_config()),
           "scan_options": toml_safe(dataclasses.asdict(options))}
    unit = "reflectance" if options.intensity_gain else RAW_UNIT
    return ({k: json.dumps(v) for k, v in doc.items()}
            | file_metadata(_ranging(device, options).snr_threshold_db, unit))


def _ranging(device: Device, options: ScanOptions) -> Any:
    ranging = device.ranging_config(offset_m=options.offset_m, interpolate=options.interpolate,
                                    ghost_windows=options.ghost_windows,
                                    min_support=options.min_support)
    if options.snr_threshold_db is not None:
        ranging = dataclasses.replace(ranging, snr_threshold_db=options.snr_threshold_db)
    return ranging


def _check_ghost_windows(windows: tuple[tuple[int, int], ...], device: Device) -> None:
    """Refuse a ghost window that misses the device's lag gate, or windows covering all of
    it (every pixel would be rejected as a ghost, silently)."""
    if not windows:
        return
    cfg, ns = device.config, device.ranging_config().samples_per_symbol
    start, length = int(cfg.get("gate_start", 0)), int(cfg.get("gate_len", ns))
    gate = (start + np.arange(length)) % ns
    span = f"lags {start} to {start + length - 1} samples (mod {ns})"
    for w in windows:
        if not in_windows(gate, (w,), ns).any():
            raise ConfigError(f"ghost window {w[0]}:{w[1]} lies outside the device's gate, "
                              f"{span}", field="ghost_window")
    if in_windows(gate, windows, ns).all():
        raise ConfigError(f"ghost windows {', '.join(f'{a}:{b}' for a, b in windows)} cover "
                          f"the whole gate, {span}: every pixel would be rejected",
                          field="ghost_window")


def open_scan(device: Device, out: str | os.PathLike[str], options: ScanOptions = ScanOptions(),
              *, resume: bool = False, force: bool = False, frame_id: int | None = None
              ) -> Scan:
    """Check what depends on the device and the output, set the power, and return the scan.

    Frame n is requested with frame id ``frame_id + n`` (default: random), which seeds
    the virtual device's noise. An existing partial scan is resumed (``resume``: it must
    be of the same device, configuration and options), overwritten (``force``) or, with
    neither, left alone with a ConfigError: nothing is deleted without being asked.
    """
    out = check_output(out)
    if device.config.get("mode") == "calibration":
        raise ConfigError("the device is in calibration mode: its columns see the "
                          "zeroth-order target at a 90 deg grating angle, not the scene; scan "
                          "with --set mode=ranging (or use 'cdma-lidar calibrate')", field="mode")
    if options.power_cap is not None and options.power_cap > device.channels:
        raise ConfigError(f"power_cap must be at most {device.channels} (every pixel of a "
                          f"column at its maximum), not {options.power_cap:g}",
                          field="power_cap")
    top = max_snr_xc_db(device.config)
    if options.snr_threshold_db is not None and options.snr_threshold_db > top:
        raise ConfigError(f"snr_threshold_db must be from 0 to {top:.1f} dB (the SNR_XC this "
                          f"configuration can report), not {options.snr_threshold_db:g}",
                          field="snr_threshold")
    _check_ghost_windows(options.ghost_windows, device)
    spath, folder = state_path(out), frames_path(out)
    if not resume and not force and (spath.exists() or folder.exists()):
        raise ConfigError(f"{str(spath)!r} holds an interrupted scan; finish it with --resume "
                          "or start afresh with --force (which overwrites it)", field="resume")
    header = _header(device, options, out)
    k, c = device.channels, device.columns
    done: list[ScanFrame] = []
    if resume:
        state = ScanState.load(spath)
        for key in ("device", "configuration", "options"):
            if state.header.get(key) != header[key]:
                raise ConfigError(
                    f"the partial scan at {str(spath)!r} does not match this scan's {key}; "
                    "resume it with the same device and options, or scan again without "
                    "--resume", field="resume")
        done = _load_frames(folder, state.frame_index, device, _ranging(device, options))
        log.info("resuming frame %d of %d: %d of %d columns already done",
                 state.frame_index + 1, options.frames, int(state.data.done.sum()), c)
    else:
        shutil.rmtree(folder, ignore_errors=True)
        spath.unlink(missing_ok=True)
        base = (int(np.random.default_rng().integers(0, 2**31 - options.frames - 1))
                if frame_id is None else int(frame_id))
        state = ScanState(header=header, frame_index=0, frame_base=base,
                          data=FrameData.empty(k, c, int(device.config.get("uid_bits", 1)),
                                               int(device.config.get("peaks", 1))))
    return Scan(device, out, options, state, done)


def _load_frames(folder: Path, count: int, device: Device, ranging: Any) -> list[ScanFrame]:
    """The ``count`` finished frames a partial scan kept in ``folder``."""
    frames = []
    for i in range(count):
        path = folder / f"frame-{i:05d}.npz"
        try:
            with np.load(path, allow_pickle=False) as z:
                cloud = _cloud_from_records(z["records"], float(z["stamp"]),
                                            device.wavelengths_m, device.column_angles_deg)
                image = image_from_cloud(cloud, ranging)
                image.snr_xc_db = np.asarray(z["snr"])
                frames.append(ScanFrame(index=i, cloud=cloud, image=image,
                                        power=np.asarray(z["power"])))
        except (OSError, ValueError, KeyError) as exc:
            raise ConfigError(f"partial scan frame {str(path)!r} is missing or damaged ({exc}); "
                              "scan again with --force", field="resume") from exc
    return frames


def run_scan(device: Device, out: str | os.PathLike[str], options: ScanOptions = ScanOptions(),
             *, resume: bool = False, force: bool = False, progress: bool = True,
             pictures_too: bool = False, frame_id: int | None = None,
             on_column: Callable[[int, int], None] | None = None,
             on_frame: Callable[[int, PointCloud, NDArray[np.float64]], None] | None = None
             ) -> ScanResult:
    """Scan, build the point cloud and write it to ``out``: open, acquire, finish.

    See :func:`open_scan` (``resume``, ``force``, ``frame_id``), :meth:`Scan.frames`
    (``progress``, ``on_column``; ScanAborted after saving the partial scan when the link
    is lost or the device ends a frame early) and :meth:`Scan.finish` (``pictures_too``).
    ``on_frame(frame_index, cloud, power)`` sees each finished frame with the (K, C) power
    matrix it was scanned with (fractions of the per-pixel maximum), e.g. for a live viewer
    (:mod:`cdma_lidar.host.view`).
    """
    scan = open_scan(device, out, options, resume=resume, force=force, frame_id=frame_id)
    for frame in scan.frames(progress=progress, on_column=on_column):
        if on_frame is not None:
            on_frame(frame.index, frame.cloud, np.array(frame.power, dtype=np.float64))
    return scan.finish(pictures_too=pictures_too)


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
