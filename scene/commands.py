"""The work of ``cdma-lidar scene ...`` (its options: :mod:`cdma_lidar.scene.cli`).

Imported when a command runs: loading and rendering a scene needs numpy and the
instrument model; ``scene list`` without ``--markdown`` needs neither.
"""

from __future__ import annotations

import argparse
import logging
import sys

import numpy as np

from cdma_lidar.errors import ConfigError
from cdma_lidar.fileio import check_writable
from cdma_lidar.scene.instrument import Instrument
from cdma_lidar.scene.loader import PRESETS, load_scene
from cdma_lidar.scene.truth import save_truth

__all__ = ["cmd_markdown", "cmd_show", "cmd_truth"]

log = logging.getLogger(__name__)


def cmd_markdown(args: argparse.Namespace) -> int:
    """``scene list --markdown``: docs/scene.md's table of name, description and pixels."""
    sys.stdout.write("| name | what | pixels (channels x columns) |\n|---|---|---|\n")
    for name in PRESETS:
        scene = load_scene(name)
        spec = scene.instrument
        sys.stdout.write(f"| `{name}` | {scene.description} | "
                         f"{spec.channels} x {spec.columns} |\n")
    return 0


def cmd_show(args: argparse.Namespace) -> int:
    """``scene show SCENE``: instrument, objects and lit pixels."""
    scene = load_scene(args.scene)
    inst = Instrument(scene, 0)
    spec = scene.instrument
    h = inst.truth.hits
    lines = [
        f"scene {scene.name}: {scene.description}",
        f"  pixels {spec.channels} x {spec.columns}, lit {int(h.lit.sum())}, "
        f"channels lit somewhere {int(h.lit.any(axis=1).sum())}",
        f"  wavelengths {spec.wavelengths_m[0] * 1e9:.3f}..{spec.wavelengths_m[-1] * 1e9:.3f} nm, "
        f"rotations {spec.rotations_deg.min():.3f}..{spec.rotations_deg.max():.3f} deg",
        f"  code degree {spec.code_degree}, {spec.chip_rate_hz / 1e6:g} Mchip/s, "
        f"S={spec.samples_per_chip}, R={spec.averages}, uid {spec.uid}/{spec.uid_bits} bits",
        f"  noise rms {inst.noise_rms_v * 1e3:.3f} mV (median column), fidelity "
        f"{scene.fidelity}, default gate {inst.default_gate()}",
        f"  calibration target (zeroth order) at {scene.calibration.target_distance_m:g} m: "
        f"calibrate with --target-distance {scene.calibration.target_distance_m:g}",
    ]
    for i, obj in enumerate(scene.objects):
        sel = h.object_id == i
        rng = h.range_m[sel]
        span = f"{rng.min():.3f}..{rng.max():.3f} m" if rng.size else "not seen"
        lines.append(f"  objects[{i}] {obj.kind:6s} {obj.name:14s} pixels {int(sel.sum()):5d} "
                     f"range {span}")
    sys.stdout.write("\n".join(lines) + "\n")
    return 0


def cmd_truth(args: argparse.Namespace) -> int:
    """``scene truth SCENE --out FILE``: per-pixel ground truth as NPZ."""
    if not str(args.out).lower().endswith(".npz"):
        raise ConfigError(f"--out must be a .npz file, not {args.out!r}", "out")
    check_writable(args.out, "--out")
    scene = load_scene(args.scene)
    figures = Instrument(scene, args.seed).link_figures()
    try:
        truth = save_truth(scene, args.out, figures)
    except OSError as exc:  # the folder changed under us after the check
        raise ConfigError(f"--out {args.out!r}: cannot write it ({exc.strerror}); choose a "
                          "writable folder", "out") from None
    lit = truth.hits.lit
    rng = truth.range_m[lit]
    summary = f"{rng.min():.3f}..{rng.max():.3f} m" if rng.size else "no hits"
    snr = figures["snr_db"][lit]
    if snr.size:
        summary += (f", SNR (eq. 30) median {np.median(snr):.1f} dB, SNR_SS (eq. 43) median "
                    f"{np.median(figures['snr_ss_db'][lit]):.1f} dB")
    sys.stdout.write(f"{args.out}: {lit.shape[0]} x {lit.shape[1]} pixels, "
                     f"{int(lit.sum())} hit ({summary})\n")
    return 0
