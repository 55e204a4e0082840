"""Steering a running ``cdma-lidar view --steer``: settings typed where the command runs.

rerun 0.41 sends nothing back from its viewers to the process that logs: its viewer
events (play, pause, a selection, the time cursor) reach only its Jupyter widget, and
none carries a value a person chose. So the settings are typed into the terminal that
runs ``view --steer``, one command a line, and take effect from the next frame:

==================  =================================================================
``threshold DB``    SNR_XC threshold (dB) the next frames accept pixels from
``averages N``      the device's averages per symbol (set before the next frame)
``cap X``           near-far power cap per column (x the per-pixel maximum; with
                    near-far on)
``near-far on|off``  per-pixel power control (needs 2 frames: it starts afresh)
``color FIELD``     colour the points by range, snr, intensity or ring (the last frame
                    is redrawn at once)
``quit``            end the scan (as Ctrl-C does)
==================  =================================================================

A command that is not one of these, or a value out of its range, is answered with one
line naming the field and what is allowed; the scan goes on. Nothing listens on a
network: only the person at the terminal (or a program writing to its stdin) steers.

The scan runs frame after frame (:func:`steer`); a change of threshold, averages, cap
or near-far ends the scan in progress after its frame and opens the next with the new
settings, a change of colour only redraws. The commands come from a callable
(``pending() -> lines typed since the last call``): :func:`stdin_commands` reads them on
a thread; tests pass a list per frame.
"""

from __future__ import annotations

import dataclasses
import logging
import math
import os
import queue
import threading
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from typing import Any, TextIO

import numpy as np

from cdma_lidar.errors import CdmaLidarError, ConfigError
from cdma_lidar.host.scan import ScanOptions, open_scan
from cdma_lidar.host.settings import COLOR_MAPS

__all__ = ["COMMANDS", "Settings", "apply", "stdin_commands", "steer"]

log = logging.getLogger(__name__)

#: Every command word with what it takes (the module docstring's table).
COMMANDS = {"threshold": "DB", "averages": "N", "cap": "X", "near-far": "on|off",
            "color": "|".join(COLOR_MAPS), "quit": ""}

#: Frames one scan of a steered view holds at most (a new scan starts after them).
_FRAMES_PER_SCAN = 1000


@dataclass(frozen=True)
class Settings:
    """What a person may change while a view scans.

    Attributes:
        threshold_db: SNR_XC threshold (dB, >= 0).
        averages: the device's averages per symbol (None: as configured).
        power_cap: near-far cap per column (x the per-pixel maximum; None: the default).
        near_far: per-pixel power control on.
        color_by: one of :data:`cdma_lidar.host.settings.COLOR_MAPS`.
        quit: the person asked to end the view.
    """

    threshold_db: float
    averages: int | None = None
    power_cap: float | None = None
    near_far: bool = False
    color_by: str = "range"
    quit: bool = False

    def scan_changed(self, other: Settings) -> bool:
        """Whether going to ``other`` needs a new scan (anything but the colour)."""
        keys = ("threshold_db", "averages", "power_cap", "near_far")
        return any(getattr(self, k) != getattr(other, k) for k in keys)


def apply(line: str, now: Settings) -> Settings:
    """``now`` changed by one typed command; ConfigError (one line) for a bad one."""
    words = line.split()
    if not words:
        return now
    word, args = words[0].lower(), words[1:]
    if word not in COMMANDS:
        raise ConfigError(f"unknown command {words[0]!r}; commands: "
                          + ", ".join(f"{k} {v}".strip() for k, v in COMMANDS.items()),
                          field="command")
    if word == "quit":
        return dataclasses.replace(now, quit=True)
    if len(args) != 1:
        raise ConfigError(f"{word} takes one value, {COMMANDS[word]}, not {len(args)}",
                          field=word)
    text = args[0]
    if word == "near-far":
        if text.lower() not in ("on", "off"):
            raise ConfigError(f"near-far must be on or off, not {text!r}", field="near_far")
        return dataclasses.replace(now, near_far=text.lower() == "on")
    if word == "color":
        if text.lower() not in COLOR_MAPS:
            raise ConfigError(f"color must be one of {', '.join(COLOR_MAPS)}, not {text!r}",
                              field="color_by")
        return dataclasses.replace(now, color_by=text.lower())
    try:
        value = int(text) if word == "averages" else float(text)
    except ValueError:
        raise ConfigError(f"{word} must be a {'whole ' * (word == 'averages')}number "
                          f"({COMMANDS[word]}), not {text!r}", field=word) from None
    if word == "threshold":
        if not (math.isfinite(value) and value >= 0):
            raise ConfigError(f"threshold must be a number of dB from 0, not {text!r}",
                              field="threshold")
        return dataclasses.replace(now, threshold_db=float(value))
    if word == "averages":
        if not 1 <= value <= 1024:
            raise ConfigError(f"averages must be from 1 to 1024, not {text!r}",
                              field="averages")
        return dataclasses.replace(now, averages=int(value))
    if not (math.isfinite(value) and value > 0):
        raise ConfigError(f"cap must be a positive number of per-pixel maxima, not {text!r}",
                          field="power_cap")
    return dataclasses.replace(now, power_cap=float(value))


def stdin_commands(stream: TextIO) -> Callable[[], list[str]]:
    """``pending()`` of the lines ``stream`` gives, read on a daemon thread (a terminal's
    stdin blocks; the scan must not)."""
    lines: queue.Queue[str] = queue.Queue()

    def read() -> None:
        for line in stream:
            lines.put(line)

    threading.Thread(target=read, name="view-commands", daemon=True).start()

    def pending() -> list[str]:
        out = []
        while True:
            try:
                out.append(lines.get_nowait())
            except queue.Empty:
                return out
    return pending


def steer(device: Any, out: str | os.PathLike[str], options: ScanOptions, settings: Settings,
          pending: Callable[[], Iterable[str]], live: Any, *, frames: int | None = None,
          frame_id: int | None = None, say: Callable[[str], None] = log.warning) -> int:
    """Scan ``device`` frame after frame into ``live`` (a :class:`~cdma_lidar.host.view.
    LiveView`), applying the commands ``pending()`` gives after each frame; returns the
    frames viewed. Ends at ``quit`` or after ``frames`` frames (None: only at ``quit`` or
    Ctrl-C). ``out`` is where the scans keep their partial state (a scratch .npz).
    ``say`` gets the one-line answer to a bad command.
    """
    done = 0
    while not settings.quit and (frames is None or done < frames):
        if settings.averages is not None and device.config.get("averages") != settings.averages:
            device.link.set_config(averages=settings.averages)
            device.refresh_config()
        count = _FRAMES_PER_SCAN if frames is None else max(frames - done, 2)
        opts = dataclasses.replace(
            options, frames=count, near_far=settings.near_far,
            snr_threshold_db=settings.threshold_db,
            power_cap=settings.power_cap if settings.near_far else None)
        live.threshold_db = settings.threshold_db
        first = None if frame_id is None else frame_id + done
        scan = open_scan(device, out, opts, force=True, frame_id=first)
        for frame in scan.frames(progress=False):
            live.log_frame(done, frame.cloud, np.array(frame.power, dtype=np.float64))
            done += 1
            new = settings
            for line in pending():
                try:
                    new = apply(line, new)
                except CdmaLidarError as exc:
                    say(str(exc))
            if new.color_by != settings.color_by:
                live.recolor(new.color_by)
            changed, settings = settings.scan_changed(new), new
            if changed or settings.quit or (frames is not None and done >= frames):
                break
    return done
