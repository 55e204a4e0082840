r"""The simulated instrument: photodiode waveform and ADC samples of one column.

Signal model (Supplementary Notes 4, 5, 9, 11)::

    lasers k (Gold member code_index[k], polarity-modulated by our UID over n periods)
      -> grating (true geometry) -> scene -> back along the same path -> one photodiode
    v(t) = sum_k A_k c_k(t - tau_k)                 echoes of the lit channels
         + sum_g A_g c_k(t - tau_g)                 grating ghosts (fixed distance, own code)
         + sum_u A_u c_u(t - tau_u)                 other LiDARs (same family, their own UID)
         + e(t)                                     receiver noise, white Gaussian
    A_k   = G_tia R_resp M P_rx[k, col]   (cdma_lidar.scene.linkbudget)      (V)
    e     : thermal, dark, shot, ambient, ASE of the link budget, per column
    tau_k = 2 r / c + system_delay                                             (s)
    codes = clip(round_half_up(adc_gain * v / lsb + adc_offset), adc_bits)     (ADC)

``c(t)`` is the bipolar NRZ chip waveform (+1 for bit 0) of period ``n * N`` chips, AC
coupled (no DC) and filtered by the detector transfer function

    H(f) = exp(-ln(2)/2 * (f / B)^2) * T(f),   T = 1 below 0.8 f_Nyq, cos^2 taper to 0 at f_Nyq

(Gaussian with its -3 dB point at ``detector_bandwidth_hz`` = B, times an anti-alias
taper that is zero from the Nyquist frequency ``f_Nyq = chip_rate * S / 2`` up). The
filtered waveform is therefore band-limited below Nyquist, so rendering it from its
Fourier series is exact for ANY delay, fractional samples included::

    Z_q = H(f_q) * sinc(q / (nN)) * DFT(chips)[q mod nN] / (nN) * exp(-2j pi f_q tau')
    f_q = q * chip_rate / (nN),  q = 0 .. L/2,  L = n N S samples per frame
    y   = irfft(L * sum_k A_k Z_q,k)        one inverse FFT per column, all channels summed

Sampling instants: ADC sample i of a frame is taken at ``(i + 1/2) / (S * chip_rate)``
after the start of the emitted frame, so sample i of chip m lies inside chip m and an
echo with ``tau = d / (S * chip_rate)`` peaks exactly at lag d in the receive chain
(``tau' = tau + Tc/2 - Ts/2`` folds the pulse centre and the sample phase in).

Cost: only what the column needs. Channels whose ray hits nothing are skipped entirely.
The L/2 + 1 bins repeat the chips' nN-point DFT under one weight (H, sinc, scale), so the
per-channel work is one period of nN bins times its phase ramp (an outer product of two
short exponentials), then one scaled add per further period; the weight multiplies the
column's sum once (:meth:`Instrument._sum_delayed`). R repetitions share the deterministic
echo, which is kept between frames (a static scene). At ``exact`` fidelity each
repetition gets independent noise and is quantised on its own
(:meth:`Instrument.render_exact`, CAPTURE RAW); what
the receive chain reads, the repetitions' sum, is drawn from its exact distribution with
L Gaussians and (R - 1) L random bytes (:meth:`Instrument.render_sum`,
:func:`draw_repetition_sum`; a batch of columns: :meth:`Instrument.render_sums`). At
``accumulated`` the sum is drawn as one Gaussian from a table of quantiles, around an
echo interpolated from each code's tabulated waveform (:meth:`Instrument.render_accumulated`,
:meth:`Instrument.tabulated_echo`; docs/scene.md for its validity and error).

Determinism: the noise of (frame, column) comes from ``numpy.random.default_rng`` seeded
with ``(seed, stream, frame, column)``, so columns can be rendered in any order (resume,
resend) and the same scene, seed and settings give the same codes.
"""

from __future__ import annotations

import functools
import logging
import math
from collections.abc import Sequence
from dataclasses import dataclass, fields

import numpy as np
from numpy.typing import NDArray

from cdma_lidar.checks import check_int, is_int
from cdma_lidar.errors import out_of_range
from cdma_lidar.firmware_model.adc import adc_limits, quantise
from cdma_lidar.firmware_model.gold import gold_codes
from cdma_lidar.scene.echo_kernel import synthesis_kernel, terms_kernel
from cdma_lidar.scene.linkbudget import LinkBudget, link_gain_v_m2_per_w
from cdma_lidar.scene.model import FIDELITY_LEVELS, InstrumentSpec, Scene
from cdma_lidar.scene.noise_kernel import repetition_kernel, row_kernel
from cdma_lidar.scene.streams import from_seed_words, seed_words
from cdma_lidar.scene.truth import Truth, compute_truth
from cdma_lidar.units import SPEED_OF_LIGHT_M_S

__all__ = [
    "ACCUMULATED_CLIP_MARGIN",
    "ACCUMULATED_MIN_NOISE_LSB",
    "ECHO_CACHE_BYTES",
    "EXACT_SUM_CLIP_MARGIN",
    "EXACT_SUM_MIN_NOISE_LSB",
    "FRAC_BITS",
    "ROUNDING_LSB",
    "SUM_TYPE",
    "TABLE_PHASES",
    "Instrument",
    "RenderSettings",
    "detector_response",
    "draw_repetition_sum",
    "draw_repetition_sums",
    "speckle_factors",
    "split_sum",
]

log = logging.getLogger(__name__)

#: Fine grid of the analog value handed to the ADC model: 2**-FRAC_BITS LSB.
FRAC_BITS = 8

#: ``accumulated`` fidelity draws the R-repetition sum directly only where the noise
#: rms is at least this many LSB (the quantiser's bias then stays below
#: exp(-2 pi^2 sigma^2) / pi < 1e-9 LSB per sample, see docs/scene.md) ...
ACCUMULATED_MIN_NOISE_LSB = 1.0
#: ... and the column's largest echo stays this many noise rms inside the ADC's range.
ACCUMULATED_CLIP_MARGIN = 6.0

#: ``exact`` fidelity draws the sum of a column's R quantised repetitions in one go (its
#: distribution, to double precision: :func:`draw_repetition_sum`) where the noise rms is at
#: least this many LSB (the lattice's aliasing terms are then below exp(-pi^2 sigma^2 / 2)
#: = 4e-20) ...
EXACT_SUM_MIN_NOISE_LSB = 3.0
#: ... and every repetition's largest value stays this many noise rms inside the ADC's
#: range (a clipped sample then has probability below 2e-19).
EXACT_SUM_CLIP_MARGIN = 9.0

#: The ADC rounds the fine grid first (rint) and then half up: for a continuous input y
#: (LSB) its code is floor(y + ROUNDING_LSB) (docs/scene.md, "Fidelity levels").
ROUNDING_LSB = 0.5 + 0.5 / (1 << FRAC_BITS)

_STREAM_SCAN = 0
_STREAM_CALIBRATE = 1
_STREAM_SPECKLE = 2

#: Integer type of the drawn repetition sums: they lie in R times the ADC's range (the plans
#: keep the noise's reach inside it), |sum| <= 1024 * 2**15 = 2**25 at the largest R and ADC
#: width the virtual board accepts, far inside int32; half the bytes of int64 to write
#: (fresh pages in every cold frame) and for the receive chain to read.
SUM_TYPE = np.int32

#: ``accumulated`` fidelity tabulates each code's waveform at this many delays per sample
#: (:meth:`Instrument.tabulated_echo`).
TABLE_PHASES = 8

#: Bytes of noise-free column echoes kept between frames (a static scene's echo is the same
#: in every frame; only the noise is new).
ECHO_CACHE_BYTES = 128 << 20


def split_sum(acc: NDArray[np.integer], repetitions: int) -> NDArray[np.int16]:
    """(R, L) int16 frames summing to ``acc`` (L,) exactly, as even as integers allow.

    Frame r holds ``acc // R + (r < acc % R)``: every frame lies between
    ``floor(acc / R)`` and ``ceil(acc / R)``, so sums of R codes in [lo, hi] split into
    codes in [lo, hi].
    """
    q, rem = np.divmod(np.asarray(acc, dtype=np.int64), repetitions)
    out = np.empty((repetitions, q.size), dtype=np.int16)
    for i in range(repetitions):
        np.add(q, rem > i, out=out[i], casting="unsafe")
    return out


