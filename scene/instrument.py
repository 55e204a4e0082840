r"""The simulated instrument: the repetition sums and ADC samples of a scene's columns.

Signal model (Supplementary Notes 4, 5, 9, 11), one module per part::

    lasers k (Gold member code_index[k], polarity-modulated by our UID over n periods)
      -> grating (true geometry) -> scene -> back along the same path -> one photodiode
    v(t) = sum_k A_k c_k(t - tau_k)                 echoes of the lit channels
         + sum_g A_g c_k(t - tau_g)                 grating ghosts       (scene.echoes)
         + sum_u A_u c_u(t - tau_u)                 other LiDARs
         + e(t)                                     receiver noise       (scene.noise)
    codes = clip(round_half_up(adc_gain * v / lsb + adc_offset), adc_bits)  (scene.sums)

The codes' filtered waveforms and their spectra: :mod:`cdma_lidar.scene.codebook`; the
repetition sums' plans (each column's mean and noise scale, kept between frames):
:mod:`cdma_lidar.scene.plans`; rendering and receiving a batch of columns, as the
virtual device and every study do: :func:`cdma_lidar.scene.acquire.acquire`.

R repetitions share the deterministic echo, which is kept between frames (a static
scene). At ``exact`` fidelity each repetition gets independent noise and is quantised on
its own (:meth:`Instrument.render_exact`, CAPTURE RAW); what the receive chain reads,
the repetitions' sum, is drawn from its exact distribution with L Gaussians and (R - 1)
L random bytes (:meth:`Instrument.render_sum`, :func:`cdma_lidar.scene.sums.draw_repetition_sum`;
a batch of columns: :meth:`Instrument.render_sums`). At ``accumulated`` the sum is drawn
as one Gaussian from a table of quantiles, around an echo interpolated from each code's
tabulated waveform (:meth:`Instrument.render_accumulated`,
:meth:`Instrument.tabulated_echo`; docs/scene.md for its validity and error).

Determinism: the noise of (frame, column) comes from ``numpy.random.default_rng`` seeded
with ``(seed, stream, frame, column)``, so columns can be rendered in any order (resume,
resend) and the same scene, seed and settings give the same codes.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence

import numpy as np
from numpy.typing import NDArray

from cdma_lidar.checks import check_int, is_int
from cdma_lidar.errors import out_of_range
from cdma_lidar.scene.codebook import Codebook, RenderSettings
from cdma_lidar.scene.echo_kernel import (
    single_synthesis_kernel,
    synthesis_kernel,
    terms_kernel,
)
from cdma_lidar.scene.echoes import ECHO_CACHE_BYTES, Echoes
from cdma_lidar.scene.linkbudget import LinkBudget
from cdma_lidar.scene.model import FIDELITY_LEVELS, Scene
from cdma_lidar.scene.noise import (
    STREAM_CALIBRATE,
    STREAM_SCAN,
    Noise,
    fixed_noise_v,
    speckle_factors,
)
from cdma_lidar.scene.noise_kernel import repetition_kernel, row_kernel
from cdma_lidar.scene.plans import SumPlans
from cdma_lidar.scene.sums import SUM_TYPE, Adc, split_sum
from cdma_lidar.scene.truth import Truth, compute_truth
from cdma_lidar.units import range_to_delay_s

__all__ = ["SUM_TYPE", "Instrument", "RenderSettings"]

log = logging.getLogger(__name__)


class Instrument:
    """Renders the ADC samples the virtual board would record for one column.

    ``Instrument(scene, seed)``; :meth:`render` for a scan column or, with
    ``calibration``, one shot of the zeroth-order target; :meth:`render_sums` for the
    repetition sums of a batch. Powers are a (K, C) matrix in watts (default: the scene's
    per-channel laser power at every column). Its parts: ``codebook`` (spectra, tables),
    ``echoes``, ``noise``, ``adc`` and ``plans`` (the drawn sums), each with its own cache.
    """

    def __init__(self, scene: Scene, seed: int = 0) -> None:
        if not is_int(seed) or seed < 0:
            raise out_of_range("seed", "a non-negative integer", seed)
        self.scene = scene
        self.spec = spec = scene.instrument
        self.seed = int(seed)
        self.truth: Truth = compute_truth(scene)
        h = self.truth.hits
        k, c = h.range_m.shape
        self.channels, self.columns = k, c
        self.default_power_w = np.repeat(spec.laser_power_w[:, None], c, axis=1)
        #: per-pixel speckle fading of the received power (None: no speckle)
        self.speckle = (speckle_factors(spec.speckle_cells, (k, c), self.seed)
                        if spec.speckle_cells > 0 else None)
        #: the physical link budget of every pixel (cdma_lidar.scene.linkbudget)
        self.budget = LinkBudget.of(spec, h.reflectivity, h.cos_incidence, h.range_m,
                                    self.speckle)
        self.codebook = Codebook(spec)
        self.echoes = Echoes(scene, self.truth, self.budget.amplitude_per_w,
                             self.default_power_w, self.codebook)
        #: per-pixel amplitude (V) per watt of laser power; 0 where nothing is hit
        self.gain_v_per_w = self.echoes.gain_v_per_w
        #: per-pixel round-trip delay (s) including the hidden system delay
        self.delay_s = self.echoes.delay_s
        #: one of cdma_lidar.scene.model.FIDELITY_LEVELS
        self.fidelity = scene.fidelity
        # the level's compiled kernels, loaded (numba's import and its cached code, once
        # per process) here, not in a frame
        tabulated = Echoes.echo_tabulated(RenderSettings.from_spec(spec))
        for kernel in ((row_kernel, terms_kernel if tabulated else single_synthesis_kernel)
                       if self.fidelity == "accumulated"
                       else (synthesis_kernel, repetition_kernel)):
            kernel()
        cal_gain = self.echoes.calibration_gain_v_per_w()
        fixed = fixed_noise_v(spec, self.gain_v_per_w * self.default_power_w, h.lit,
                              cal_gain * spec.laser_power_w,
                              self.unit_signal_power(RenderSettings.from_spec(spec)))
        self.noise = Noise(self.budget, self.default_power_w,
                           cal_gain / self.budget.volts_per_rx_w, fixed)
        self.adc = Adc(spec)
        self.plans = SumPlans(self.adc, self.echoes, self.noise, self.seed)
        self._models: dict[tuple, tuple[NDArray[np.floating], float]] = {}
        self._models_bytes = 0
        #: per-sample noise rms (V) at the scene's own settings and power, median over columns
        self.noise_rms_v = float(np.median(self.noise_rms_columns_v()))

    # -- the parts' answers ------------------------------------------------------------

    def calibration_gain_v_per_w(self) -> float:
        """Amplitude (V) per watt of one channel's echo from the zeroth-order target."""
        return self.echoes.calibration_gain_v_per_w()

    def lit_channels(self, column: int) -> NDArray[np.int64]:
        """Channels whose ray hits an object at ``column``."""
        return self.echoes.lit_channels(column)

    def noise_rms_columns_v(self, cfg: RenderSettings | None = None,
                            power_w: NDArray[np.float64] | None = None) -> NDArray[np.float64]:
        """(C,) per-sample noise rms (V) of every column at laser power ``power_w`` (K, C)."""
        return self.noise.rms_columns_v(cfg or RenderSettings.from_spec(self.spec), power_w)

    def noise_rms_v_at(self, column: int, cfg: RenderSettings,
                       power_w: NDArray[np.float64] | None = None,
                       calibration: bool = False) -> float:
        """Per-sample noise rms (V) of one column (or calibration shot) at power ``power_w``
        (K,): :meth:`cdma_lidar.scene.noise.Noise.rms_v_at`."""
        return self.noise.rms_v_at(column, cfg, power_w, calibration)

    def echo(self, column: int, cfg: RenderSettings, power_w: NDArray[np.float64] | None = None,
             calibration: bool = False, single: bool = False) -> NDArray[np.floating]:
        """Noise-free photodiode voltage (V) of one frame at ``column``:
        :meth:`cdma_lidar.scene.echoes.Echoes.echo`."""
        return self.echoes.echo(column, cfg, power_w, calibration, single)

    def tabulated_echo(self, column: int, cfg: RenderSettings,
                       power_w: NDArray[np.float64] | None = None, calibration: bool = False,
                       out: NDArray[np.float32] | None = None) -> NDArray[np.float32]:
        """``accumulated`` fidelity's echo (float32):
        :meth:`cdma_lidar.scene.echoes.Echoes.tabulated_echo`."""
        return self.echoes.tabulated_echo(column, cfg, power_w, calibration, out)

    @staticmethod
    def echo_tabulated(cfg: RenderSettings) -> bool:
        """Whether ``accumulated`` renders echoes from waveform tables under ``cfg``."""
        return Echoes.echo_tabulated(cfg)

    def other_users_signal(self, column: int, cfg: RenderSettings,
                           total_samples: int) -> NDArray[np.float64] | None:
        """Other LiDARs' light at our photodiode (V) over ``total_samples`` (None if none)."""
        return self.echoes.other_users_signal(column, cfg, total_samples)

    def unit_signal_power(self, cfg: RenderSettings) -> float:
        """Mean square (V^2) of one channel's filtered waveform at amplitude 1 V."""
        return self.codebook.unit_signal_power(cfg)

    def to_codes(self, volts: NDArray[np.float64]) -> NDArray[np.int16]:
        """ADC codes of volts: :meth:`cdma_lidar.scene.sums.Adc.to_codes`."""
        return self.adc.to_codes(volts)

    # -- the scene's needs ---------------------------------------------------------------

    def link_figures(self, cfg: RenderSettings | None = None,
                     power_w: NDArray[np.float64] | None = None) -> dict[str, NDArray]:
        """Per-pixel (K, C) link budget and the paper's SNRs; NaN where nothing is hit.

        ``rx_power_w`` received optical power (W); ``amplitude_v`` echo amplitude (V);
        ``signal_power_v2`` P_s = A^2 * (mean square of the unit filtered code), V^2 at the
        ADC; ``noise_power_v2`` sigma_eta^2, the column's noise variance per sample with the
        ADC's lsb^2/12 (V^2); ``snr_db`` eq. 30, P_s / (sigma^2 + sum of the column's other
        echoes' P_i); ``snr_ss_db`` eq. 43, N P_s / (sigma^2 + 2/3 sum P_i) for one code
        period; ``snr_ss_avg_db`` the same with the noise averaged over the R * n periods
        a column accumulates; ``footprint_m`` the beam diameter at the target (m).
        Ghosts and other users are not counted as interference.
        """
        cfg = cfg or RenderSettings.from_spec(self.spec)
        p = self.default_power_w if power_w is None else np.asarray(power_w, dtype=np.float64)
        lit = self.truth.hits.lit
        amp = self.gain_v_per_w * p
        ps = amp**2 * self.unit_signal_power(cfg)
        noise = self.noise_rms_columns_v(cfg, p) ** 2
        lsb = self.spec.adc_full_scale_v / (1 << (self.spec.adc_bits - 1)) / self.spec.adc_gain
        sigma2 = (noise + lsb**2 / 12)[None, :]
        others = ps.sum(axis=0, keepdims=True) - ps
        n = (1 << cfg.poly_u[0]) - 1
        periods = cfg.averages * cfg.uid_bits
        with np.errstate(divide="ignore"):
            snr = 10 * np.log10(ps / (sigma2 + others))
            snr_ss = 10 * np.log10(n * ps / (sigma2 + 2 / 3 * others))
            snr_ss_avg = 10 * np.log10(n * ps / (sigma2 / periods + 2 / 3 * others))
        rng = self.truth.range_m

        def masked(a: NDArray) -> NDArray[np.float64]:
            return np.where(lit, a, np.nan)

        return {
            "rx_power_w": masked(self.budget.rx_per_w * p),
            "amplitude_v": masked(amp),
            "signal_power_v2": masked(ps),
            "noise_power_v2": np.broadcast_to(sigma2, lit.shape).copy(),
            "snr_db": masked(snr), "snr_ss_db": masked(snr_ss),
            "snr_ss_avg_db": masked(snr_ss_avg),
            "footprint_m": masked(self.spec.beam_waist_m + np.nan_to_num(rng)
                                  * self.spec.beam_divergence_rad),
        }

    def range_bounds_m(self) -> tuple[float, float]:
        """(min, max) range (m) of the lit pixels and the calibration target, or the overrides."""
        rng = self.truth.hits.range_m
        cand = [self.scene.calibration.target_distance_m]
        if np.any(np.isfinite(rng)):
            cand += [float(np.nanmin(rng)), float(np.nanmax(rng))]
        lo, hi = min(cand), max(cand)
        if self.spec.min_range_m is not None:
            lo = self.spec.min_range_m
        if self.spec.max_range_m is not None:
            hi = self.spec.max_range_m
        return lo, hi

    def default_gate(self, samples_per_chip: int | None = None, margin: int = 16,
                     minimum: int = 128) -> tuple[int, int]:
        """(gate_start, gate_len) in samples covering the scene's echoes plus margins.

        Covers the range bounds (lit pixels, calibration target; system delay included),
        the other users' delays and the ghosts' delays, ``margin`` samples either side,
        at least ``minimum`` lags, rounded up to a multiple of 16. A long enough gate matters
        for the noise floor: with 64 lags (47 after excluding +-8 around the peak, about 12
        independent values at S = 4) a pixel that sees nothing can reach SNR_XC near 18 dB,
        with 128 lags it stays near 16 dB while lit pixels of paper-scene1 sit above 18.8 dB
        (5th percentile).
        """
        s = samples_per_chip or self.spec.samples_per_chip
        fs = self.spec.chip_rate_hz * s
        lo, hi = self.range_bounds_m()
        sys_d = self.spec.system_delay_s
        delays = [range_to_delay_s(lo) + sys_d, range_to_delay_s(hi) + sys_d]
        delays += [u.delay_s for u in self.spec.other_users]
        delays += [range_to_delay_s(g.distance_m) + sys_d for g in self.spec.ghosts]
        period = self.spec.code_length * s
        start = max(int(np.floor(min(delays) * fs)) - margin, 0)
        length = int(np.ceil(max(delays) * fs)) + margin - start + 1
        length = max(minimum, -(-length // 16) * 16)
        if length >= period:
            return 0, period
        return start % period, length

    # -- rendering ---------------------------------------------------------------------

    def forget(self) -> None:
        """Drop what is kept between frames: the column models, the sums' plans and the
        other users' light (to measure a cold first frame, or free memory); the codebook's
        spectra and tables stay."""
        self._models.clear()
        self._models_bytes = 0
        self.plans.forget()
        self.echoes.forget()

    def column_model(self, column: int, cfg: RenderSettings,
                     power_w: NDArray[np.float64] | None = None, calibration: bool = False,
                     single: bool = False) -> tuple[NDArray[np.floating], float]:
        """(noise-free echo of one repetition (V, L samples, read-only), noise rms (V)).

        Kept between frames (up to ECHO_CACHE_BYTES): the scene is static, so a column's
        echo and noise level depend only on the column, the settings and the power.
        """
        power = self.default_power_w[:, column] if power_w is None else np.asarray(
            power_w, dtype=np.float64)
        key = (column, calibration, cfg, power.tobytes(), single)
        hit = self._models.get(key)
        if hit is not None:
            return hit
        echo = self.echo(column, cfg, power, calibration=calibration, single=single)
        echo.flags.writeable = False
        hit = (echo, self.noise_rms_v_at(column, cfg, power, calibration))
        if self._models_bytes + echo.nbytes > ECHO_CACHE_BYTES:
            self._models.clear()
            self._models_bytes = 0
        self._models[key] = hit
        self._models_bytes += echo.nbytes
        return hit

    def _noise_rng(self, frame: int, col: int, calibration: bool,
                   shot: int) -> np.random.Generator:
        """The noise generator of one rendered column (or calibration shot); many at
        once: :func:`cdma_lidar.scene.streams.generators` of the same keys."""
        stream = STREAM_CALIBRATE if calibration else STREAM_SCAN
        return np.random.default_rng([self.seed, stream, frame, shot if calibration else col])

    def _column_inputs(self, column: int, cfg: RenderSettings, frame: int,
                       power_w: NDArray[np.float64] | None, calibration: bool, shot: int
                       ) -> tuple[NDArray[np.float64], float, np.random.Generator, int]:
        """(one repetition's echo on the fine grid incl. offset, noise rms in fine units,
        the column's noise generator, the column index rendered)."""
        if not calibration:
            check_int("column", column, 0, self.columns - 1)
        col = 0 if calibration else column
        scale, offset = self.adc.fine_scale()
        echo, sigma = self.column_model(col, cfg, power_w, calibration)
        one = echo * scale
        one += offset
        return one, sigma * scale, self._noise_rng(frame, col, calibration, shot), col

    def render(self, column: int, cfg: RenderSettings | None = None, frame: int = 0,
               power_w: NDArray[np.float64] | None = None, *, calibration: bool = False,
               shot: int = 0) -> NDArray[np.int16]:
        """ADC codes of one column: ``averages * uid_bits * N * S`` samples (repetition r,
        period p, sample i).

        ``frame`` is the scan's frame counter (noise seed); ``power_w`` the per-channel laser
        power (W) at this column; ``calibration`` renders shot ``shot`` of the zeroth-order
        target instead of the scene. At ``accumulated`` fidelity the column's R repetitions
        are :meth:`render_accumulated`'s sums split evenly into R frames of valid codes
        (their sum, which is all the receive chain uses, is the drawn one; the single
        frames are not what an ADC would give).
        """
        cfg = cfg or RenderSettings.from_spec(self.spec)
        acc = self.render_accumulated(column, cfg, frame, power_w, calibration=calibration,
                                      shot=shot) if self.fidelity == "accumulated" else None
        if acc is not None:
            return split_sum(acc.reshape(-1), cfg.averages).reshape(-1)
        return self.render_exact(column, cfg, frame, power_w, calibration=calibration, shot=shot)

    def render_exact(self, column: int, cfg: RenderSettings, frame: int = 0,
                     power_w: NDArray[np.float64] | None = None, *, calibration: bool = False,
                     shot: int = 0) -> NDArray[np.int16]:
        """:meth:`render` at ``exact`` fidelity: every repetition drawn and quantised alone."""
        one, sigma, rng, col = self._column_inputs(column, cfg, frame, power_w, calibration,
                                                   shot)
        length = one.size
        total = length * cfg.averages
        if sigma > 0:
            # float32 Gaussians (half the cost of float64), widened while scaling
            fine = np.multiply(rng.standard_normal(total, dtype=np.float32), sigma,
                               dtype=np.float64)
            fine.reshape(cfg.averages, length)[...] += one
        else:
            fine = np.tile(one, cfg.averages)
        if not calibration:
            users = self.other_users_signal(col, cfg, total)
            if users is not None:
                fine += users * self.adc.fine_scale()[0]
        return self.adc.quantise_fine(fine)

    def render_accumulated(self, column: int, cfg: RenderSettings | None = None,
                           frame: int = 0, power_w: NDArray[np.float64] | None = None, *,
                           calibration: bool = False, shot: int = 0
                           ) -> NDArray[np.int32] | None:
        """The sum of the R quantised repetitions, drawn directly: (n, N S) int32, or None.

        ``sum_r Q(x + e_r)`` for noise e_r of rms sigma is, when sigma >= 1 LSB, the value
        ``R x + e`` with ``e`` Gaussian of variance ``R (sigma^2 + 1/12)`` up to the
        quantiser's periodic bias (below 1e-9 LSB); it is drawn as
        ``floor(R x + sqrt(R (sigma^2 + 1/12) - 1/12) z + 1/2)`` (the last rounding adds
        the missing 1/12), z from a table of 65536 normal quantiles picked by a 16-bit word
        (:func:`cdma_lidar.scene.sums._normal_table`) and x the echo of
        :meth:`tabulated_echo` (no Fourier transform per column). Returns None (the caller
        renders ``exact``) when sigma < ACCUMULATED_MIN_NOISE_LSB or the column's echo
        comes within ACCUMULATED_CLIP_MARGIN sigma of the ADC's clip.
        """
        return self._render_one("accumulated", column, cfg, frame, power_w, calibration, shot)

    def render_sum(self, column: int, cfg: RenderSettings | None = None, frame: int = 0,
                   power_w: NDArray[np.float64] | None = None, *, calibration: bool = False,
                   shot: int = 0) -> NDArray[np.int32] | None:
        """The sum of the column's R quantised repetitions at the scene's fidelity, (n, N S)
        int32 (:data:`SUM_TYPE`), drawn directly; None where the level must render the
        repetitions (then :meth:`render_exact` and a sum give it).

        What the receive chain reads of a scan column is this sum (it accumulates the R
        repetitions before anything else). ``exact``: :func:`draw_repetition_sum`, the
        sum's own distribution (not an approximation), where the noise rms is at least
        EXACT_SUM_MIN_NOISE_LSB and nothing comes within EXACT_SUM_CLIP_MARGIN noise rms
        of the ADC's clip; L Gaussian draws and (R - 1) L random bytes instead of R L
        Gaussians and R L quantisations. ``accumulated``: :meth:`render_accumulated`.
        ``calibration``: shot ``shot`` of the calibration target. Many columns at once:
        :meth:`render_sums`.
        """
        return self._render_one(self.fidelity, column, cfg, frame, power_w, calibration, shot)

    def _render_one(self, level: str, column: int, cfg: RenderSettings | None, frame: int,
                    power_w: NDArray[np.float64] | None, calibration: bool,
                    shot: int) -> NDArray[np.int32] | None:
        sums, drawn = self.render_sums([shot if calibration else column], cfg, frame,
                                       None if power_w is None else [power_w],
                                       calibration=calibration, level=level)
        return sums[0] if drawn[0] else None

    def render_sums(self, columns: Sequence[int], cfg: RenderSettings | None = None,
                    frame: int = 0, power_w: Sequence[NDArray[np.float64]] | None = None, *,
                    calibration: bool = False, level: str | None = None,
                    complete: bool = False, out: NDArray[np.int32] | None = None
                    ) -> tuple[NDArray[np.int32], NDArray[np.bool_]]:
        """:meth:`render_sum` of a batch of columns (``calibration``: of calibration shots
        ``columns``): ((B, n, N S) int32 sums, (B,) bool: drawn).

        A row not drawn is zero: the level cannot draw that column's sum; with
        ``complete`` it is :meth:`render_exact`'s R repetitions summed instead (what the
        receive chain would accumulate), so every row is the column's sum. Each column
        keeps its own noise generator, so a column's sum is the same whatever batch it is
        drawn in (render_sum is a batch of one); the plans (echoes, scaling) are made,
        and the noise's arithmetic done, on blocks of the batch's columns that stay in a
        core's cache (the same values: tests/scene/test_noise_blocks.py). ``power_w``: the
        laser power (K,) W of each column (None: the scene's). ``level``: one of
        FIDELITY_LEVELS (default the scene's). ``out``: a C-contiguous (B, n, N S) int32
        array to write the sums into (returned; as numpy's ``out``): a scan passes the
        same one every frame, so its 5 to 10 MB are not handed back to the system and
        faulted in again each frame (what the allocator does with a freed array of that
        size depends on the process's history).
        """
        cfg = cfg or RenderSettings.from_spec(self.spec)
        level = level or self.fidelity
        if level not in FIDELITY_LEVELS:
            raise out_of_range("level", "one of " + ", ".join(FIDELITY_LEVELS), level)
        shape = (len(columns), cfg.uid_bits, cfg.frame_samples // cfg.uid_bits)
        if out is not None and (out.shape != shape or out.dtype != SUM_TYPE
                                or not out.flags.c_contiguous):
            raise out_of_range("out", f"a C-contiguous {shape} {np.dtype(SUM_TYPE)} array",
                               f"{out.shape} {out.dtype}")
        if not calibration and not (len(columns) and all(type(c) is int for c in columns)
                                    and 0 <= min(columns) and max(columns) < self.columns):
            for column in columns:  # (the common case above: one check for the batch)
                check_int("column", column, 0, self.columns - 1)
        sums, drawn = self.plans.draw(level, cfg, frame, columns, power_w, calibration,
                                      np.empty(shape, dtype=SUM_TYPE) if out is None else out)
        for j in np.flatnonzero(~drawn).tolist() if complete else ():
            p = None if power_w is None else power_w[j]
            raw = self.render_exact(0 if calibration else columns[j], cfg, frame, p,
                                    calibration=calibration, shot=columns[j])
            np.add.reduce(raw.reshape(cfg.averages, -1), axis=0, dtype=SUM_TYPE,
                          out=sums[j].reshape(-1))
        return sums, drawn

