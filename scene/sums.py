"""The ADC and the drawn repetition sums: what the receive chain reads of a column.

The ADC (:class:`Adc`) puts the analog value on a grid 2**-FRAC_BITS LSB fine and hands it
to :func:`cdma_lidar.firmware_model.adc.quantise`::

    codes = clip(round_half_up(adc_gain * v / lsb + adc_offset), adc_bits)

The receive chain first sums a column's R repetitions; that sum is drawn directly from
its distribution (:func:`draw_repetition_sum` at ``exact`` fidelity: L Gaussians and
(R - 1) L random bytes instead of R L Gaussians and R L quantisations; at ``accumulated``
one Gaussian per sample from a table of quantiles, :func:`_draw_table_sums`), a frame's
columns each from its own generator seeded by key (:mod:`cdma_lidar.scene.streams`).
What the sums' means and scales are: :mod:`cdma_lidar.scene.plans`.
"""

from __future__ import annotations

import functools
from collections.abc import Sequence

import numpy as np
from numpy.typing import NDArray

from cdma_lidar.firmware_model.adc import quantise
from cdma_lidar.scene.model import InstrumentSpec
from cdma_lidar.scene.noise_kernel import repetition_kernel, row_kernel
from cdma_lidar.scene.streams import from_seed_words

__all__ = [
    "ACCUMULATED_CLIP_MARGIN",
    "ACCUMULATED_MIN_NOISE_LSB",
    "BLOCK_VALUES",
    "EXACT_SUM_CLIP_MARGIN",
    "EXACT_SUM_MIN_NOISE_LSB",
    "FRAC_BITS",
    "ROUNDING_LSB",
    "SUM_TYPE",
    "Adc",
    "draw_repetition_sum",
    "draw_repetition_sums",
    "split_sum",
]

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

#: Integer type of the drawn repetition sums: they lie in R times the ADC's range (the plans
#: keep the noise's reach inside it), |sum| <= 1024 * 2**15 = 2**25 at the largest R and ADC
#: width the virtual board accepts, far inside int32; half the bytes of int64 to write
#: (fresh pages in every cold frame) and for the receive chain to read.
SUM_TYPE = np.int32


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

    The arithmetic runs on blocks of about BLOCK_VALUES values (columns that stay in a
    core's cache together); every value goes through the same float64 operations in the
    same order as the whole batch at once: the same sums bit for bit
    (tests/scene/test_noise_blocks.py). ``out``: the (B, L) int32 array to write them
    into (returned). A frame's columns, seeded by key: :func:`_draw_exact_sums`.
    """
    r = repetitions
    size = means_lsb[0].size
    out = np.empty((len(rngs), size), dtype=SUM_TYPE) if out is None else out
    scales = _repetition_scales(sigmas_lsb, r)
    step = max(1, BLOCK_VALUES // size)
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
    on blocks of about BLOCK_VALUES values, as in draw_repetition_sums. Both are the
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
    step = max(1, BLOCK_VALUES // size)
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

#: Values per block of the noise's arithmetic (and of a batch's echo spectra,
#: :meth:`cdma_lidar.scene.echoes.Echoes.batch`): float64 blocks of 512 kB, a few of which
#: stay in one core's 2 MB cache while every pass runs over them.
BLOCK_VALUES = 1 << 16

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



class Adc:
    """The instrument's ADC: gain, LSB, offset and width of ``spec``."""

    def __init__(self, spec: InstrumentSpec) -> None:
        self.spec = spec

    def fine_scale(self) -> tuple[float, float]:
        """(fine-grid units per volt, offset in fine units): ADC gain, LSB and offset."""
        spec = self.spec
        lsb = spec.adc_full_scale_v / (1 << (spec.adc_bits - 1))
        return spec.adc_gain / lsb * (1 << FRAC_BITS), spec.adc_offset * (1 << FRAC_BITS)

    def quantise_fine(self, fine: NDArray[np.float64]) -> NDArray[np.int16]:
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
        scale, offset = self.fine_scale()
        return self.quantise_fine(np.asarray(volts, dtype=np.float64) * scale + offset)
