"""``replay://FILE``: a recorded scan fed back through the host instead of a device.

:class:`Replay` has the shape of :class:`cdma_lidar.host.scan.Scan`: ``frames()`` yields a
:class:`~cdma_lidar.host.scan.ScanFrame` per recorded frame (an ``.mcap`` holds one per
frame, the other formats one) and ``finish()`` writes them to the output like a scan does
(every frame to ``.mcap``, the last to the others; pictures on request), so
``cdma-lidar scan --port replay://scan.mcap --out again.ply --pictures`` redraws a
recording, and whatever consumes a scan's frames (a viewer, a recorder) takes a replay
too. A replay has no device: ranges are as recorded (its calibration and threshold
stay), ``--combine`` other than ``last``, ``--near-far`` and device settings are refused.
"""

from __future__ import annotations

import json
import logging
import os
from collections.abc import Callable, Iterator
from pathlib import Path

import numpy as np

from cdma_lidar.errors import ConfigError
from cdma_lidar.host import pictures
from cdma_lidar.host.cloud_formats import (
    MULTI_FRAME_FORMATS,
    check_output,
    read_frames,
    write_frames,
)
from cdma_lidar.host.cloud_formats.mcap import read_metadata
from cdma_lidar.host.intensity import RAW_UNIT
from cdma_lidar.host.pointcloud import file_metadata
from cdma_lidar.host.ranging import RangingConfig
from cdma_lidar.host.scan import ScanFrame, ScanOptions, ScanResult, image_from_cloud, picture_paths

__all__ = ["SCHEME", "Replay", "is_replay"]

log = logging.getLogger(__name__)

#: URL scheme of a replayed recording.
SCHEME = "replay://"


def is_replay(url: str) -> bool:
    """Whether a ``--port`` URL names a recording (``replay://FILE``)."""
    return url.lower().startswith(SCHEME)


class Replay:
    """A recording read back as a scan (module docstring): ``frames()`` then ``finish()``."""

    def __init__(self, url: str, out: str | os.PathLike[str],
                 options: ScanOptions | None = None) -> None:
        options = options if options is not None else ScanOptions()
        path = Path(url[len(SCHEME):] if is_replay(url) else url)
        if options.combine != "last" or options.near_far:
            raise ConfigError("a replay keeps the recorded frames: --combine last only, no "
                              "--near-far", field="combine")
        self.source, self.out, self.options = path, check_output(out), options
        self.clouds = read_frames(path)
        if not self.clouds:
            raise ConfigError(f"{str(path)!r} holds no frame", field="port")
        if options.frames > len(self.clouds):
            raise ConfigError(f"--frames {options.frames} asks for more frames than "
                              f"{str(path)!r} holds ({len(self.clouds)})", field="frames")
        self.metadata = read_metadata(path) if path.suffix.lower() == ".mcap" else {}
        threshold = options.snr_threshold_db
        self.ranging = RangingConfig() if threshold is None else \
            RangingConfig(snr_threshold_db=threshold)
        recorded = json.loads(self.metadata.get("snr_threshold_db", "null"))
        unit = json.loads(self.metadata.get("intensity_unit", json.dumps(RAW_UNIT)))
        self.metadata |= file_metadata(
            recorded if threshold is None and recorded is not None
            else self.ranging.snr_threshold_db, unit)
        self.done: list[ScanFrame] = []
        self.columns_scanned = 0

    def frames(self, *, progress: bool = False,
               on_column: Callable[[int, int], None] | None = None) -> Iterator[ScanFrame]:
        """The recorded frames, in order (``progress`` and ``on_column`` as for a scan)."""
        for i, cloud in enumerate(self.clouds[len(self.done):], start=len(self.done)):
            if on_column is not None:
                for col in range(cloud.shape[1]):
                    on_column(i, col)
            self.columns_scanned += cloud.shape[1]
            frame = ScanFrame(index=i, cloud=cloud, image=image_from_cloud(cloud, self.ranging),
                              power=np.full(cloud.shape, np.nan))
            self.done.append(frame)
            yield frame

    def finish(self, *, pictures_too: bool = False) -> ScanResult:
        """Write the frames to the output (and pictures); returns them as a ScanResult."""
        for _ in self.frames():
            pass
        clouds = [f.cloud for f in self.done]
        last = self.done[-1]
        multi = self.out.suffix.lower() in MULTI_FRAME_FORMATS
        write_frames(clouds if multi else clouds[-1:], self.out, self.metadata)
        files = [self.out]
        if pictures_too:
            angles = None
            if "beam_elevation_deg" in self.metadata:
                angles = pictures.Angles(
                    np.array(json.loads(self.metadata["beam_elevation_deg"])),
                    np.array(json.loads(self.metadata["beam_azimuth_deg"])))
                if angles.elevation_deg.shape != last.cloud.shape:
                    angles = None
            title = f"replay of {self.source.name}, frame {last.index} of {len(self.done)}"
            files += pictures.scan_pictures(
                picture_paths(self.out), last.cloud, [last.image.snr_xc_db],
                self.ranging.snr_threshold_db, title=title, frame_titles=["SNR_XC"],
                angles=angles)
        return ScanResult(cloud=last.cloud, image=last.image, data=None,  # type: ignore[arg-type]
                          snr_maps=[f.image.snr_xc_db for f in self.done],
                          powers=[], columns_scanned=self.columns_scanned, files=files,
                          clouds=clouds)