def draw_repetition_sum(rng: np.random.Generator, mean_lsb: NDArray[np.float64],
                        sigma_lsb: float, repetitions: int) -> NDArray[np.int32]:
    """The sum of R quantised noisy repetitions, drawn with L Gaussians instead of R L.

    Wanted: ``A = sum_r floor(y_r + e_r)`` per sample, e_r independent Gaussian of rms
    ``sigma_lsb`` (LSB), ``mean_lsb = sum_r y_r`` (L,). Drawn as

        A = floor(mean_lsb + sqrt(R sigma^2 + (R - 1) h^2 / 12) z - sum_{i<R-1} U_i)

    z standard normal (float64), U_i = (b_i + 1/2) h uniform on a grid of h = 2**-8 (b_i
    a random byte of the generator). Why this is A's distribution: floor(y + e) takes the
    value k with probability g(k), g the density of y + e - U (U uniform on [0, 1)); by
    Poisson summation the lattice variable's characteristic function is g's Fourier
    transform plus aliases of size exp(-sigma^2 pi^2 / 2) on [-pi, pi]; so the sum's
    probabilities are the density of sum_r (y_r + e_r - U_r) at the integers, and one U
    turns that density at k into P(floor(...) = k). The byte grid: a continuous U is the
    grid's U plus an independent uniform of width h, so the grid loses h^2 / 12 of
    variance per uniform, which the Gaussian's variance gives back; what remains differs
    from the continuous law in the fourth cumulant, (R - 1) h^4 / 120 = 2e-12 (R - 1)
    LSB^4, and by aliases at 2 pi / h that the Gaussian's exp(-(2 pi / h)^2 R sigma^2 / 2)
    removes entirely. Exact up to the aliases (below 4e-20 at sigma >= 3 LSB) and that
    cumulant (probabilities off by under 1e-15); no clipping (the caller checks the
    range). tests/scene/test_fidelity.py compares it with the R-fold convolution of the
    per-repetition probabilities (and fails without the variance the grid lacks).
    Many columns at once, each with its own generator: :func:`draw_repetition_sums`.
    """
    return draw_repetition_sums([rng], [mean_lsb], [sigma_lsb], repetitions)[0]


