"""What the host commands do: ``info``, ``scan``, ``view``, ``convert`` and ``calibrate``.

Their options are in :mod:`cdma_lidar.host.cli` (which imports this module only when a
command runs); each ``cmd_NAME(args)`` returns the exit status. See that module for the
error contract.
"""

from __future__ import annotations

import argparse
import logging
import sys
import tempfile
import time
import tomllib
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import tomli_w

from cdma_lidar.errors import ConfigError
from cdma_lidar.fileio import atomic_write_text, check_writable
from cdma_lidar.host.calibration import Calibration
from cdma_lidar.host.cli import connect_options
from cdma_lidar.host.cloud_formats import (
    MULTI_FRAME_FORMATS,
    check_output,
    read_frames,
    write_frames,
)
from cdma_lidar.host.cloud_formats.mcap import read_metadata
from cdma_lidar.host.connection import connect
from cdma_lidar.host.intensity import intensity_gain
from cdma_lidar.host.ranging import (
    DEFAULT_SNR_THRESHOLD_DB,
    ghost_windows_from_image,
    sample_range_m,
)
from cdma_lidar.host.replay import Replay, is_replay
from cdma_lidar.host.scan import (
    ScanOptions,
    calibrate_device,
    default_power_level,
    multi_user_peaks,
    run_scan,
    state_path,
)
from cdma_lidar.host.steer import COMMANDS as STEER_COMMANDS
from cdma_lidar.host.steer import Settings, stdin_commands, steer
from cdma_lidar.host.view import LiveView, view_options, wait_forever

__all__ = ["apply_profile", "cmd_calibrate", "cmd_convert", "cmd_info", "cmd_scan", "cmd_view"]

log = logging.getLogger(__name__)



def _say(*parts: object) -> None:
    """One line of command output on stdout (CLI results, not logging)."""
    sys.stdout.write(" ".join(str(p) for p in parts) + "\n")
    sys.stdout.flush()


def _configure(device: Any, settings: list[tuple[str, Any]]) -> None:
    if settings:
        device.link.set_config(**dict(settings))
        device.refresh_config()


def cmd_info(args: argparse.Namespace) -> int:
    """Print identity, limits, geometry and configuration."""

    with connect(args.port, **connect_options(args)) as dev:
        info, cfg = dev.info, dev.config
        wl = dev.wavelengths_m
        ang = dev.column_angles_deg
        _say(f"device      {info.serial} (firmware {info.firmware_version}, protocol "
              f"{info.protocol_version})")
        _say(f"channels    {dev.channels}: {wl[0] * 1e9:.3f} .. {wl[-1] * 1e9:.3f} nm")
        _say(f"columns     {dev.columns}: {ang[0]:.4f} .. {ang[-1]:.4f} deg")
        _say(f"chip rate   {info.chip_rate_hz / 1e6:g} Mchip/s, code length {dev.code_length}")
        geo = dev.geometry()
        _say(f"grating     {geo.grooves_per_mm:g} lines/mm, incidence {geo.incidence_deg:g} deg, "
              f"tilt {np.degrees(geo.gamma_rad):.3f} deg")
        rc = dev.ranging_config()
        _say(f"range scale {rc.samples_per_chip} samples/chip, "
              f"{100 * sample_range_m(rc.samples_per_chip, rc.chip_rate_hz):.2f} cm per lag "
              "sample")
        for key, value in cfg.items():
            _say(f"  {key:18s} {value}")
    return 0


