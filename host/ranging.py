r"""From correlation peaks to ranges: sub-sample lag, SNR_XC, threshold, fill-in.

Range (eq. 2): a peak at lag ``L`` samples is a round-trip delay
``tau = L / (S * f_chip)`` (S samples per chip, ``f_chip`` chips/s), so::

    r = c * tau / 2 - offset            (m; offset from calibration, Note 6)

One sample is ``c / (2 S f_chip)`` of range (0.60 m at 62.5 Mchip/s and S = 4), so
the integer lag alone is far too coarse; the lag is refined from the peak ``y0`` and
its two neighbours ``y-`` and ``y+`` (all taken with the peak's sign, so a negative
peak works the same way)::

    parabolic:  delta = (y- - y+) / (2 (y- - 2 y0 + y+))
    triangle:   delta = (y+ - y-) / (2 (y0 - min(y-, y+)))   (equiangular line fit)

both clipped to [-1/2, +1/2] sample. The autocorrelation of a rectangular-chip code is
a triangle S samples wide on each side, which the line fit recovers exactly; the
parabola is biased towards the integer lag on it (by up to 1/4 sample) but tolerates
a rounded, band-limited peak better. ``bench/bench_host.py`` measures both against
the scene truth; the default (``triangle``) had the smaller median error there
(paper-scene1: 0.016 m against 0.022 m parabolic and 0.249 m integer lag).

SNR_XC (eq. 44, Note 9) comes from the receiver's integer noise statistics through
the one shared function :func:`cdma_lidar.firmware_model.snr.snr_xc_db`. Pixels below the
threshold are rejected; its default follows the configuration
(:func:`default_snr_threshold_db`: 16 dB unless multiple-access interference caps
SNR_XC near it). On top of it, a pixel above the threshold is kept only if
``min_support`` of its 8 neighbours are above it too at a lag within ``support_tol``
(:func:`neighbour_support`; 0 turns this off): on paper-scene1 the strongest empty
pixels and the weakest object pixels overlap within about 1 dB, so the threshold alone
lets isolated noise peaks through (docs/host.md has the measurement). Like the paper
("3D imaging"), rejected pixels may be filled by linear interpolation of the
neighbouring channels' ranges in the same column.

Precision (eq. 27, Note 7)::

    sigma = sqrt(6 / N_s) / (2 pi) * dR / sqrt(SNR),    dR = c / (2 f_chip)   (eq. 26)

with ``N_s = N * S`` samples per symbol period and SNR the per-sample SNR of the
record. Correlating over N_s samples gives SNR_XC = N_s * SNR (processing gain), so
:func:`precision_eq27_m` accepts either.

Pixel flags (bitfield): 0 valid measured, 1 interpolated, 2 rejected, 4 foreign UID,
8 ghost, 16 saturated (the record's ``saturated`` field: the strongest peak's ``out``
word sat at a rail, so its lag may be early along the clipped plateau; docs/hdl.md).
A rejected pixel keeps its cause bits (4, 8, 16); a
filled one has bit 1 set and bit 2 cleared.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.special import fdtr, fdtri, ndtri

from cdma_lidar.errors import out_of_range
from cdma_lidar.firmware_model.snr import snr_xc_db
from cdma_lidar.host.frame import SUMSQ_UNKNOWN, FrameData
from cdma_lidar.host.settings import DEFAULT_SNR_THRESHOLD_DB
from cdma_lidar.host.uid_filter import ForeignReturns, find_foreign, select_own
from cdma_lidar.units import SPEED_OF_LIGHT_M_S

__all__ = [
    "DEFAULT_SNR_THRESHOLD_DB",
    "DETECTION_AT_CEILING",
    "FALSE_ALARM_RATE",
    "FLAG_FOREIGN",
    "FLAG_GHOST",
    "FLAG_INTERPOLATED",
    "FLAG_REJECTED",
    "FLAG_SATURATED",
    "METHODS",
    "RangeImage",
    "RangingConfig",
    "default_snr_threshold_db",
    "estimate_ranges",
    "false_alarm_rate",
    "fill_columns",
    "ghost_windows_from_image",
    "in_windows",
    "lag_to_range_m",
    "mai_ceiling_db",
    "neighbour_support",
    "precision_eq27_m",
    "sample_range_m",
    "subsample_delta",
]

log = logging.getLogger(__name__)

FLAG_INTERPOLATED = 1
FLAG_REJECTED = 2
FLAG_FOREIGN = 4
FLAG_GHOST = 8
#: The record's ``saturated`` field: the strongest peak's out word at a rail (lag may be early).
FLAG_SATURATED = 16
METHODS = ("none", "parabolic", "triangle")
#: Probability that a pixel with no echo passes the default threshold (per pixel).
FALSE_ALARM_RATE = 1e-3
#: Probability that an echo at the multiple-access ceiling passes the default threshold.
DETECTION_AT_CEILING = 0.99


def _gate_lags(gate_len: int, samples_per_chip: int, peak_exclude: int) -> tuple[int, float]:
    """(lags the peak is the largest of, independent lags of the noise floor): every gate
    lag is a trial (an upper bound: lags within a chip are correlated, 1 - 1/S), while the
    floor's variance has only one independent value per chip."""
    return gate_len, max(gate_len - 2 * peak_exclude - 1, samples_per_chip) / samples_per_chip


