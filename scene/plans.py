"""The plans of the drawn repetition sums: each column's mean and noise scale, and the draw.

A column's plan is what its R-repetition sum is drawn from (:mod:`cdma_lidar.scene.sums`):
its mean in LSB (echoes, ghosts and other users scaled by the ADC, with the offset and the
rounding's constant) and the draw's scale (the noise rms in LSB), or None where the
fidelity level cannot draw the sum (noise under its floor, echoes near the clip). Plans
are kept between frames (a static scene: only the noise is new) in this module's own
cache, up to ECHO_CACHE_BYTES.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from numpy.typing import NDArray

from cdma_lidar.firmware_model.adc import adc_limits
from cdma_lidar.scene.codebook import RenderSettings
from cdma_lidar.scene.echoes import ECHO_CACHE_BYTES, Echoes
from cdma_lidar.scene.noise import STREAM_CALIBRATE, STREAM_SCAN, Noise
from cdma_lidar.scene.streams import seed_words
from cdma_lidar.scene.sums import (
    ACCUMULATED_CLIP_MARGIN,
    ACCUMULATED_MIN_NOISE_LSB,
    EXACT_SUM_CLIP_MARGIN,
    EXACT_SUM_MIN_NOISE_LSB,
    FRAC_BITS,
    ROUNDING_LSB,
    Adc,
    _draw_exact_sums,
    _draw_table_sums,
)

__all__ = ["SumPlans"]


class SumPlans:
    """Plans of a scene's columns and calibration shots, and the sums drawn from them.

    ``seed``: the scene's noise seed (column c of frame f draws from the generator of
    ``(seed, stream, f, c)``).
    """

    def __init__(self, adc: Adc, echoes: Echoes, noise: Noise, seed: int) -> None:
        self.adc, self.echoes, self.noise, self.seed = adc, echoes, noise, seed
        self.spec = echoes.spec
        self._plans: dict[tuple, tuple | None] = {}
        self._bytes = 0

    def forget(self) -> None:
        """Drop the plans kept between frames."""
        self._plans.clear()
        self._bytes = 0

    def draw(self, level: str, cfg: RenderSettings, frame: int, columns: Sequence[int],
             power_w: Sequence[NDArray[np.float64] | None] | None, calibration: bool,
             out: NDArray[np.int32]) -> tuple[NDArray[np.int32], NDArray[np.bool_]]:
        """``out`` (B, n, N S) filled with the sums of ``columns`` (calibration shots) the
        level draws, zero elsewhere; (B,) which were drawn. The plans are looked up, and
        made for the batch's missing (column, power) pairs at once."""
        plans: list[tuple | None] = []
        missing: dict[tuple, tuple[int, NDArray[np.float64], list[int]]] = {}
        for j, column in enumerate(columns):
            col = 0 if calibration else column
            p = None if power_w is None else power_w[j]
            power = self.echoes.default_power_w[:, col] if p is None else np.asarray(
                p, dtype=np.float64)
            key = (level, col, calibration, cfg, power.tobytes())
            if key in self._plans:
                plans.append(self._plans[key])
            else:
                plans.append(None)
                missing.setdefault(key, (col, power, []))[2].append(j)
        if missing:
            made = self._make_plans(level, cfg, [(c, p) for c, p, _ in missing.values()],
                                    calibration)
            for (key, (_, _, where)), plan in zip(missing.items(), made, strict=True):
                self._keep(key, plan)
                for j in where:
                    plans[j] = plan
        drawn = np.array([p is not None for p in plans], dtype=bool)
        return self._draw(level, cfg, frame, columns, plans, drawn, calibration, out), drawn

    def _keep(self, key: tuple, plan: tuple | None) -> None:
        """Store a plan, the cache emptied first when it would pass ECHO_CACHE_BYTES."""
        nbytes = 0 if plan is None else plan[0].nbytes
        if self._bytes + nbytes > ECHO_CACHE_BYTES:
            self.forget()
        self._plans[key] = plan
        self._bytes += nbytes

    def _draw(self, level: str, cfg: RenderSettings, frame: int, columns: Sequence[int],
                   plans: list[tuple | None], drawn: NDArray[np.bool_], calibration: bool,
                   out: NDArray[np.int32]) -> NDArray[np.int32]:
        """``out`` (B, n, N S): the sums of the ``drawn`` columns from their plans (zero
        elsewhere)."""
        rows = np.flatnonzero(drawn).tolist()
        flat = out.reshape(len(plans), cfg.frame_samples)
        if len(rows) < len(plans):
            flat[~drawn] = 0
        if not rows:
            return out
        stream = STREAM_CALIBRATE if calibration else STREAM_SCAN
        keys = [(self.seed, stream, frame, columns[j]) for j in rows]
        means = [plans[j][0] for j in rows]
        sigmas = [plans[j][1] for j in rows]
        into = flat if len(rows) == len(plans) else None  # else drawn apart, then placed
        if level == "accumulated":
            got = _draw_table_sums(seed_words(keys), means, sigmas, into)
        else:
            got = _draw_exact_sums(seed_words(keys), means, sigmas, cfg.averages, into)
        if into is None:
            flat[rows] = got
        return out

    def _make_plans(self, level: str, cfg: RenderSettings,
                    items: list[tuple[int, NDArray[np.float64]]],
                    calibration: bool) -> list[tuple | None]:
        """Plans of (column, power) ``items``: (the sum's mean in LSB, read-only, with the
        offset and the rounding's constant; the draw's scale) or None where ``level``
        cannot draw the sum (noise under its floor, echoes near the clip).

        ``exact``: float64, the mean ``R (x + offset + ROUNDING_LSB)`` from the same float64
        echo render_exact uses and the noise rms sigma. ``accumulated``: float32, ``R (x +
        offset) + 1/2`` from :meth:`~cdma_lidar.scene.echoes.Echoes.tabulated_echo` and
        ``sqrt(R (sigma^2 + 1/12) - 1/12)``.
        """
        lsb_per_v = self.adc.fine_scale()[0] / (1 << FRAC_BITS)
        top = adc_limits(self.spec.adc_bits)[1]
        exact = level != "accumulated"
        least = EXACT_SUM_MIN_NOISE_LSB if exact else ACCUMULATED_MIN_NOISE_LSB
        sigmas = (self.noise.rms_items(cfg, items, calibration) * lsb_per_v).tolist()
        keep = [i for i, sigma in enumerate(sigmas) if sigma >= least]
        out: list[tuple | None] = [None] * len(items)
        if not keep:
            return out
        sub = [items[i] for i in keep]
        if exact:
            means, peaks = self._exact_means(cfg, sub, calibration)
        else:  # largest echo that keeps the clip margin: the peak is found only beyond it
            means, peaks = self._accumulated_means(cfg, sub, calibration, [
                top - 0.5 - ACCUMULATED_CLIP_MARGIN * sigmas[i] for i in keep])
        r = cfg.averages
        scales = sigmas if exact else (  # the scale of the R-repetition sum's Gaussian
            np.sqrt(r * (np.square(sigmas) + 1.0 / 12) - 1.0 / 12).astype(np.float32))
        for i, mean, peak in zip(keep, means, peaks, strict=True):
            sigma = sigmas[i]
            if exact and peak + EXACT_SUM_CLIP_MARGIN * sigma > top:
                continue
            if not exact and peak + ACCUMULATED_CLIP_MARGIN * sigma > top - 0.5:
                continue
            mean.flags.writeable = False
            out[i] = (mean, scales[i])
        return out

    def _exact_means(self, cfg: RenderSettings, items: list[tuple[int, NDArray[np.float64]]],
                     calibration: bool) -> tuple[list[NDArray[np.float64]], list[float]]:
        """(R (x + offset + ROUNDING_LSB) per item, float64 LSB; each repetition's largest
        |value|, LSB): :meth:`~cdma_lidar.scene.echoes.Echoes.batch` with the scaling to LSB
        and the constant made in the spectrum."""
        scale, offset = self.adc.fine_scale()
        lsb_per_v = scale / (1 << FRAC_BITS)
        r = cfg.averages
        shift = offset / (1 << FRAC_BITS) + ROUNDING_LSB
        block, top = self.echoes.batch(cfg, items, calibration, r * lsb_per_v, r * shift)
        peaks = (top / r).tolist()
        means = list(block)
        for j, (col, _) in enumerate(items):
            users = None if calibration else self.echoes.other_users_signal(col, cfg,
                                                                     block.shape[1] * r)
            if users is not None:
                each = users.reshape(r, block.shape[1]) * lsb_per_v
                each += block[j] / r
                peaks[j] = float(np.abs(each).max())
                means[j] = each.sum(axis=0)
        return means, peaks

    def _accumulated_means(self, cfg: RenderSettings,
                           items: list[tuple[int, NDArray[np.float64]]], calibration: bool,
                           limits: Sequence[float]
                           ) -> tuple[list[NDArray[np.float32]], list[float]]:
        """(R (x + offset) + 1/2 per item, float32 LSB; each repetition's largest |value|,
        LSB, or a bound on it where that bound is at most the item's ``limits`` entry: the
        pass over the row that finds the value is made only where the bound is not).
        Single precision: the sum's values stay below 2**15 R, resolved to about 1e-3 LSB,
        against a noise rms of sqrt(R) sigma >= 1 LSB. The scaling to LSB goes into the
        echoes' amplitudes and the constant into the rows they are added to, so no pass
        over the block is spent on either."""
        scale, offset = self.adc.fine_scale()
        lsb_per_v = scale / (1 << FRAC_BITS)
        offset_lsb = offset / (1 << FRAC_BITS)
        r, length = cfg.averages, cfg.frame_samples
        gain = r * lsb_per_v
        shift = np.float32(r * offset_lsb + 0.5)
        users = [None if calibration or not self.spec.other_users
                 else self.echoes.other_users_signal(col, cfg, length * r) for col, _ in items]
        reach = np.array([0.0 if u is None else float(np.abs(u).max()) * lsb_per_v
                          for u in users])
        tabulated = self.echoes.echo_tabulated(cfg)
        terms = self.echoes.batch_terms(cfg, items, calibration) if tabulated else None
        # Items with no echo and no other user share one constant row (a third of a frame)
        busy = [j for j, u in enumerate(users)
                if terms is None or terms[j] is not None or u is not None]
        block = np.empty((len(busy), length), dtype=np.float32)
        means = [np.full(length, shift, dtype=np.float32)] * len(items)
        for j, row in zip(busy, block, strict=True):
            means[j] = row
        bounds = np.zeros(len(items))
        if tabulated:  # the whole batch at once
            bounds[busy] = self.echoes.tabulated_echoes(cfg, [items[j] for j in busy], calibration,
                                                  block, gain, shift,
                                                  [terms[j] for j in busy])
        else:  # a table of every member would not fit: the Fourier synthesis
            block[:] = shift
            bounds[:] = np.inf
            for row, (col, power) in zip(block, items, strict=True):
                echo = self.echoes.echo(col, cfg, power, calibration=calibration, single=True)
                row += echo * np.float32(gain)
        # The rows' float32 sums may exceed the bound by their rounding (a few 2**-24 of
        # the values' size): 2**-12 of it is ample.
        bounds = (bounds * (1 + 2.0**-12) + abs(shift) * 2.0**-12) / r + abs(offset_lsb) + reach
        for j in np.flatnonzero(bounds > np.asarray(limits)).tolist():
            top = max(means[j].max() - shift, shift - means[j].min())  # R |echo|
            bounds[j] = top / r + abs(offset_lsb) + reach[j]
        for j, u in enumerate(users):
            if u is not None:
                means[j] += (u.reshape(r, length).sum(axis=0) * lsb_per_v).astype(np.float32)
        return means, bounds.tolist()