def draw_repetition_sums(rngs: Sequence[np.random.Generator],
                         means_lsb: Sequence[NDArray[np.float64]],
                         sigmas_lsb: Sequence[float], repetitions: int,
                         out: NDArray[np.int32] | None = None) -> NDArray[np.int32]:
    """(B, L) :func:`draw_repetition_sum` of B columns of L samples, column b drawn from
    ``rngs[b]`` (its Gaussians first, then its bytes: the same values as alone).

    The arithmetic runs on blocks of about _BLOCK_VALUES values (columns that stay in a
    core's cache together); every value goes through the same float64 operations in the
    same order as the whole batch at once: the same sums bit for bit
    (tests/scene/test_noise_blocks.py). ``out``: the (B, L) int32 array to write them
    into (returned). A frame's columns, seeded by key: :func:`_draw_exact_sums`.
    """
    r = repetitions
    size = means_lsb[0].size
    out = np.empty((len(rngs), size), dtype=SUM_TYPE) if out is None else out
    scales = _repetition_scales(sigmas_lsb, r)
    step = max(1, _BLOCK_VALUES // size)
    rows = max(1, _BYTES_PER_DRAW // size)  # byte rows per draw
    draw = np.empty((min(step, len(rngs)), size))
    uniforms = np.empty(draw.shape)
    total = np.empty(draw.shape, dtype=np.uint16 if (r - 1) * 255 < 1 << 16 else np.uint32)
    for b0 in range(0, len(rngs), step):
        block = slice(b0, b0 + step)
        n_b = len(rngs[block])
        d, u, t = draw[:n_b], uniforms[:n_b], total[:n_b]
        for row, rng in zip(d, rngs[block], strict=True):
            rng.standard_normal(out=row)
        d *= scales[block, None]
        for row, mean in zip(d, means_lsb[block], strict=True):
            row += mean
        if r > 1:
            t[...] = 0
            for acc, rng in zip(t, rngs[block], strict=True):
                for r0 in range(0, r - 1, rows):
                    n = min(rows, r - 1 - r0) * size
                    octets = rng.bit_generator.random_raw(-(-n // 8)).view(np.uint8)[:n]
                    acc += np.add.reduce(octets.reshape(-1, size), axis=0, dtype=t.dtype)
            np.add(t, 0.5 * (r - 1), out=u)  # sum of (b + 1/2): exact in float64
            u *= 1.0 / 256  # exact: a power of two
            d -= u
        np.floor(d, out=out[block], casting="unsafe")
    return out


def _repetition_scales(sigmas_lsb: Sequence[float], r: int) -> NDArray[np.float64]:
    """The Gaussian's scale (LSB) of each column's repetition sum: sqrt(R sigma^2 + (R - 1)
    h^2 / 12) (:func:`draw_repetition_sum`)."""
    return np.sqrt(r * np.square(np.asarray(sigmas_lsb, dtype=np.float64))
                   + (r - 1) * _BYTE_VARIANCE)


def _draw_exact_sums(seeds: NDArray[np.uint64], means_lsb: Sequence[NDArray[np.float64]],
                     sigmas_lsb: Sequence[float], repetitions: int,
                     out: NDArray[np.int32] | None = None) -> NDArray[np.int32]:
    """:func:`draw_repetition_sums` of the PCG64 generators seeded with the rows of
    ``seeds`` (B, 4) (:func:`cdma_lidar.scene.streams.seed_words`, what
    ``default_rng(key)`` seeds it with): the same values.

    With numba (the ``fast`` extra) each column is one call of a compiled kernel that runs
    numpy's PCG64 and ziggurat itself and does the arithmetic in numpy's order
    (:func:`cdma_lidar.scene.noise_kernel.repetition_kernel`: no generator object, no call
    through a function pointer per draw); without it, or where a column's bytes take more
    than one draw, numpy's generators and blocks (tests/scene/test_noise_blocks.py).
    """
    r, size = repetitions, means_lsb[0].size
    kernel = repetition_kernel() if r - 1 <= max(1, _BYTES_PER_DRAW // size) else None
    if kernel is None:
        return draw_repetition_sums(from_seed_words(seeds), means_lsb, sigmas_lsb, r, out)
    out = np.empty((len(seeds), size), dtype=SUM_TYPE) if out is None else out
    draw, total = np.empty(size), np.empty(size, dtype=np.uint32)
    words = np.empty(-(-(r - 1) * size // 8), dtype=np.uint64)
    for row, seed, mean, scale in zip(out, seeds, means_lsb,
                                      _repetition_scales(sigmas_lsb, r).tolist(), strict=True):
        kernel(seed, r, scale, np.ascontiguousarray(mean, dtype=np.float64), draw, total,
               words, row)
    return out


def _draw_table_sums(seeds: NDArray[np.uint64], means: Sequence[NDArray[np.float32]],
                     stds: Sequence[np.float32], out: NDArray[np.int32] | None = None
                     ) -> NDArray[np.int32]:
    """(B, L) ``floor(mean + std z)`` of ``accumulated`` fidelity, z from _normal_table
    picked by 16-bit words of each column's generator (a fourth of a word per value): the
    PCG64 generator seeded with that column's row of ``seeds`` (B, 4)
    (:func:`cdma_lidar.scene.streams.seed_words`, what ``default_rng(key)`` seeds it with).

    No clip is needed: |z| <= 4.3 and the plan keeps the echo 6 sigma inside the ADC's
    range, so R x + 4.3 sqrt(R (sigma^2 + 1/12)) stays below R times the top code. With
    numba (the ``fast`` extra) each column is one call of a compiled kernel that runs
    numpy's PCG64 itself (:mod:`cdma_lidar.scene.noise_kernel`: no generator object, no
    call per draw); without it numpy's generators draw the words and the arithmetic runs
    on blocks of about _BLOCK_VALUES values, as in draw_repetition_sums. Both are the
    same words and the same float32 operations in the same order: the same values bit
    for bit (tests/scene/test_noise_blocks.py). ``out``: the (B, L) int32 array to write
    them into (returned).
    """
    size = means[0].size
    out = np.empty((len(seeds), size), dtype=SUM_TYPE) if out is None else out
    scales = np.asarray(stds, dtype=np.float32)
    table = _normal_table()
    kernel = row_kernel()
    if kernel is not None:
        for row, seed, mean, scale in zip(out, seeds, means, scales, strict=True):
            kernel(seed, table, scale, mean, row)
        return out
    rngs = from_seed_words(seeds)
    quarter = -(-size // 4)
    step = max(1, _BLOCK_VALUES // size)
    index = np.empty((min(step, len(rngs)), size), dtype=np.intp)
    draw = np.empty(index.shape, dtype=np.float32)
    for b0 in range(0, len(rngs), step):
        block = slice(b0, b0 + step)
        n_b = len(rngs[block])
        d = draw[:n_b]
        for row, rng in zip(index[:n_b], rngs[block], strict=True):  # 16-bit quarters
            np.copyto(row, rng.bit_generator.random_raw(quarter).view(np.uint16)[:size])
        np.take(table, index[:n_b], out=d, mode="clip")  # in range: clip only skips a copy
        d *= scales[block, None]
        for row, mean in zip(d, means[block], strict=True):
            row += mean
        np.floor(d, out=out[block], casting="unsafe")
    return out


#: Most random bytes :func:`draw_repetition_sums` draws at a time (16 MB, in whole rows of
#: L): a column whose R - 1 byte rows are more takes several draws (and numpy's blocks).
_BYTES_PER_DRAW = 1 << 24

#: Variance (LSB^2) a uniform on the byte grid (b + 1/2) / 256 lacks against a continuous one.
_BYTE_VARIANCE = 1.0 / (12 * 256**2)

#: Values per block of the noise's arithmetic: float64 blocks of 512 kB, a few of which
#: stay in one core's 2 MB cache while every pass runs over them.
_BLOCK_VALUES = 1 << 16


@functools.cache
def _normal_table() -> NDArray[np.float32]:
    """65536 standard normal quantiles, ``Phi^-1((i + 1/2) / 65536)``, scaled to variance 1.

    ``accumulated`` fidelity's Gaussians: a uniform 16-bit word picks one (a fourth of a
    generator word and a table look-up per value instead of a ziggurat draw). The law
    is symmetric with mean 0 and variance 1, within 2^-16 of the normal's distribution
    function everywhere (Kolmogorov distance) and cut at 4.2 standard deviations.
    """
    from scipy.special import ndtri  # deferred: start-up time of every command with a scene

    q = ndtri((np.arange(1 << 16) + 0.5) / (1 << 16))
    q /= np.sqrt(np.mean(q * q))
    return q.astype(np.float32)


def speckle_factors(cells: float, shape: tuple[int, ...], seed: int) -> NDArray[np.float64]:
    """Per-pixel speckle power fading: Gamma(cells, 1/cells) (mean 1, variance 1/cells).

    Fully developed speckle integrated over ``cells`` correlation cells of the aperture;
    fixed for a static scene (seeded by the noise seed only, not the frame), so averaging
    frames does not remove it.
    """
    rng = np.random.default_rng([seed, _STREAM_SPECKLE])
    return rng.gamma(cells, 1.0 / cells, size=shape)


@dataclass(frozen=True)
class RenderSettings:
    """What the device is configured to emit and sample (may differ from the scene's defaults).

    code_index: Gold member per channel; uid_bits/uid: our UID (n periods per frame);
    samples_per_chip S; averages R (frames per column); poly_u/poly_v: the code pair.
    """

    samples_per_chip: int
    averages: int
    uid_bits: int
    uid: int
    code_index: tuple[int, ...]
    poly_u: tuple[int, ...]
    poly_v: tuple[int, ...]

    @classmethod
    def from_spec(cls, spec: InstrumentSpec) -> RenderSettings:
        """The scene's own defaults."""
        return cls(samples_per_chip=spec.samples_per_chip, averages=spec.averages,
                   uid_bits=spec.uid_bits, uid=spec.uid, code_index=spec.code_indices,
                   poly_u=spec.poly_u, poly_v=spec.poly_v)

    def __hash__(self) -> int:
        """The fields' hash, computed once (every column a frame renders looks its plan up
        under a key that holds the settings, and the code indices are 40 or more ints);
        not pickled (:meth:`__getstate__`), so a copy in another process hashes anew."""
        h = self.__dict__.get("_hash")
        if h is None:
            h = hash(tuple(getattr(self, f.name) for f in fields(self)))
            object.__setattr__(self, "_hash", h)
        return h

    def __getstate__(self) -> dict:
        """The fields, without the cached hash."""
        return {k: v for k, v in self.__dict__.items() if k != "_hash"}

    @property
    def frame_chips(self) -> int:
        """Chips per UID frame: n * N."""
        return self.uid_bits * ((1 << self.poly_u[0]) - 1)

    @property
    def frame_samples(self) -> int:
        """Samples per UID frame: n * N * S."""
        return self.frame_chips * self.samples_per_chip


def detector_response(f_hz: NDArray[np.float64], bandwidth_hz: float,
                      nyquist_hz: float) -> NDArray[np.float64]:
    """H(f): Gaussian (-3 dB at ``bandwidth_hz``) times the anti-alias taper; H(0) = 0 (AC)."""
    f = np.abs(np.asarray(f_hz, dtype=np.float64))
    h = np.exp(-0.5 * np.log(2.0) * (f / bandwidth_hz) ** 2)
    knee = 0.8 * nyquist_hz
    x = np.clip((f - knee) / (nyquist_hz - knee), 0.0, 1.0)
    h *= np.cos(0.5 * np.pi * x) ** 2
    h[f == 0] = 0.0
    return h


@functools.lru_cache(maxsize=8)
def _bin_weights(m: int, period: int, length: int, chip_rate_hz: float,
                 bandwidth_hz: float, nyquist_hz: float) -> NDArray[np.float64]:
    """(m,) H(f_q) sinc(q / nN) L / nN, f_q = q chip_rate / nN (read-only; nN = ``period``)."""
    q = np.arange(m)
    h = detector_response(q * chip_rate_hz / period, bandwidth_hz, nyquist_hz)
    weight = h * np.sinc(q / period) / period * length
    weight.flags.writeable = False
    return weight


def _uid_signs(uid: int, n: int) -> NDArray[np.float64]:
    """(-1)^bit_p(uid) for periods p = 0..n-1."""
    return np.where((uid >> np.arange(n)) & 1, -1.0, 1.0)


class Instrument:
    """Renders the ADC samples the virtual board would record for one column.

    ``Instrument(scene, seed)``; :meth:`render` for a scan column, :meth:`render_calibration`
    for one shot of the zeroth-order target. Powers are a (K, C) matrix in watts (default:
    the scene's per-channel laser power at every column).
    """

    def __init__(self, scene: Scene, seed: int = 0) -> None:
        if not is_int(seed) or seed < 0:
            raise out_of_range("seed", "a non-negative integer", seed)
        self.scene = scene
        self.spec = scene.instrument
        self.seed = int(seed)
        self.truth: Truth = compute_truth(scene)
        h = self.truth.hits
        k, c = h.range_m.shape
        self.channels, self.columns = k, c
        self.default_power_w = np.repeat(self.spec.laser_power_w[:, None], c, axis=1)
        lit = h.lit
        #: the channels each column lights (lit_channels), read-only
        self._lit_channels = [np.flatnonzero(lit[:, col]) for col in range(c)]
        for chans in self._lit_channels:
            chans.flags.writeable = False
        r = np.where(lit, h.range_m, 1.0)
        #: per-pixel speckle fading of the received power (None: no speckle)
        self.speckle = (speckle_factors(self.spec.speckle_cells, (k, c), self.seed)
                        if self.spec.speckle_cells > 0 else None)
        #: the physical link budget of every pixel (cdma_lidar.scene.linkbudget)
        self.budget = LinkBudget.of(self.spec, h.reflectivity, h.cos_incidence, h.range_m,
                                    self.speckle)
        #: per-pixel amplitude (V) per watt of laser power; 0 where nothing is hit
        self.gain_v_per_w = self.budget.amplitude_per_w
        #: per-pixel round-trip delay (s) including the hidden system delay
        self.delay_s = np.where(lit, 2.0 * r / SPEED_OF_LIGHT_M_S + self.spec.system_delay_s,
                                np.nan)
        #: one of cdma_lidar.scene.model.FIDELITY_LEVELS
        self.fidelity = scene.fidelity
        # the level's compiled kernels, loaded (numba's import and its cached code, once
        # per process) here, not in a frame
        for kernel in ((row_kernel, terms_kernel) if self.fidelity == "accumulated"
                       else (synthesis_kernel, repetition_kernel)):
            kernel()
        self._spectra: dict[tuple, dict[int, NDArray[np.complex128]]] = {}
        self._columns: dict[tuple, tuple[NDArray[np.float64], float]] = {}
        self._columns_bytes = 0
        self._coefficients: dict[int, dict[str, float]] = {}
        self._fixed_noise_v = self._fixed_noise(RenderSettings.from_spec(self.spec))
        #: per-sample noise rms (V) at the scene's own settings and power, median over columns
        self.noise_rms_v = float(np.median(self.noise_rms_columns_v()))

    # -- the scene's needs ---------------------------------------------------------------

    def calibration_gain_v_per_w(self) -> float:
        """Amplitude (V) per watt of one channel's echo from the zeroth-order target."""
        cal = self.scene.calibration
        return (link_gain_v_m2_per_w(self.spec) * cal.reflectivity * cal.zeroth_order_efficiency
                / cal.target_distance_m**2)

    def noise_rms_columns_v(self, cfg: RenderSettings | None = None,
                            power_w: NDArray[np.float64] | None = None) -> NDArray[np.float64]:
        """(C,) per-sample noise rms (V) of every column at laser power ``power_w`` (K, C)."""
        cfg = cfg or RenderSettings.from_spec(self.spec)
        if self._fixed_noise_v is not None:
            return np.full(self.columns, self._fixed_noise_v)
        p = self.default_power_w if power_w is None else np.asarray(power_w, dtype=np.float64)
        return np.sqrt(self.budget.noise_variance_v2(p, self.budget.rx_per_w,
                                                     cfg.samples_per_chip))

    def noise_rms_v_at(self, column: int, cfg: RenderSettings,
                       power_w: NDArray[np.float64] | None = None,
                       calibration: bool = False) -> float:
        """Per-sample noise rms (V) of one column (or calibration shot) at power ``power_w`` (K,).

        The signal's own shot noise and the ASE beat depend on what the column receives;
        the other sources do not. A fixed ``noise_rms_v`` or ``snr_db`` replaces all.
        """
        if self._fixed_noise_v is not None:
            return self._fixed_noise_v
        p = self.default_power_w[:, column] if power_w is None else np.asarray(power_w)
        if calibration:
            rx = np.full(self.channels, self.calibration_gain_v_per_w()
                         / self.budget.volts_per_rx_w)
        else:
            rx = self.budget.rx_per_w[:, column]
        return float(np.sqrt(self.budget.noise_variance_v2(p, rx, cfg.samples_per_chip,
                                                           self._noise_coefficients(cfg))))

    def _noise_coefficients(self, cfg: RenderSettings) -> dict[str, float]:
        coef = self._coefficients.get(cfg.samples_per_chip)
        if coef is None:
            coef = self._coefficients[cfg.samples_per_chip] = self.budget.coefficients(
                cfg.samples_per_chip)
        return coef

    def _noise_rms_items(self, cfg: RenderSettings,
                         items: Sequence[tuple[int, NDArray[np.float64] | None]],
                         calibration: bool) -> NDArray[np.float64]:
        """(B,) :meth:`noise_rms_v_at` of each (column, power), for the batch at once: the
        same values (each column's sums over its channels run along one contiguous row,
        as a column's alone does; tests/scene/test_noise_blocks.py)."""
        if self._fixed_noise_v is not None:
            return np.full(len(items), self._fixed_noise_v)
        p = np.stack([self.default_power_w[:, col] if pw is None else np.asarray(pw)
                      for col, pw in items])
        if calibration:
            rx = np.full(p.shape, self.calibration_gain_v_per_w() / self.budget.volts_per_rx_w)
        else:
            rx = np.ascontiguousarray(self.budget.rx_per_w[:, [col for col, _ in items]].T)
        return np.sqrt(self.budget.noise_variance_v2(p, rx, cfg.samples_per_chip,
                                                     self._noise_coefficients(cfg), axis=1))

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

    def lit_channels(self, column: int) -> NDArray[np.int64]:
        """Channels whose ray hits an object at ``column``."""
        return self._lit_channels[column]

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
        delays = [2 * lo / SPEED_OF_LIGHT_M_S + sys_d, 2 * hi / SPEED_OF_LIGHT_M_S + sys_d]
        delays += [u.delay_s for u in self.spec.other_users]
        delays += [2 * g.distance_m / SPEED_OF_LIGHT_M_S + sys_d for g in self.spec.ghosts]
        period = self.spec.code_length * s
        start = max(int(np.floor(min(delays) * fs)) - margin, 0)
        length = int(np.ceil(max(delays) * fs)) + margin - start + 1
        length = max(minimum, -(-length // 16) * 16)
        if length >= period:
            return 0, period
        return start % period, length

    # -- spectra ---------------------------------------------------------------------------

    def _frame_bins(self, cfg: RenderSettings) -> tuple[NDArray[np.float64], int]:
        length = cfg.frame_samples
        m = length // 2 + 1
        f = np.arange(m) * self.spec.chip_rate_hz / cfg.frame_chips
        return f, length

    def _code_spectra(self, cfg: RenderSettings, indices: tuple[int, ...], uid: int,
                      uid_bits: int) -> NDArray[np.complex128]:
        """(len(indices), L/2+1) filtered NRZ spectra of Gold members with a UID, scaled by L."""
        rows = self._spectrum_rows(cfg, indices, uid, uid_bits)
        return np.stack([rows[i] for i in indices])

    def _spectrum_rows(self, cfg: RenderSettings, indices: tuple[int, ...], uid: int,
                       uid_bits: int) -> dict[int, NDArray[np.complex128]]:
        """Whole spectra by Gold member (L/2 + 1 bins: ``dft[q % nN] * weight[q]`` of
        :meth:`_chip_spectra`), computed once per (settings, member, UID) and dropped
        with the settings."""
        rows = self._book(("rows", cfg.samples_per_chip, cfg.poly_u, cfg.poly_v, uid, uid_bits))
        missing = tuple(sorted({i for i in indices if i not in rows}))
        if missing:
            dfts, period = self._chip_spectra(cfg, missing, uid, uid_bits)
            weight = self._spectral_weight(cfg, period)
            q = np.arange(weight.size) % period
            for i in missing:
                rows[i] = dfts[i].reshape(-1)[q] * weight
        return rows

    def _chip_spectra(self, cfg: RenderSettings, indices: tuple[int, ...], uid: int,
                      uid_bits: int, single: bool = False
                      ) -> tuple[dict[int, NDArray[np.complexfloating]], int]:
        """(by Gold member: the nN-point DFT of its UID-signed bipolar chips, zero-padded to
        an (A, B) array, A B >= nN; the period nN in bins). A member's spectrum at bin q
        is ``dft[q % nN] * weight[q]`` (:meth:`_spectral_weight`): the L/2 + 1 bins of
        an S-samples-per-chip frame repeat the chips' DFT S/2 times under one smooth
        weight, which :meth:`_sum_delayed` exploits. Computed once per member and
        UID. ``single``: complex64 copies."""
        rows = self._book(("chips", single, cfg.poly_u, cfg.poly_v, uid, uid_bits))
        period = uid_bits * ((1 << cfg.poly_u[0]) - 1)
        missing = tuple(sorted({i for i in indices if i not in rows}))
        if missing:
            codes = gold_codes(cfg.poly_u, cfg.poly_v, missing, field="code_index")
            bip = 1.0 - 2.0 * codes.astype(np.float64)  # (k, N)
            chips = (bip[:, None, :] * _uid_signs(uid, uid_bits)[None, :, None]
                     ).reshape(len(missing), period)
            b = math.isqrt(period - 1) + 1
            a = -(-period // b)
            spec = np.zeros((len(missing), a * b), dtype=np.complex128)
            spec[:, :period] = np.fft.fft(chips, axis=1)
            for i, row in zip(missing, spec, strict=True):
                rows[i] = row.reshape(a, b).astype(np.complex64) if single else row.reshape(a, b)
        return rows, period

    def _book(self, key: tuple) -> dict:
        """The codebook's entry ``key``: a dict (spectra by Gold member; the waveform
        tables' stack, rows and peaks), new and empty the first time; the whole codebook
        is dropped when it holds 16 entries (the settings changed that often)."""
        book = self._spectra.get(key)
        if book is None:
            if len(self._spectra) >= 16:
                self._spectra.clear()
            book = self._spectra[key] = {}
        return book

    def _spectral_weight(self, cfg: RenderSettings, period: int) -> NDArray[np.float64]:
        """(L/2 + 1,) real weight of every member's spectrum: the detector's H(f), the NRZ
        chip's sinc and the scale L / (nN) (``period`` = nN chips per frame)."""
        length = period * cfg.samples_per_chip
        return _bin_weights(length // 2 + 1, period, length, self.spec.chip_rate_hz,
                            self.spec.detector_bandwidth_hz,
                            self.spec.chip_rate_hz * cfg.samples_per_chip / 2)

    def _sample_shift_s(self, cfg: RenderSettings) -> float:
        tc = 1.0 / self.spec.chip_rate_hz
        return tc / 2 - tc / cfg.samples_per_chip / 2

    def _echo_terms(self, column: int, cfg: RenderSettings, power_w: NDArray[np.float64] | None,
                    calibration: bool) -> tuple[NDArray[np.float64], NDArray[np.float64],
                                                tuple[int, ...], NDArray[np.int64]] | None:
        """(amplitudes (V), delays (s, sample shift included), Gold members, channels) of the
        column's echoes and ghosts (in that order: the echoes by ascending channel); None
        when nothing is lit."""
        power = self.default_power_w[:, column] if power_w is None else np.asarray(power_w)
        if calibration:
            cal = self.scene.calibration
            chans = np.arange(self.channels)
            amps = self.calibration_gain_v_per_w() * power
            taus = np.full(self.channels, 2 * cal.target_distance_m / SPEED_OF_LIGHT_M_S
                           + self.spec.system_delay_s)
        else:
            chans = self.lit_channels(column)
            amps = self.gain_v_per_w[chans, column] * power[chans]
            taus = self.delay_s[chans, column]
        if self.spec.ghosts:
            amps, taus, chans = self._with_ghosts(column, amps, taus, chans)
        keep = amps != 0
        if not keep.all():
            amps, taus, chans = amps[keep], taus[keep], chans[keep]
        if not amps.size:
            return None
        members = tuple(int(cfg.code_index[c]) for c in chans.tolist())
        return amps, taus + self._sample_shift_s(cfg), members, chans

    def _batch_echo_terms(self, cfg: RenderSettings,
                          items: Sequence[tuple[int, NDArray[np.float64] | None]],
                          calibration: bool) -> list[tuple | None]:
        """:meth:`_echo_terms` of each (column, power), the scan's common case (no ghosts,
        not calibration) gathered for the whole batch at once (the same values)."""
        if calibration or self.spec.ghosts or not items:
            return [self._echo_terms(col, cfg, p, calibration) for col, p in items]
        cols = [col for col, _ in items]
        chans = [self._lit_channels[col] for col in cols]
        counts = [c.size for c in chans]
        if not sum(counts):
            return [None] * len(items)
        ch = np.concatenate(chans)
        which = np.repeat(np.arange(len(items)), counts)
        power = np.stack([self.default_power_w[:, col] if p is None else np.asarray(p)
                          for col, p in items])
        amps = self.gain_v_per_w[ch, np.repeat(cols, counts)] * power[which, ch]
        taus = self.delay_s[ch, np.repeat(cols, counts)] + self._sample_shift_s(cfg)
        keep = amps != 0
        if not keep.all():
            amps, taus, ch, which = amps[keep], taus[keep], ch[keep], which[keep]
        members = np.asarray(cfg.code_index, dtype=np.int64)[ch].tolist()
        ends = np.cumsum(np.bincount(which, minlength=len(items))).tolist()
        out: list[tuple | None] = []
        for j, end in enumerate(ends):
            start = ends[j - 1] if j else 0
            out.append((amps[start:end], taus[start:end], tuple(members[start:end]),
                        ch[start:end]) if end > start else None)
        return out

    def echo(self, column: int, cfg: RenderSettings,
             power_w: NDArray[np.float64] | None = None,
             calibration: bool = False, single: bool = False) -> NDArray[np.floating]:
        """Noise-free photodiode voltage (V) of one frame (L samples) at ``column``.

        Our own channels (lit ones only) and the ghosts configured for this column; other
        users are not periodic in our frame in general and are added by :meth:`render`.
        ``power_w``: laser power per channel (W) at this column. In ``calibration`` mode every
        channel sees the zeroth-order target. ``single``: computed in single precision
        (complex64 spectra, float32 result, relative error about 1e-7 of the largest
        echo, i.e. below 1e-4 LSB for echoes inside the ADC's range); about half the cost.
        """
        length = cfg.frame_samples
        m = length // 2 + 1
        f0 = self.spec.chip_rate_hz / cfg.frame_chips if m > 1 else 0.0  # bin spacing (Hz)
        terms = self._echo_terms(column, cfg, power_w, calibration)
        if terms is None:
            return np.zeros(length, dtype=np.float32 if single else np.float64)
        amps, taus, members, _ = terms
        dfts, period = self._chip_spectra(cfg, members, cfg.uid, cfg.uid_bits, single)
        total = self._sum_delayed(f0, amps, taus, *self._stack(dfts, members), period,
                                  self._spectral_weight(cfg, period))
        return np.fft.irfft(total, n=length)

    @staticmethod
    def echo_tabulated(cfg: RenderSettings) -> bool:
        """Whether ``accumulated`` renders echoes from waveform tables under ``cfg`` (the
        tables of every code member fit ECHO_CACHE_BYTES) or by the Fourier synthesis."""
        return (TABLE_PHASES + 1) * cfg.frame_samples * 8 * len(set(cfg.code_index)) \
            <= ECHO_CACHE_BYTES

    def tabulated_echo(self, column: int, cfg: RenderSettings,
                       power_w: NDArray[np.float64] | None = None,
                       calibration: bool = False, out: NDArray[np.float32] | None = None
                       ) -> NDArray[np.float32]:
        """:meth:`echo` from a table of waveforms, float32: ``accumulated`` fidelity's echo.

        Each Gold member's filtered waveform is tabulated once per configuration at
        TABLE_PHASES + 1 delays p / TABLE_PHASES of a sample, p = 0..TABLE_PHASES (float32,
        :meth:`_waveform_table`). A channel at delay ``tau`` (d whole samples plus p + t
        table steps, 0 <= t < 1) adds ``A ((1 - t) w_p + t w_(p+1))`` rotated by d
        samples: no Fourier transform per column. Linear interpolation between phases
        1/8 of a sample apart errs by about ``t (1 - t) (pi f / (8 f_s))^2 / 2`` of the
        component at frequency f: below 0.5 % of the echo's peak on paper-scene1
        (tests/scene/test_fidelity.py), a pure low-pass with no delay bias to first order.
        ``out``: a contiguous (L,) float32 array to write into (its values are not read).
        """
        if out is None:
            out = np.empty(cfg.frame_samples, dtype=np.float32)
        self._tabulated_echoes(cfg, [(column, power_w)], calibration, out[None, :])
        return out

    def _tabulated_echoes(self, cfg: RenderSettings,
                          items: Sequence[tuple[int, NDArray[np.float64] | None]],
                          calibration: bool, out: NDArray[np.float32], gain: float = 1.0,
                          start: float = 0.0, terms: list[tuple | None] | None = None
                          ) -> NDArray[np.float64]:
        """``start`` (float32) plus :meth:`tabulated_echo` of each (column, power) times
        ``gain``, written into the rows of ``out`` (B, L) float32 (C-contiguous; what it
        held is overwritten, a row with no echo is ``start``): the delays of the whole
        batch split into samples, table phases and fractions at once, then two saxpy calls
        per channel, in the batch's order (each row its terms in its own order), reading
        one stack of every member's table (BLAS reads and writes at offsets into the flat
        stack and batch: no view per call). With numba, :mod:`cdma_lidar.scene.echo_kernel`
        does the whole batch in one call, each row's terms in passes over the row of up to
        four terms (their eight multiply-adds in the saxpy calls' order: the same values
        where BLAS fuses its multiply-adds), so a row is read and written once per four
        terms.
        Returns (B,) each row's sum of |amplitude x gain| times its members' largest
        |table value|: a bound on the largest |value| added to the row (an interpolation
        between two phases stays within their extremes), found with no pass over the row.
        ``terms``: the items' :meth:`_batch_echo_terms`, where the caller has them."""
        if not out.flags.c_contiguous:  # (then the flat view below is a view, not a copy)
            raise ValueError("out must be C-contiguous: BLAS adds into its flat view")
        if terms is None:
            terms = self._batch_echo_terms(cfg, items, calibration)
        lit = [j for j, t in enumerate(terms) if t is not None]
        out[[j for j, t in enumerate(terms) if t is None]] = start
        if not lit:
            return np.zeros(len(items))
        length = cfg.frame_samples
        rows = np.repeat(lit, [len(terms[j][2]) for j in lit])
        amps = np.concatenate([terms[j][0] for j in lit]) * gain
        steps = np.concatenate([terms[j][1] for j in lit]) * (
            self.spec.chip_rate_hz * cfg.samples_per_chip * TABLE_PHASES)
        members = [i for j in lit for i in terms[j][2]]
        stack, where, peak = self._waveform_table(cfg, tuple(members))
        whole = np.floor(steps)
        frac = steps - whole
        delay, phase = np.divmod(whole.astype(np.int64), TABLE_PHASES)
        # member's table, row p, rotated by the delay; the term's row of the batch
        x_at = (np.array([where[i] for i in members]) * (TABLE_PHASES + 1) + phase) * (
            2 * length) + length - delay % length
        y_at = rows * length
        first, second = amps * (1.0 - frac), amps * frac
        y, flat = out.reshape(-1), stack.reshape(-1)
        kernel = terms_kernel()
        if kernel is not None:  # the whole batch in one compiled call, rows set as reached
            kernel(flat, x_at, y_at, first.astype(np.float32), second.astype(np.float32),
                   np.float32(start), y, length)
        else:
            from scipy.linalg.blas import saxpy  # deferred, as in _normal_table

            out[lit] = start
            two = 2 * length
            for a, b, x0, y0 in zip(first.tolist(), second.tolist(), x_at.tolist(),
                                    y_at.tolist(), strict=True):
                saxpy(flat, y, length, a, x0, 1, y0)  # y[y0:y0 + L] += a w_p[rotated]
                saxpy(flat, y, length, b, x0 + two, 1, y0)  # ... + b w_(p+1)[rotated]
        largest = np.array([peak[i] for i in members])
        return np.bincount(rows, np.abs(amps) * largest, minlength=len(items))

    def _waveform_table(self, cfg: RenderSettings, members: tuple[int, ...]
                        ) -> tuple[NDArray[np.float32], dict[int, int], dict[int, float]]:
        """((M, TABLE_PHASES + 1, 2 L) float32 waveforms: row p of a member's table is its
        filtered, unit-amplitude echo delayed by p / TABLE_PHASES of a sample (before the
        sample shift), one frame written twice (so any rotation is a slice); each Gold
        member's table in it; each member's largest |value| there). Built once per
        (settings, member) from the spectra and kept with them (TABLE_PHASES + 1 inverse
        FFTs per member); members not tabulated before are appended to the stack, so a
        batch's terms all read one array."""
        book = self._book(("table", cfg.samples_per_chip, cfg.poly_u, cfg.poly_v, cfg.uid,
                           cfg.uid_bits))
        where, peak = book.setdefault("row", {}), book.setdefault("peak", {})
        missing = tuple(sorted({i for i in members if i not in where}))
        if missing:
            spectra = self._spectrum_rows(cfg, missing, cfg.uid, cfg.uid_bits)
            import scipy.fft  # deferred, as in _normal_table

            length = cfg.frame_samples
            m = length // 2 + 1
            step = 1.0 / (self.spec.chip_rate_hz * cfg.samples_per_chip * TABLE_PHASES)
            f = np.arange(m) * (self.spec.chip_rate_hz / cfg.frame_chips)
            ramps = np.exp(-2j * np.pi * np.outer(np.arange(TABLE_PHASES + 1) * step, f))
            new = np.empty((len(missing), TABLE_PHASES + 1, 2 * length), dtype=np.float32)
            for table, i in zip(new, missing, strict=True):
                table[:, :length] = scipy.fft.irfft((ramps * spectra[i]).astype(np.complex64),
                                                    n=length, axis=1, overwrite_x=True)
                table[:, length:] = table[:, :length]  # a rotation is one slice
                peak[i] = float(np.abs(table[:, :length]).max())
            book["stack"] = np.concatenate([book["stack"], new]) if where else new
            where.update({i: len(where) + n for n, i in enumerate(missing)})
        return book["stack"], where, peak

    def _with_ghosts(self, column: int, amps: NDArray[np.float64], taus: NDArray[np.float64],
                     chans: NDArray[np.int64]) -> tuple[NDArray, NDArray, NDArray]:
        """The column's echoes plus the grating ghosts configured for it."""
        amps_l, taus_l, chans_l = [amps], [taus], [chans]
        for g in self.spec.ghosts:
            if g.columns and column not in g.columns:
                continue
            gch = np.asarray(g.channels if g.channels else range(self.channels), dtype=np.int64)
            amps_l.append(np.full(gch.size, g.amplitude_v))
            taus_l.append(np.full(gch.size, 2 * g.distance_m / SPEED_OF_LIGHT_M_S
                                  + self.spec.system_delay_s))
            chans_l.append(gch)
        return np.concatenate(amps_l), np.concatenate(taus_l), np.concatenate(chans_l)

    @staticmethod
    def _stack(dfts: dict[int, NDArray[np.complexfloating]], members: Sequence[int]
               ) -> tuple[NDArray[np.complexfloating], NDArray[np.int64]]:
        """(the distinct members' spectra of ``dfts`` stacked, (M, A, B); each member's row
        there, (T,)): the two arguments :meth:`_sum_delayed` takes."""
        distinct = sorted(set(members))
        row = {i: n for n, i in enumerate(distinct)}
        return (np.stack([dfts[i] for i in distinct]),
                np.array([row[i] for i in members], dtype=np.int64))

    @staticmethod
    def _sum_delayed(f0_hz: float, amps: NDArray[np.float64], taus: NDArray[np.float64],
                     spectra: NDArray[np.complexfloating], members: NDArray[np.int64],
                     period: int, weight: NDArray[np.float64],
                     out: NDArray[np.complexfloating] | None = None,
                     rows: Sequence[int] | None = None) -> NDArray[np.complexfloating]:
        """weight[q] sum_k amps_k dft_k[q % period] exp(-2j pi q f0 tau_k), q < m = weight.size:
        the per-channel work of the Fourier synthesis. Term k's chip spectrum dft_k is
        ``spectra[members[k]]`` (:meth:`_chip_spectra`'s (A, B) arrays stacked,
        :meth:`_stack`); their dtype, complex128 or complex64, is the sum's.

        With q = j period + p, the term is ``u_k[p] exp(-2j pi f0 tau_k j period)``, u_k =
        amps_k dft_k[p] exp(-2j pi p f0 tau_k) over one period (p < period), its ramp the
        outer product of two short exponentials (p = alpha B + beta): two complex
        multiplies over a period, then one multiply and add per further period of bins,
        where multiplying every bin by its own ramp and the member's whole spectrum costs
        three passes over all m bins (1.5x the work at S = 4, 2.4x at S = 16). The weight
        multiplies each sum once at the end. ``out``: an (m,) array of the spectra's
        dtype to write the sum into (overwritten). ``rows``: several sums at once, term k
        added into ``out[rows[k]]`` ((R, m) ``out``), the terms in the order given.

        Every complex product is numpy's (one rounding per part: ``re = fma(xr, yr,
        -(xi yi))``, ``im = fma(xr, yi, xi yr)``) and every sum a plain add, in this
        order; with numba (the ``fast`` extra), complex128 sums run in one compiled call
        doing the same operations (:func:`cdma_lidar.scene.echo_kernel.synthesis_kernel`;
        the same values bit for bit, tests/scene/test_echo_kernel.py).
        """
        m = weight.size
        a, b = spectra.shape[1:]
        dtype = spectra.dtype  # complex64 in single precision
        w = -2.0 * np.pi * f0_hz * taus
        hi = (np.exp(1j * np.outer(w, b * np.arange(a))) * amps[:, None]).astype(dtype)
        lo = np.exp(1j * np.outer(w, np.arange(b))).astype(dtype)
        starts = range(0, m, period)  # the first bin of each period of bins
        turns = np.exp(1j * np.outer(w, starts[1:])).astype(dtype)
        total = np.empty(m, dtype=dtype) if out is None else out
        kernel = synthesis_kernel() if dtype == np.complex128 else None
        if kernel is not None:
            if not total.flags.c_contiguous:  # (the kernel writes into its 2-D view)
                raise ValueError("out must be C-contiguous")
            kernel(spectra.reshape(len(spectra), -1), np.asarray(members, dtype=np.int64),
                   np.zeros(len(members), dtype=np.int64) if rows is None
                   else np.asarray(rows, dtype=np.int64), lo, hi, turns, period,
                   total.reshape(-1, m))
            total *= weight
            return total
        sums = [total] if rows is None else list(total)
        # each sum's periods of bins, and the same lengths of one period's terms
        parts = [[row[q0:q0 + period] for q0 in starts] for row in sums]
        tmp = np.empty((a, b), dtype=dtype)
        scratch = np.empty(period, dtype=dtype)
        heads = [tmp.reshape(-1)[:part.size] for part in parts[0]]
        written = [False] * len(sums)  # a sum's first term is written, not added
        for k, i in enumerate(np.asarray(members).tolist()):
            np.multiply(spectra[i], lo[k], out=tmp)
            np.multiply(tmp, hi[k][:, None], out=tmp)
            r = 0 if rows is None else rows[k]
            (first, *rest), add = parts[r], written[r]
            written[r] = True
            if not add:
                first[...] = heads[0]
            else:
                np.add(first, heads[0], out=first)
            for part, head, turn in zip(rest, heads[1:], turns[k], strict=True):
                if not add:
                    np.multiply(head, turn, out=part)
                    continue
                product = scratch[:part.size]
                np.multiply(head, turn, out=product)
                np.add(part, product, out=part)
        for row, done in zip(sums, written, strict=True):
            if not done:
                row[...] = 0
        total *= weight
        return total

    def other_users_signal(self, column: int, cfg: RenderSettings,
                           total_samples: int) -> NDArray[np.float64] | None:
        """Other LiDARs' light at our photodiode (V) over ``total_samples`` (None if none).

        The same for every column that sees the same users: computed once per set of
        users and settings (read-only result).
        """
        seen = tuple(i for i, u in enumerate(self.spec.other_users)
                     if not u.columns or column in u.columns)
        if not seen:
            return None
        users = [self.spec.other_users[i] for i in seen]
        key = ("users", seen, cfg, total_samples)
        hit = self._columns.get(key)
        if hit is not None:
            return hit[0]
        out = self._users_signal(users, cfg, total_samples)
        out.flags.writeable = False
        self._keep(key, (out, 0.0), out.nbytes)
        return out

    def _users_signal(self, users: list, cfg: RenderSettings,
                      total_samples: int) -> NDArray[np.float64]:
        out = np.zeros(total_samples)
        idx = np.arange(total_samples)
        for u in users:
            ucfg = RenderSettings(cfg.samples_per_chip, 1, u.uid_bits, u.uid, cfg.code_index,
                                  cfg.poly_u, cfg.poly_v)
            f, length = self._frame_bins(ucfg)
            dfts, period = self._chip_spectra(ucfg, (u.code_index,), u.uid, u.uid_bits)
            frame = np.fft.irfft(self._sum_delayed(
                f[1], np.array([u.amplitude_v]), np.array([u.delay_s + self._sample_shift_s(cfg)]),
                *self._stack(dfts, (u.code_index,)), period,
                self._spectral_weight(ucfg, period)), n=length)
            out += frame[idx % length]
        return out

    # -- noise and ADC -----------------------------------------------------------------------

    def _fixed_noise(self, cfg: RenderSettings) -> float | None:
        """The noise rms (V) a scene fixes (``noise_rms_v``, ``snr_db``), None: physical."""
        spec = self.spec
        if spec.noise_rms_v is not None:
            return float(spec.noise_rms_v)
        if spec.snr_db is None:
            return None
        amp = self.gain_v_per_w * self.default_power_w
        lit = self.truth.hits.lit
        if not np.any(lit):
            mean_a2 = float(np.mean((self.calibration_gain_v_per_w() * spec.laser_power_w) ** 2))
        else:
            mean_a2 = float(np.median(amp[lit] ** 2))
        return float(np.sqrt(mean_a2 * self.unit_signal_power(cfg) / 10 ** (spec.snr_db / 10)))

    def unit_signal_power(self, cfg: RenderSettings) -> float:
        """Mean square (V^2) of one channel's filtered waveform at amplitude 1 V."""
        spectra = self._code_spectra(cfg, (int(cfg.code_index[0]),), 0, 1)
        y = np.fft.irfft(spectra[0], n=cfg.samples_per_chip * ((1 << cfg.poly_u[0]) - 1))
        return float(np.mean(y * y))

    def _fine_scale(self) -> tuple[float, float]:
        """(fine-grid units per volt, offset in fine units): ADC gain, LSB and offset."""
        spec = self.spec
        lsb = spec.adc_full_scale_v / (1 << (spec.adc_bits - 1))
        return spec.adc_gain / lsb * (1 << FRAC_BITS), spec.adc_offset * (1 << FRAC_BITS)

    def _quantise_fine(self, fine: NDArray[np.float64]) -> NDArray[np.int16]:
        """ADC codes of a fine-grid float64 array, which is consumed (the work buffer).

        ``cdma_lidar.firmware_model.adc.quantise`` of ``rint(fine)``: its float path, five
        in-place float64 passes, bit-identical to the integer quantiser.
        """
        return quantise(fine, FRAC_BITS, self.spec.adc_bits, float_input=True,
                        overwrite_input=True)

    def to_codes(self, volts: NDArray[np.float64]) -> NDArray[np.int16]:
        """ADC: ``clip(round_half_up(gain * v / lsb + offset))``.

        The analog value goes to ``cdma_lidar.firmware_model.adc.quantise`` on a grid
        2**-FRAC_BITS LSB fine.
        """
        scale, offset = self._fine_scale()
        return self._quantise_fine(np.asarray(volts, dtype=np.float64) * scale + offset)

    def forget(self) -> None:
        """Drop the echoes kept between frames (to measure a cold first frame, or free memory)."""
        self._columns.clear()
        self._columns_bytes = 0

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
        hit = self._columns.get(key)
        if hit is not None:
            return hit
        echo = self.echo(column, cfg, power, calibration=calibration, single=single)
        echo.flags.writeable = False
        hit = (echo, self.noise_rms_v_at(column, cfg, power, calibration))
        self._keep(key, hit, echo.nbytes)
        return hit

    def _keep(self, key: tuple, value: tuple, nbytes: int) -> None:
        """Store ``value`` (``nbytes`` large) in the column cache, emptied first when
        the entry would take it past ECHO_CACHE_BYTES."""
        if self._columns_bytes + nbytes > ECHO_CACHE_BYTES:
            self._columns.clear()
            self._columns_bytes = 0
        self._columns[key] = value
        self._columns_bytes += nbytes

    def _noise_rng(self, frame: int, col: int, calibration: bool,
                   shot: int) -> np.random.Generator:
        """The noise generator of one rendered column (or calibration shot); many at
        once: :func:`cdma_lidar.scene.streams.generators` of the same keys."""
        stream = _STREAM_CALIBRATE if calibration else _STREAM_SCAN
        return np.random.default_rng([self.seed, stream, frame, shot if calibration else col])

    def _column_inputs(self, column: int, cfg: RenderSettings, frame: int,
                       power_w: NDArray[np.float64] | None, calibration: bool, shot: int
                       ) -> tuple[NDArray[np.float64], float, np.random.Generator, int]:
        """(one repetition's echo on the fine grid incl. offset, noise rms in fine units,
        the column's noise generator, the column index rendered)."""
        if not calibration:
            check_int("column", column, 0, self.columns - 1)
        col = 0 if calibration else column
        scale, offset = self._fine_scale()
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
                fine += users * self._fine_scale()[0]
        return self._quantise_fine(fine)

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
        (:func:`_normal_table`) and x the echo of :meth:`tabulated_echo` (no Fourier
        transform per column). Returns None (the caller renders ``exact``) when sigma <
        ACCUMULATED_MIN_NOISE_LSB or the column's echo comes within
        ACCUMULATED_CLIP_MARGIN sigma of the ADC's clip.
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
        plans: list[tuple | None] = []
        missing: dict[tuple, tuple[int, NDArray[np.float64], list[int]]] = {}
        for j, column in enumerate(columns):
            col = 0 if calibration else column
            p = None if power_w is None else power_w[j]
            power = self.default_power_w[:, col] if p is None else np.asarray(
                p, dtype=np.float64)
            key = (level, col, calibration, cfg, power.tobytes())
            hit = self._columns.get(key)
            plans.append(None if hit is None else hit[0])
            if hit is None:
                missing.setdefault(key, (col, power, []))[2].append(j)
        if missing:
            made = self._make_plans(level, cfg, [(c, p) for c, p, _ in missing.values()],
                                    calibration)
            for (key, (_, _, where)), plan in zip(missing.items(), made, strict=True):
                self._keep(key, (plan, 0.0), 0 if plan is None else plan[0].nbytes)
                for j in where:
                    plans[j] = plan
        drawn = np.array([p is not None for p in plans], dtype=bool)
        sums = self._draw_sums(level, cfg, frame, columns, plans, drawn, calibration,
                               np.empty(shape, dtype=SUM_TYPE) if out is None else out)
        for j in np.flatnonzero(~drawn).tolist() if complete else ():
            p = None if power_w is None else power_w[j]
            raw = self.render_exact(0 if calibration else columns[j], cfg, frame, p,
                                    calibration=calibration, shot=columns[j])
            np.add.reduce(raw.reshape(cfg.averages, -1), axis=0, dtype=SUM_TYPE,
                          out=sums[j].reshape(-1))
        return sums, drawn

    def _draw_sums(self, level: str, cfg: RenderSettings, frame: int, columns: Sequence[int],
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
        stream = _STREAM_CALIBRATE if calibration else _STREAM_SCAN
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
        offset) + 1/2`` from :meth:`tabulated_echo` and ``sqrt(R (sigma^2 + 1/12) - 1/12)``.
        """
        lsb_per_v = self._fine_scale()[0] / (1 << FRAC_BITS)
        top = adc_limits(self.spec.adc_bits)[1]
        exact = level != "accumulated"
        least = EXACT_SUM_MIN_NOISE_LSB if exact else ACCUMULATED_MIN_NOISE_LSB
        sigmas = (self._noise_rms_items(cfg, items, calibration) * lsb_per_v).tolist()
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
        |value|, LSB): :meth:`_echoes` with the scaling to LSB and the constant made in
        the spectrum."""
        scale, offset = self._fine_scale()
        lsb_per_v = scale / (1 << FRAC_BITS)
        r = cfg.averages
        shift = offset / (1 << FRAC_BITS) + ROUNDING_LSB
        block, top = self._echoes(cfg, items, calibration, r * lsb_per_v, r * shift)
        peaks = (top / r).tolist()
        means = list(block)
        for j, (col, _) in enumerate(items):
            users = None if calibration else self.other_users_signal(col, cfg,
                                                                     block.shape[1] * r)
            if users is not None:
                each = users.reshape(r, block.shape[1]) * lsb_per_v
                each += block[j] / r
                peaks[j] = float(np.abs(each).max())
                means[j] = each.sum(axis=0)
        return means, peaks

    def _echoes(self, cfg: RenderSettings, items: list[tuple[int, NDArray[np.float64]]],
                calibration: bool, gain: float = 1.0, shift: float = 0.0
                ) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """((B, L) float64 ``gain * echo + shift`` of each (column, power), (B,) the
        largest |value| of each): the spectra of about _BLOCK_VALUES values at a time (one
        buffer, in the cache), their batched inverse FFT and its extremes. The gain
        multiplies the spectral weight and the shift is the DC bin's (the defaults give
        :meth:`echo`'s values bit for bit: the same operations on each value, a column's
        channels added in the same order)."""
        length = cfg.frame_samples
        m = length // 2 + 1
        f0 = self.spec.chip_rate_hz / cfg.frame_chips if m > 1 else 0.0
        terms = self._batch_echo_terms(cfg, items, calibration)
        lit = [j for j, t in enumerate(terms) if t is not None]
        out = np.empty((len(items), length))
        out[[j for j, t in enumerate(terms) if t is None]] = shift
        peaks = np.empty(len(items))
        peaks[:] = abs(shift)
        if not lit:
            return out, peaks
        dfts, period = self._chip_spectra(
            cfg, tuple({i for j in lit for i in terms[j][2]}), cfg.uid, cfg.uid_bits)
        spectra, members = self._stack(dfts, [i for j in lit for i in terms[j][2]])
        first = np.cumsum([0, *(len(terms[j][2]) for j in lit)]).tolist()  # items' terms
        weight = self._spectral_weight(cfg, period)
        if gain != 1.0:
            weight = weight * gain
        step = max(1, _BLOCK_VALUES // length)
        sums = np.empty((min(step, len(lit)), m), dtype=np.complex128)
        for b0 in range(0, len(lit), step):
            block = lit[b0:b0 + step]
            part = sums[:len(block)]
            self._sum_delayed(f0, np.concatenate([terms[j][0] for j in block]),
                              np.concatenate([terms[j][1] for j in block]), spectra,
                              members[first[b0]:first[b0 + len(block)]], period, weight,
                              out=part,
                              rows=[r for r, j in enumerate(block) for _ in terms[j][2]])
            part[:, 0] += shift * length  # the weight is 0 at DC (AC coupling)
            if block[-1] - block[0] == len(block) - 1:  # consecutive rows: written in place
                wave = np.fft.irfft(part, n=length, axis=1, out=out[block[0]:block[-1] + 1])
            else:
                out[block] = wave = np.fft.irfft(part, n=length, axis=1)
            peaks[block] = np.maximum(wave.max(axis=1), -wave.min(axis=1))  # in the cache
        return out, peaks

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
        scale, offset = self._fine_scale()
        lsb_per_v = scale / (1 << FRAC_BITS)
        offset_lsb = offset / (1 << FRAC_BITS)
        r, length = cfg.averages, cfg.frame_samples
        gain = r * lsb_per_v
        shift = np.float32(r * offset_lsb + 0.5)
        users = [None if calibration or not self.spec.other_users
                 else self.other_users_signal(col, cfg, length * r) for col, _ in items]
        reach = np.array([0.0 if u is None else float(np.abs(u).max()) * lsb_per_v
                          for u in users])
        tabulated = self.echo_tabulated(cfg)
        terms = self._batch_echo_terms(cfg, items, calibration) if tabulated else None
        # Items with no echo and no other user share one constant row (a third of a frame)
        busy = [j for j, u in enumerate(users)
                if terms is None or terms[j] is not None or u is not None]
        block = np.empty((len(busy), length), dtype=np.float32)
        means = [np.full(length, shift, dtype=np.float32)] * len(items)
        for j, row in zip(busy, block, strict=True):
            means[j] = row
        bounds = np.zeros(len(items))
        if tabulated:  # the whole batch at once
            bounds[busy] = self._tabulated_echoes(cfg, [items[j] for j in busy], calibration,
                                                  block, gain, shift,
                                                  [terms[j] for j in busy])
        else:  # a table of every member would not fit: the Fourier synthesis
            block[:] = shift
            bounds[:] = np.inf
            for row, (col, power) in zip(block, items, strict=True):
                echo = self.echo(col, cfg, power, calibration=calibration, single=True)
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