def false_alarm_rate(threshold_db: float, gate_len: int, samples_per_chip: int,
                     peak_exclude: int = 8, uid_bits: int = 1) -> float:
    """Probability (per pixel) that a gate holding no echo reports SNR_XC >= ``threshold_db``.

    Model: the gate's lags hold zero-mean Gaussian noise (receiver noise plus the other
    channels' multiple-access interference, which is Gaussian by the central limit theorem
    at large K and only rescales the floor, so it cancels in the ratio). The peak is the
    largest ``x^2`` of ``G = gate_len`` lags (taken as independent trials: an upper bound),
    and the floor's variance is estimated from ``nu = (gate_len - 2 W - 1) / S``
    independent values (W = ``peak_exclude``, one per chip), so each lag's
    ``peak^2 / sigma^2`` is F(1, nu) distributed and::

        P_fa = 2^-n (1 - (1 - Q_F(1, nu)(10^(threshold_db / 10)))^G)

    (``Q_F``: the F distribution's upper tail); the factor ``2^-n`` is the chance that a
    noise peak's n period signs (``uid_bits``) read as our UID, which the host requires
    (with n = 1: a positive peak). At paper-massive's configuration this
    matches the receiver's own noise-only gates (tests/host/test_ranging.py).
    """
    g, nu = _gate_lags(gate_len, samples_per_chip, peak_exclude)
    x = 10.0 ** (threshold_db / 10.0)
    tail = 1.0 - float(fdtr(1.0, nu, x))
    largest = -math.expm1(g * math.log1p(-tail)) if tail < 1 else 1.0
    return float(largest / 2**uid_bits)


def mai_ceiling_db(channels: int, code_length: int) -> float:
    """The SNR_XC (dB) multiple-access interference alone allows an echo, whatever the power.

    ``10 log10(N / ((2/3) (K - 1)))``: each of the K - 1 other channels' echoes (as strong as
    ours) adds a Gold cross-correlation of variance about N chips^2, two-thirds of it on
    average over a sub-chip delay (linear between chip lags); the peak is N. S and R scale
    both alike and cancel. ``inf`` for one channel.
    """
    if channels <= 1:
        return math.inf
    return 10.0 * math.log10(code_length / (2.0 / 3.0 * (channels - 1)))


