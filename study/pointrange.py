"""Repeated single-point ranging on the simulated instrument (paper Fig. 2c, 2d).

One pixel of a scene (one channel of one column), the other channels dark (laser power 0,
so no multi-channel interference: the paper's Fig. 2c measures a single channel),
acquired ``repeats`` times with independent noise (frame ids 0..repeats-1) through the
device's acquisition path (:func:`cdma_lidar.scene.acquire.acquire`: the scene's
repetition sums, then the bit-exact chain
:class:`~cdma_lidar.firmware_model.receiver.FastReceiver`, ``method="auto"``, on the
pixel's channel, with a gate of at least 32 chips of lags) and turned into ranges the
host's way: peak lag plus the sub-sample correction
(:func:`cdma_lidar.host.ranging.subsample_delta`), times the sample's range, minus the
true system delay (perfect calibration).

Eq. 27 needs the per-sample SNR: the pixel's eq. 30 SNR from the instrument's link
budget (:meth:`~cdma_lidar.scene.instrument.Instrument.link_figures`, one channel lit, so
signal against noise alone), times the R * n code periods the receiver sums (the noise
averages, the echo does not), with N_s = N * S samples per symbol.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from cdma_lidar.errors import out_of_range
from cdma_lidar.firmware_model.receiver import FastReceiver
from cdma_lidar.host.ranging import lag_to_range_m, precision_eq27_m, subsample_delta
from cdma_lidar.scene import load_scene
from cdma_lidar.scene.acquire import acquire
from cdma_lidar.scene.instrument import Instrument, RenderSettings
from cdma_lidar.study.simulate import receiver_setup, smallest_out_shift, true_offset_m

__all__ = ["PointRanges", "repeat_ranges"]


@dataclass
class PointRanges:
    """``repeats`` ranges (m) of one pixel, its true range (m) and what eq. 27 predicts."""

    range_m: NDArray[np.float64]
    truth_m: float
    snr_eq30_db: float          # per sample, one code period
    snr_effective_db: float     # per sample after summing R * n periods (eq. 27's SNR)
    samples_per_symbol: int     # N_s = N * S
    chip_rate_hz: float
    precision_eq27_m: float     # sigma of eq. 27
    snr_xc_median_db: float

    @property
    def resolution_2sigma_m(self) -> float:
        """The paper's depth resolution: twice the measured standard deviation (m)."""
        return 2.0 * float(np.std(self.range_m, ddof=1))


def repeat_ranges(scene: str, overrides: dict[str, Any], repeats: int, seed: int, *,
                  channel: int = 20, column: int = 0, method: str = "triangle"
                  ) -> PointRanges:
    """Range pixel (``channel``, ``column``) of ``scene`` (+ ``overrides``) ``repeats`` times."""
    inst = Instrument(load_scene(scene, overrides), seed=seed)
    k, c = inst.channels, inst.columns
    if not 0 <= channel < k:
        raise out_of_range("channel", f"0..{k - 1}", channel)
    if not 0 <= column < c:
        raise out_of_range("column", f"0..{c - 1}", column)
    if not inst.truth.hits.lit[channel, column]:
        raise out_of_range("channel/column", "a pixel that sees an object", (channel, column))
    spec = inst.spec
    power = np.zeros(k)
    power[channel] = inst.default_power_w[channel, column]
    sp = spec.samples_per_chip
    # The device's defaults (128 lags, +-8 excluded) suit S = 4; at larger S the peak's own
    # triangle (+-S lags, wider through the detector) would count as noise floor and a
    # 128-lag gate holds few chips, so exclude +-2S and keep at least 32 chips of lags.
    cfg, codes = receiver_setup(inst, gate=inst.default_gate(minimum=max(128, 32 * sp)))
    cfg = smallest_out_shift(cfg.replace(peak_exclude=max(cfg.peak_exclude, 2 * sp)),
                             codes.shape[1])
    rx = FastReceiver(cfg, codes[channel:channel + 1])
    settings = RenderSettings.from_spec(spec)
    lags, peaks, nbs, snr_xc = [], [], [], []
    for f in range(repeats):
        for out in acquire(inst, rx, settings, f, [column], [power]).outputs:
            lags.append(int(out.peak_lag[0]))
            peaks.append(int(out.peak[0]))
            nbs.append(out.neighbours[0].astype(np.float64))
            snr_xc.append(float(out.snr_db()[0]))
    delta = subsample_delta(np.array(peaks, dtype=np.float64), np.array(nbs), method)
    rng = lag_to_range_m(np.array(lags) + delta, spec.samples_per_chip, spec.chip_rate_hz,
                         true_offset_m(inst))
    p = np.zeros_like(inst.default_power_w)
    p[:, column] = power
    snr30 = float(inst.link_figures(power_w=p)["snr_db"][channel, column])
    periods = spec.averages * spec.uid_bits
    snr_eff = snr30 + 10 * np.log10(periods)
    ns = spec.code_length * spec.samples_per_chip
    sigma27 = float(precision_eq27_m(spec.chip_rate_hz, ns, snr=10 ** (snr_eff / 10)))
    return PointRanges(range_m=rng, truth_m=float(inst.truth.range_m[channel, column]),
                       snr_eq30_db=snr30, snr_effective_db=float(snr_eff),
                       samples_per_symbol=ns, chip_rate_hz=spec.chip_rate_hz,
                       precision_eq27_m=sigma27,
                       snr_xc_median_db=float(np.median(snr_xc)))