def apply_profile(args: argparse.Namespace, parser: argparse.ArgumentParser) -> None:
    """Fill the options not given on the command line from ``args.config`` (TOML).

    Keys are the command's long options without dashes (``snr-threshold`` or
    ``snr_threshold``); values go through the same checks as on the command line
    (repeatable options take a list, flags true or false). An option given on the
    command line (any value but its default) wins over the file.
    """
    if not getattr(args, "config", None):
        return
    path = args.config
    try:
        doc = tomllib.loads(Path(path).read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise ConfigError(f"--config {path!r} does not exist", field="config") from None
    except (OSError, UnicodeDecodeError, tomllib.TOMLDecodeError) as exc:
        raise ConfigError(f"--config {path!r} is not a readable TOML file ({exc})",
                          field="config") from None
    actions = {a.dest: a for a in parser._actions
               if a.option_strings and a.dest not in ("help", "config")}
    for key, value in doc.items():
        action = actions.get(key.replace("-", "_"))
        if action is None:
            raise ConfigError(f"--config {path!r}: unknown option {key!r}; allowed: "
                              + ", ".join(sorted(d.replace("_", "-") for d in actions)),
                              field="config")
        if getattr(args, action.dest) != action.default:
            continue  # the command line wins
        setattr(args, action.dest, _profile_value(action, key, value, path))


def _profile_value(action: argparse.Action, key: str, value: Any, path: str) -> Any:
    """One profile value, converted and checked as argparse would on the command line."""
    def bad(allowed: str) -> ConfigError:
        return ConfigError(f"--config {path!r}: {key} must be {allowed}, not {value!r}",
                           field="config")

    if action.nargs == 0:  # a flag
        if not isinstance(value, bool):
            raise bad("true or false")
        return value
    repeat = isinstance(action, argparse._AppendAction)
    items = value if repeat and isinstance(value, list) else [value]
    if any(isinstance(v, dict | list | bool) for v in items):
        raise bad("a number or a string" + (" (or a list of them)" if repeat else ""))
    out = []
    for v in items:
        try:
            conv = action.type(str(v)) if action.type is not None else str(v)
        except argparse.ArgumentTypeError as exc:  # says "must be ..., not ..."
            raise ConfigError(f"--config {path!r}: {key} {exc}", field="config") from None
        except ValueError:
            raise bad("a whole number" if action.type is int else "valid") from None
        if action.choices is not None and conv not in action.choices:
            raise bad("one of " + ", ".join(map(str, action.choices)))
        out.append(conv)
    return out if repeat else out[0]


def cmd_scan(args: argparse.Namespace,
             on_frame: Callable[..., None] | None = None,
             steered: Callable[[Any, Path, ScanOptions], int] | None = None) -> int:
    """Scan and write the point cloud; ``on_frame`` sees each frame (``view``).

    ``steered(device, out, options)`` (``view --steer``) scans instead, once the device
    is connected, configured and its calibration checked; nothing is written.
    """

    apply_profile(args, args.profile_parser)
    for name in ("port", "out"):
        if getattr(args, name) is None:
            raise ConfigError(f"--{name} is required (on the command line or in --config)",
                              field=name)
    out = check_output(args.out)
    if args.calibrate_intensity is not None and not args.calibration:
        raise ConfigError("--calibrate-intensity needs --calibration FILE to store the gain "
                          "in", field="calibrate_intensity")
    if args.resume and not state_path(out).is_file():
        raise ConfigError(f"nothing to resume: {state_path(out)} does not exist; scan "
                          "without --resume", field="resume")
    if args.power_cap is not None and not args.near_far:
        raise ConfigError("--power-cap needs --near-far (a uniform scan uses one power)",
                          field="power_cap")
    cal = Calibration.load(args.calibration) if args.calibration else None
    ghosts = list(args.ghost_window)
    if args.ghost_map:
        ghosts += _load_ghost_map(args.ghost_map)
    if args.save_ghost_map:
        if Path(args.save_ghost_map).suffix.lower() != ".toml":
            raise ConfigError(f"--save-ghost-map must be a .toml file, not "
                              f"{args.save_ghost_map!r}", field="save_ghost_map")
        check_writable(args.save_ghost_map, "--save-ghost-map")
    if args.frame_id is not None and not 0 <= args.frame_id <= 2**31 - 1 - args.frames:
        raise ConfigError(f"--frame-id must be from 0 to {2**31 - 1 - args.frames}, not "
                          f"{args.frame_id}", field="frame_id")
    options = ScanOptions(frames=args.frames, near_far=args.near_far,
                          snr_threshold_db=args.snr_threshold, min_support=args.min_support,
                          interpolate=args.interpolate,
                          ghost_windows=tuple(ghosts), power_cap=args.power_cap,
                          offset_m=cal.offset_m if cal else 0.0, combine=args.combine,
                          keep_foreign=args.keep_foreign,
                          intensity_gain=cal.intensity_gain if cal else None)
    if is_replay(args.port):
        if steered is not None:
            raise ConfigError(f"--steer needs a device, not a replay ({args.port})",
                              field="steer")
        return _replay(args, out, options)
    with connect(args.port, **connect_options(args)) as dev:
        _configure(dev, args.set)
        peaks = multi_user_peaks(dev, {key for key, _ in args.set})
        if peaks:
            _say(f"UID configured ({dev.config.get('uid_bits')} bits): asking for {peaks} "
                 "peaks per channel so other users' returns cannot hide ours (--set peaks=1 "
                 "to turn this off)")
        if cal is not None:
            cal.check_applies(dev.identity(), dev.calibration_config())
        else:
            log.warning("no --calibration: ranges include the system delay")
        if steered is not None:
            steered(dev, out, options)
            return 0
        t0 = time.monotonic()
        try:
            res = run_scan(dev, out, options, resume=args.resume, force=args.force,
                           progress=not args.no_progress, pictures_too=args.pictures,
                           frame_id=args.frame_id, on_frame=on_frame)
        except KeyboardInterrupt:
            sys.stderr.write(f"partial scan saved to {state_path(out)}; run the same command "
                             "with --resume to finish it\n")
            raise
        dt = time.monotonic() - t0
    img = res.image
    _say(f"scanned {res.columns_scanned} columns in {dt:.1f} s; "
          f"{int(img.valid.sum())} of {img.range_m.size} pixels valid "
          f"({100 * float(img.valid.mean()):.1f} %)")
    if args.near_far and len(res.snr_maps) > 1:
        thr = img.config.snr_threshold_db
        fr = [100 * float(np.mean(m >= thr)) for m in res.snr_maps]
        _say(f"pixels above {thr:g} dB per frame (of all {img.range_m.size}): "
             + ", ".join(f"{f:.1f} %" for f in fr))
        cap = args.power_cap if args.power_cap is not None else \
            dev.channels * default_power_level(dev, options.initial_power)
        _say(f"largest column power sum per frame (cap {cap:g} x the per-pixel maximum): "
             + ", ".join(f"{float(p.sum(axis=0).max()):.2f}" for p in res.powers[:-1]))
    if len(img.foreign):
        users = ", ".join(f"UID {u}: {n}" for u, n in img.foreign.users().items())
        fate = ("kept in the cloud with their user_id" if args.keep_foreign
                else "rejected; --keep-foreign keeps them")
        _say(f"other users' returns: {len(img.foreign)} ({users}), {fate}")
    if args.calibrate_intensity is not None:
        assert cal is not None
        # the last frame's power matrix (near-far's list also holds the next frame's)
        power = res.powers[-2] if args.near_far and len(res.powers) > 1 else res.powers[-1]
        cal.intensity_gain = intensity_gain(res.clouds[-1].peak, res.clouds[-1].range, power,
                                            dev.config, args.calibrate_intensity,
                                            res.clouds[-1].flags == 0)
        cal.save(args.calibration)
        _say(f"intensity gain {cal.intensity_gain:.6g} (a flat target of reflectivity "
             f"{args.calibrate_intensity:g}); added to {args.calibration}")
    if args.save_ghost_map:

        windows = ghost_windows_from_image(img)
        text = tomli_w.dumps({"windows": [list(w) for w in windows],
                              "device": dev.identity()})
        atomic_write_text(args.save_ghost_map, text)
        _say(f"ghost map: {len(windows)} windows {list(windows)}; wrote {args.save_ghost_map}")
    for f in res.files:
        if not getattr(args, "temporary_out", False):
            _say(f"wrote {f}")
    return 0


def cmd_view(args: argparse.Namespace) -> int:
    """Scan as ``scan`` does, logging every finished frame to a rerun viewer."""
    apply_profile(args, args.profile_parser)
    if args.out is None and (args.pictures or args.resume):
        raise ConfigError("--pictures and --resume need --out FILE in view", field="out")
    threshold = (DEFAULT_SNR_THRESHOLD_DB if args.snr_threshold is None
                 else args.snr_threshold)
    if args.steer:
        for name in ("out", "pictures", "resume", "calibrate_intensity", "save_ghost_map"):
            if getattr(args, name):
                raise ConfigError(f"--{name.replace('_', '-')} needs a finished scan; --steer "
                                  "scans until quit (keep it with --save FILE.rrd)",
                                  field=name)
    live = LiveView(view_options(args, threshold), description=f"cdma-lidar view {args.port}")
    if live.url:
        _say(f"web viewer: {live.url}")
    steered = None
    if args.steer:
        settings = Settings(threshold_db=threshold, power_cap=args.power_cap,
                            near_far=args.near_far, color_by=args.color_by)
        frames, args.frames = (args.frames if args.frames > 1 else None), max(args.frames, 2)
        pending = stdin_commands(sys.stdin)
        _say("steer: type " + ", ".join(f"{k} {v}".strip() for k, v in STEER_COMMANDS.items())
             + " (one a line; from the next frame on)")

        def steered(dev: Any, out: Path, options: ScanOptions) -> int:
            try:
                return steer(dev, out, options, settings, pending, live, frames=frames,
                             frame_id=args.frame_id,
                             say=lambda text: sys.stderr.write(f"cdma-lidar view: {text}\n"))
            except KeyboardInterrupt:  # Ctrl-C ends a steered scan as `quit` does
                return live.frames
    # Without --out the cloud goes to a temporary file that is never reported.
    with tempfile.TemporaryDirectory(prefix="cdma-lidar-view-") as tmp:
        if args.out is None:
            args.out, args.temporary_out = str(Path(tmp) / "view.npz"), True
        try:
            code = cmd_scan(args, on_frame=live.log_frame, steered=steered)
        except BaseException:
            live.close()
            raise
    _say(f"viewed {live.frames} frames" + (f"; recording in {args.save}" if args.save else ""))
    try:
        if live.url:
            _say("serving the web viewer; Ctrl-C ends it")
        live.close(wait=wait_forever)
    except KeyboardInterrupt:  # Ctrl-C between the line above and the wait: the same end
        live.close()
    return code


def _replay(args: argparse.Namespace, out: Path, options: ScanOptions) -> int:
    """``scan --port replay://FILE``: a recording through the host's writers and pictures."""
    for name in ("set", "calibration", "calibrate_intensity", "save_ghost_map", "resume"):
        if getattr(args, name):
            raise ConfigError(f"--{name.replace('_', '-')} needs a device, not a replay "
                              f"({args.port})", field=name)
    replay = Replay(args.port, out, options)
    res = replay.finish(pictures_too=args.pictures)
    img = res.image
    _say(f"replayed {len(res.clouds)} frames from {replay.source}; {int(img.valid.sum())} of "
         f"{img.range_m.size} pixels valid in the last")
    for f in res.files:
        _say(f"wrote {f}")
    return 0


def cmd_convert(args: argparse.Namespace) -> int:
    """Convert a cloud file between formats (every frame where the output holds several)."""
    out = check_output(args.out_file, "OUT")
    clouds = read_frames(args.in_file)
    meta = read_metadata(args.in_file) if Path(args.in_file).suffix.lower() == ".mcap" else {}
    n = write_frames(clouds, out, meta)
    kept = len(clouds) if out.suffix.lower() in MULTI_FRAME_FORMATS else 1
    _say(f"wrote {n} points of {kept} of {len(clouds)} frames to {out}"
         + ("" if kept == len(clouds) else " (this format holds one frame: the last)"))
    return 0


def _load_ghost_map(path: str) -> list[tuple[int, int]]:
    try:
        doc = tomllib.loads(Path(path).read_text(encoding="utf-8"))
        windows = [(int(a), int(b)) for a, b in doc["windows"]]
    except FileNotFoundError:
        raise ConfigError(f"ghost map {path!r} does not exist; make one with "
                          "--save-ghost-map on an empty field", field="ghost_map") from None
    except OSError as exc:  # a folder, a symlink loop, no permission
        raise ConfigError(f"ghost map {path!r} cannot be read ({exc.strerror})",
                          field="ghost_map") from None
    except (tomllib.TOMLDecodeError, KeyError, TypeError, ValueError) as exc:
        raise ConfigError(f"ghost map {path!r} is not a list of [start, length] windows "
                          f"({exc})", field="ghost_map") from None
    if any(a < 0 or b < 1 for a, b in windows):
        raise ConfigError(f"ghost map {path!r} has a window with start < 0 or length < 1",
                          field="ghost_map")
    return windows


def cmd_calibrate(args: argparse.Namespace) -> int:
    """Zeroth-order calibration to a TOML file."""

    out = Path(args.out)
    if out.suffix.lower() != ".toml":
        raise ConfigError(f"--out must be a .toml file, not {str(out)!r}", field="out")
    check_writable(out, "--out")
    if not 1 <= args.shots <= 65535:
        raise ConfigError(f"--shots must be from 1 to 65535, not {args.shots}", field="shots")
    with connect(args.port, **connect_options(args)) as dev:
        _configure(dev, args.set)
        cal = calibrate_device(dev, args.target_distance, shots=args.shots,
                               snr_threshold_db=args.snr_threshold,
                               max_spread_m=args.max_spread)
    cal.save(out)
    _say(f"offset {cal.offset_m:.4f} m, spread {cal.spread_m:.4f} m from {cal.samples} "
          f"returns of {cal.shots} shots; wrote {out}")
    return 0