def default_snr_threshold_db(channels: int, code_length: int, samples_per_chip: int,
                             gate_len: int, peak_exclude: int = 8, uid_bits: int = 1) -> float:
    """The host's default SNR_XC threshold (dB) for a configuration.

    ``min(16 dB, max(T_fa, T_mai))``, where

    * ``T_fa``: the level a gate with no echo exceeds with probability
      :data:`FALSE_ALARM_RATE` (:func:`false_alarm_rate`: the largest of ``gate_len``
      lags, each F(1, nu), read as our UID), so noise never passes more often;
    * ``T_mai = 10 log10((sqrt(rho) - z)^2)``, with ``rho`` the multiple-access ceiling
      (:func:`mai_ceiling_db`, linear) and ``z`` the normal quantile of
      :data:`DETECTION_AT_CEILING`: the level an echo limited by the other channels alone
      clears with that probability (its peak is ``sqrt(rho)`` floor deviations plus one
      Gaussian deviation).

    16 dB (:data:`DEFAULT_SNR_THRESHOLD_DB`) stays wherever the interference leaves room
    above it (``rho`` >= 18.7 dB: every preset of 40 channels at degree 11, ceiling
    19.0 dB); paper-massive (K = 1,200, N = 32,767, S = 2, 128 lags), whose ceiling is
    16.1 dB, gets ``T_fa`` = 13.5 dB. All values in dB.
    """
    rho = 10.0 ** (mai_ceiling_db(channels, code_length) / 10.0)
    z = float(ndtri(DETECTION_AT_CEILING))
    t_mai = 10.0 * math.log10(max(math.sqrt(rho) - z, 1e-9) ** 2) if math.isfinite(rho) \
        else math.inf
    g, nu = _gate_lags(gate_len, samples_per_chip, peak_exclude)
    largest = min(FALSE_ALARM_RATE * 2**uid_bits, 0.5)   # of G lags, before the UID test
    per_lag = -math.expm1(math.log1p(-largest) / g)
    t_fa = 10.0 * math.log10(float(fdtri(1.0, nu, 1.0 - per_lag)))
    return min(DEFAULT_SNR_THRESHOLD_DB, max(t_fa, t_mai))



def sample_range_m(samples_per_chip: int, chip_rate_hz: float) -> float:
    """Range spanned by one lag sample (m): ``c / (2 S f_chip)``."""
    if samples_per_chip < 1:
        raise out_of_range("samples_per_chip", "at least 1", samples_per_chip)
    if not (np.isfinite(chip_rate_hz) and chip_rate_hz > 0):
        raise out_of_range("chip_rate_hz", "finite and positive (chips/s)", chip_rate_hz)
    return SPEED_OF_LIGHT_M_S / (2.0 * samples_per_chip * chip_rate_hz)


def lag_to_range_m(lag: ArrayLike, samples_per_chip: int, chip_rate_hz: float,
                   offset_m: float = 0.0) -> NDArray[np.float64]:
    """Range (m) of a (fractional) lag in samples, minus the calibration offset (m), eq. 2."""
    return (np.asarray(lag, dtype=np.float64) * sample_range_m(samples_per_chip, chip_rate_hz)
            - offset_m)


def subsample_delta(peak: ArrayLike, neighbours: ArrayLike,
                    method: str = "parabolic") -> NDArray[np.float64]:
    """Fractional lag correction (samples, in [-0.5, 0.5]) from a peak and its neighbours.

    ``peak`` (...,) and ``neighbours`` (..., 2) hold the outputs at lag, lag-1, lag+1.
    Where the three values do not form a maximum (flat or degenerate), the correction is 0.
    """
    if method not in METHODS:
        raise out_of_range("method", f"one of {METHODS}", method)
    y0 = np.asarray(peak, dtype=np.float64)
    nb = np.asarray(neighbours, dtype=np.float64)
    if method == "none":
        return np.zeros_like(y0)
    sign = np.where(y0 < 0, -1.0, 1.0)
    y0 = y0 * sign
    ym = nb[..., 0] * sign
    yp = nb[..., 1] * sign
    with np.errstate(divide="ignore", invalid="ignore"):
        if method == "parabolic":
            den = ym - 2.0 * y0 + yp
            delta = np.where(den < 0, 0.5 * (ym - yp) / den, 0.0)
        else:
            den = y0 - np.minimum(ym, yp)
            delta = np.where(den > 0, 0.5 * (yp - ym) / den, 0.0)
    delta = np.where(np.isfinite(delta), delta, 0.0)
    return np.clip(delta, -0.5, 0.5)


