"""Steering ``view --steer`` headless: typed commands change the scan between frames.

The commands come from a list per frame (what ``pending()`` returns after each frame), so
nothing waits on a clock; the viewer is a recorder of what the scan logs to it.
"""

from __future__ import annotations

import io
import time

import numpy as np
import pytest

import cdma_lidar.virtual  # noqa: F401 - registers virtual:// with pyserial
from cdma_lidar.errors import ConfigError
from cdma_lidar.host.connection import connect
from cdma_lidar.host.scan import ScanOptions
from cdma_lidar.host.steer import Settings, apply, stdin_commands, steer

START = Settings(threshold_db=16.0)


@pytest.mark.parametrize(("line", "field", "value"), [
    ("threshold 25.5", "threshold_db", 25.5),
    ("averages 20", "averages", 20),
    ("cap 12", "power_cap", 12.0),
    ("near-far on", "near_far", True),
    ("NEAR-FAR off", "near_far", False),
    ("color intensity", "color_by", "intensity"),
    ("color ring", "color_by", "ring"),
    ("quit", "quit", True),
    ("   ", "threshold_db", 16.0),
])
def test_each_command_changes_its_setting(line, field, value) -> None:
    assert getattr(apply(line, START), field) == value


@pytest.mark.parametrize(("line", "words"), [
    ("bogus 3", ["unknown command 'bogus'", "threshold DB"]),
    ("threshold", ["threshold takes one value"]),
    ("threshold -1", ["threshold must be", "from 0"]),
    ("threshold nan", ["threshold must be"]),
    ("averages 2.5", ["averages must be a whole number"]),
    ("averages 5000", ["from 1 to 1024"]),
    ("cap 0", ["cap must be a positive number"]),
    ("near-far maybe", ["near-far must be on or off"]),
    ("color blue", ["color must be one of range, snr, intensity, ring"]),
])
def test_a_bad_command_is_one_line_naming_the_field(line, words) -> None:
    with pytest.raises(ConfigError) as exc:
        apply(line, START)
    assert "\n" not in str(exc.value)
    for word in words:
        assert word in str(exc.value)


class Recorder:
    """What a LiveView is given: each frame (with the threshold then) and each recolour."""

    def __init__(self) -> None:
        self.threshold_db = 16.0
        self.frames: list[tuple[int, float, np.ndarray, np.ndarray]] = []
        self.colors: list[str] = []

    def log_frame(self, index, cloud, power) -> None:
        self.frames.append((index, self.threshold_db, cloud.snr_xc[cloud.flags == 0], power))

    def recolor(self, color_by: str) -> None:
        self.colors.append(color_by)


def test_commands_change_the_running_scan(tmp_path) -> None:
    script = iter([["threshold 20"], ["averages 20", "color snr"], ["near-far on", "cap 20"],
                   ["bogus", "threshold -1"], [], ["quit"]])
    said: list[str] = []
    live = Recorder()
    with connect("virtual://flat-wall?seed=1") as dev:
        averages_before = dev.config["averages"]
        n = steer(dev, tmp_path / "scratch.npz", ScanOptions(), START, lambda: next(script),
                  live, frame_id=7, say=said.append)
        averages_after = dev.config["averages"]
    assert n == 6 and [f[0] for f in live.frames] == list(range(6))
    thresholds = [f[1] for f in live.frames]
    assert thresholds == [16.0, 20.0, 20.0, 20.0, 20.0, 20.0]
    # the threshold reached the ranging: no pixel below 20 dB is valid from frame 1 on
    assert live.frames[0][2].min() < 20 <= np.concatenate([f[2] for f in live.frames[1:]]).min()
    assert (averages_before, averages_after) == (10, 20)
    assert live.colors == ["snr"]
    # near-far from frame 3 on: after its first frame the power matrix is far from uniform
    # and a column's sum reaches the new cap (20 per-pixel maxima, not the 10 of 40 x 0.25)
    powers = [f[3] for f in live.frames]
    assert all(np.ptp(p) == 0 for p in powers[:3]) and np.ptp(powers[4]) > 0.1
    assert powers[4].sum(axis=0).max() == pytest.approx(20, rel=1e-3)
    assert [s.split(";")[0] for s in said] == ["unknown command 'bogus'",
                                               "threshold must be a number of dB from 0, "
                                               "not '-1'"]


def test_frames_ends_a_steered_view_without_quit(tmp_path) -> None:
    live = Recorder()
    with connect("virtual://flat-wall?seed=1") as dev:
        n = steer(dev, tmp_path / "s.npz", ScanOptions(), START, list, live, frames=2,
                  frame_id=1)
    assert n == 2 and len(live.frames) == 2


def test_stdin_commands_hands_over_every_line() -> None:
    pending = stdin_commands(io.StringIO("threshold 20\ncolor snr\n"))
    got: list[str] = []
    end = time.monotonic() + 60   # a generous bound: the reader thread needs no set time
    while len(got) < 2 and time.monotonic() < end:
        got += pending()
    assert [g.strip() for g in got] == ["threshold 20", "color snr"]
