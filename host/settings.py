"""Defaults and allowed values of the host's options, importable without numpy.

``cdma-lidar COMMAND --help`` shows them (:mod:`cdma_lidar.host.cli` builds the parser
from this module alone, so help starts without loading the host stack); the modules that
act on them (ranging, calibration, combine, the viewer, capture) import them from here.
"""

from __future__ import annotations

__all__ = ["CAPTURE_KINDS", "COLOR_MAPS", "COMBINE_MODES", "DEFAULT_SNR_THRESHOLD_DB",
           "GRPC_PORT", "LOOPBACK", "MIN_TIMEOUT_S", "TARGET_DISTANCE_M", "WEB_PORT"]

#: Pixels below this SNR_XC (dB) are rejected unless ``--snr-threshold`` says otherwise.
DEFAULT_SNR_THRESHOLD_DB = 16.0

#: The shortest ``--timeout`` (s): a request's round trip (a column's frames on a serial
#: line, a loaded host) takes longer than this, so a shorter wait only fails, and the
#: error would blame a device that was never given time to answer.
MIN_TIMEOUT_S = 0.05

#: Allowed ``--target-distance`` of a calibration (m): from, to.
TARGET_DISTANCE_M = (0.01, 1000.0)

#: How N frames become one cloud (``--combine``; :mod:`cdma_lidar.host.combine`).
COMBINE_MODES = ("last", "mean", "median")

#: What ``view`` colours the points by (``--color-by``; :data:`cdma_lidar.host.view.COLOR_BY`).
COLOR_MAPS = ("range", "snr", "intensity", "ring")

#: rerun's default ports: gRPC (the log stream) and the web viewer (HTTP).
GRPC_PORT, WEB_PORT = 9876, 9090

#: Where everything ``view`` serves listens unless ``--bind`` says otherwise.
LOOPBACK = "127.0.0.1"

#: What ``capture`` records (``--kind``; :mod:`cdma_lidar.host.capture`).
CAPTURE_KINDS = ("corr", "raw")