def precision_eq27_m(chip_rate_hz: float, samples_per_symbol: int, *,
                     snr: ArrayLike | None = None,
                     snr_xc_db: ArrayLike | None = None) -> NDArray[np.float64]:
    """Ranging precision sigma (m) of eq. 27 from the per-sample SNR or from SNR_XC (dB).

    ``sigma = sqrt(6/N_s) / (2 pi) * dR / sqrt(SNR)`` with ``dR = c / (2 f_chip)`` and
    ``N_s`` samples per symbol; with SNR_XC given, ``SNR = SNR_XC / N_s``.
    """
    if samples_per_symbol < 1:
        raise out_of_range("samples_per_symbol", "at least 1", samples_per_symbol)
    if (snr is None) == (snr_xc_db is None):
        raise out_of_range("snr/snr_xc_db", "exactly one of the two given", (snr, snr_xc_db))
    d_r = SPEED_OF_LIGHT_M_S / (2.0 * chip_rate_hz)
    if snr is None:
        snr = 10.0 ** (np.asarray(snr_xc_db, dtype=np.float64) / 10.0) / samples_per_symbol
    snr = np.asarray(snr, dtype=np.float64)
    return np.sqrt(6.0 / samples_per_symbol) / (2.0 * np.pi) * d_r / np.sqrt(snr)


def in_windows(lag: ArrayLike, windows: tuple[tuple[int, int], ...],
               samples_per_symbol: int) -> NDArray[np.bool_]:
    """True where ``lag`` (samples) falls in one of the ``(start, length)`` windows (mod N_s)."""
    lag = np.asarray(lag, dtype=np.int64)
    hit = np.zeros(lag.shape, dtype=bool)
    for start, length in windows:
        hit |= np.mod(lag - int(start), samples_per_symbol) < int(length)
    return hit


def neighbour_support(lag: NDArray, strong: NDArray, tol_samples: float) -> NDArray[np.int64]:
    """How many of each pixel's 8 grid neighbours are ``strong`` with a lag within ``tol``.

    ``lag`` (K, C) in samples (float), ``strong`` (K, C) bool. Neighbours outside the
    grid do not count. A real surface lights several adjacent pixels at nearly the same
    lag; a noise peak that crossed the threshold stands alone at a random lag.
    """
    k, c = lag.shape
    pad_lag = np.full((k + 2, c + 2), np.nan)
    pad_lag[1:-1, 1:-1] = np.where(strong, lag, np.nan)
    count = np.zeros((k, c), dtype=np.int64)
    for dk in (-1, 0, 1):
        for dc in (-1, 0, 1):
            if dk == 0 and dc == 0:
                continue
            other = pad_lag[1 + dk:1 + dk + k, 1 + dc:1 + dc + c]
            with np.errstate(invalid="ignore"):
                count += np.abs(other - lag) <= tol_samples
    return count


def ghost_windows_from_image(image: RangeImage, margin: int = 2
                             ) -> tuple[tuple[int, int], ...]:
    """Ghost map from a scan of an empty field (beam trap, open sky): lag windows (samples).

    Grating ghosts (Note 5) carry the channel's own code from a fixed distance, so with
    nothing in the field every detection that survives the threshold and the isolation
    check is a ghost. Their integer lags, widened by ``margin`` samples on each side,
    are merged into ``(start, length)`` windows for :attr:`RangingConfig.ghost_windows`.
    """
    ns = image.config.samples_per_symbol
    lags = np.unique(np.rint(image.lag[image.valid]).astype(np.int64) % ns)
    if lags.size == 0:
        return ()
    lo, hi = lags - margin, lags + margin
    windows: list[list[int]] = []
    for a, b in zip(lo.tolist(), hi.tolist(), strict=True):
        if windows and a <= windows[-1][1] + 1:
            windows[-1][1] = max(windows[-1][1], b)
        else:
            windows.append([a, b])
    return tuple((int(a % ns), int(b - a + 1)) for a, b in windows)


def fill_columns(range_m: NDArray, ok: NDArray, max_gap: int) -> tuple[NDArray, NDArray]:
    """Fill runs of up to ``max_gap`` not-ok channels between two ok ones, per column.

    Linear interpolation over the channel index (axis 0) of each column. Returns
    ``(filled_range_m, filled_mask)``; runs touching the first or last channel, or
    longer than ``max_gap``, stay unfilled.
    """
    k, c = range_m.shape
    out = np.array(range_m, dtype=np.float64)
    filled = np.zeros((k, c), dtype=bool)
    if max_gap < 1:
        return out, filled
    idx = np.arange(k)
    # Previous and next ok channel for every pixel (vectorised over columns).
    prev = np.where(ok, idx[:, None], -1)
    prev = np.maximum.accumulate(prev, axis=0)
    nxt = np.where(ok, idx[:, None], k)
    nxt = np.minimum.accumulate(nxt[::-1], axis=0)[::-1]
    gap = nxt - prev - 1
    can = ~ok & (prev >= 0) & (nxt < k) & (gap <= max_gap)
    if np.any(can):
        cols = np.broadcast_to(np.arange(c)[None, :], (k, c))
        p, n, ch, cl = prev[can], nxt[can], idx[:, None].repeat(c, 1)[can], cols[can]
        rp, rn = out[p, cl], out[n, cl]
        w = (ch - p) / (n - p)
        out[can] = rp + w * (rn - rp)
        filled[can] = True
    return out, filled


@dataclass(frozen=True)
class RangingConfig:
    """How a frame's peaks become ranges.

    Attributes:
        samples_per_chip: S (samples/chip).
        chip_rate_hz: chip rate (chips/s).
        code_length: N (chips per period); ``N * S`` samples make one symbol period.
        snr_threshold_db: pixels below this SNR_XC (dB) are rejected.
        method: sub-sample lag refinement, one of ``none``, ``parabolic``, ``triangle``.
        offset_m: calibration offset subtracted from every range (m).
        interpolate: fill rejected pixels from their column neighbours (flag 1).
        max_gap: longest run of rejected channels that is filled.
        ghost_windows: ``(start, length)`` lag windows (samples) of known grating ghosts.
        uid: our UID (bit p = period p inverted).
        min_support: a pixel above the threshold is kept only if at least this many of
            its 8 neighbours are also above it with a lag within ``support_tol``
            (isolated noise peaks are rejected); 0 turns the check off.
        support_tol: lag tolerance (samples) for a neighbour to count as support.
        foreign_threshold_db: other users' peaks are reported from this SNR_XC (dB) on,
            if they repeat in an adjacent column (their UID is read from all n periods,
            so a weaker peak still names its user).
    """

    samples_per_chip: int = 4
    chip_rate_hz: float = 62.5e6
    code_length: int = 2047
    snr_threshold_db: float = DEFAULT_SNR_THRESHOLD_DB
    method: str = "triangle"
    offset_m: float = 0.0
    interpolate: bool = False
    max_gap: int = 2
    ghost_windows: tuple[tuple[int, int], ...] = ()
    uid: int = 0
    min_support: int = 1
    support_tol: float = 1.5
    foreign_threshold_db: float = 12.0

    def __post_init__(self) -> None:
        sample_range_m(self.samples_per_chip, self.chip_rate_hz)  # checks both
        if self.code_length < 1:
            raise out_of_range("code_length", "at least 1 chip", self.code_length)
        if self.method not in METHODS:
            raise out_of_range("method", f"one of {METHODS}", self.method)
        if not np.isfinite(self.snr_threshold_db):
            raise out_of_range("snr_threshold_db", "a finite number (dB)", self.snr_threshold_db)
        if not np.isfinite(self.offset_m):
            raise out_of_range("offset_m", "a finite number (m)", self.offset_m)
        if self.max_gap < 0:
            raise out_of_range("max_gap", "0 or more channels", self.max_gap)
        if not 0 <= self.min_support <= 8:
            raise out_of_range("min_support", "from 0 to 8 neighbours", self.min_support)
        if not (np.isfinite(self.support_tol) and self.support_tol >= 0):
            raise out_of_range("support_tol", ">= 0 samples", self.support_tol)

    @property
    def samples_per_symbol(self) -> int:
        """N_s = N * S samples in one code period."""
        return self.code_length * self.samples_per_chip


@dataclass
class RangeImage:
    """Ranges of one frame, (K, C) arrays, and the other users' returns seen in it.

    ``range_m`` is NaN where a pixel has no range (rejected and not filled, or its
    column never arrived); ``lag`` is the refined lag (samples) of our own peak.
    """

    range_m: NDArray[np.float64]
    lag: NDArray[np.float64]
    snr_xc_db: NDArray[np.float64]
    peak: NDArray[np.int64]
    flags: NDArray[np.uint8]
    foreign: ForeignReturns
    config: RangingConfig = field(repr=False, default_factory=RangingConfig)

    @property
    def valid(self) -> NDArray[np.bool_]:
        """Pixels measured and accepted (flags == 0)."""
        return self.flags == 0


def estimate_ranges(frame: FrameData, config: RangingConfig) -> RangeImage:
    """Turn one frame of receiver results into a :class:`RangeImage`.

    Steps, vectorised over all pixels: pick our own return (UID), flag ghosts, compute
    SNR_XC with the shared function, refine the lag, convert to range, threshold, and
    optionally fill rejected pixels along each column.
    """

    ns = config.samples_per_symbol

    def in_ghost(lags: NDArray[np.int64]) -> NDArray[np.bool_]:
        return in_windows(lags, config.ghost_windows, ns)

    own = select_own(frame, config.uid, in_ghost if config.ghost_windows else None)
    # a noise floor past the host's word (SUMSQ_UNKNOWN) gives no SNR: rejected, flagged 16
    unknown_floor = frame.noise_sumsq >= SUMSQ_UNKNOWN
    snr = np.asarray(snr_xc_db(own.peak, frame.noise_count, frame.noise_sum,
                               frame.noise_sumsq), dtype=np.float64)
    snr[unknown_floor] = np.nan
    delta = subsample_delta(own.peak, own.neighbours, config.method)
    delta = np.where(own.has_neighbours, delta, 0.0)
    lag = own.lag.astype(np.float64) + delta
    rng = lag_to_range_m(lag, config.samples_per_chip, config.chip_rate_hz, config.offset_m)
    ghost = own.ghost
    done = np.broadcast_to(frame.done[None, :], frame.shape)
    ours = own.source >= 0
    # lag -1: the device found no eligible lag (all ghosted, or fewer peaks than asked)
    ok = done & ours & (own.lag >= 0) & ~ghost & (snr >= config.snr_threshold_db)
    if config.min_support > 0:
        ok &= neighbour_support(lag, ok, config.support_tol) >= config.min_support
    flags = np.where(ok, 0, FLAG_REJECTED).astype(np.uint8)
    flags |= np.where(own.foreign, FLAG_FOREIGN, 0).astype(np.uint8)
    flags |= np.where(ghost, FLAG_GHOST, 0).astype(np.uint8)
    flags |= np.where(frame.saturated | unknown_floor, FLAG_SATURATED, 0).astype(np.uint8)
    out_range = np.where(ok, rng, np.nan)
    if config.interpolate:
        out_range, filled = fill_columns(out_range, ok, config.max_gap)
        filled &= done
        flags = np.where(filled, (flags & ~np.uint8(FLAG_REJECTED)) | FLAG_INTERPOLATED,
                         flags).astype(np.uint8)
        out_range = np.where(ok | filled, out_range, np.nan)
    foreign = find_foreign(frame, config.uid, config.foreign_threshold_db,
                           column_support=config.min_support > 0,
                           tol_samples=config.support_tol)
    log.debug("frame %d: %d valid, %d rejected, %d foreign returns", frame.frame,
              int(np.count_nonzero(flags == 0)),
              int(np.count_nonzero(flags & FLAG_REJECTED)), len(foreign))
    return RangeImage(range_m=out_range, lag=lag, snr_xc_db=snr, peak=own.peak,
                      flags=flags, foreign=foreign, config=config)
