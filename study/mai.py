"""Asynchronous multi-channel signals for the capacity studies (Supplementary Notes 8 and 9).

The paper's Fig. 11 simulation: K channels of equal power, each a bipolar NRZ Gold code
(+1 for chip bit 0) of N chips sampled S = 50 times per chip, delayed by a random whole
number of samples (so the channels are asynchronous at 1/S of a chip), summed on one
detector; optionally white Gaussian noise per sample. This module builds those ADC samples
fast and gives the receive chain's configuration for them; the studies then run the
samples through :class:`cdma_lidar.firmware_model.receiver.FastReceiver` (the whole chain,
bit-exact) and count how often the peak lag misses the true delay.

Also here: the *standard Gaussian approximation* (SGA) of the same experiment, the
analytical shortcut the studies offer as ``fidelity=sga`` next to the simulation.

Fast synthesis. For channel k with delay ``d_k = S m_k + f_k`` samples (0 <= f_k < S),
sample ``s`` (0..S-1) of chip n is ``c_k[n - m_k - (s < f_k)]``. With
``A_f[n] = sum_{k: f_k = f} c_k[n - m_k]`` (chip domain, O(K N)) and the running sum
``P_s = sum_{f <= s} A_f``, the sum over channels is::

    x[n, s] = P_s[n] + (T - P_s)[n - 1],      T = sum_f A_f

so a trial costs O(K N + S N) instead of O(K N S). :func:`direct_signal` is the literal
sum (tests compare the two).
"""

from __future__ import annotations

import functools
import logging
import time
from collections.abc import Iterable

import numpy as np
from numpy.typing import NDArray

from cdma_lidar.errors import out_of_range
from cdma_lidar.firmware_model.adc import adc_limits
from cdma_lidar.firmware_model.gold import bipolar, gold_codes
from cdma_lidar.firmware_model.pairs import preferred_pairs
from cdma_lidar.firmware_model.receiver import ReceiverConfig, fast_frame
from cdma_lidar.study.simulate import smallest_out_shift

__all__ = [
    "DETECTORS",
    "bipolar",
    "code_bits",
    "direct_signal",
    "gross_error",
    "mai_config",
    "mai_signal",
    "run_trial_blocks",
    "run_trials_detectors",
    "sga_error_rate",
    "snr_per_sample_eq30",
    "snr_ss_eq43",
]

log = logging.getLogger(__name__)

#: Peak detectors: ``abs`` takes the largest |corr| (the receiver's rule: a UID bit of 1
#: flips the code, so the peak may be negative); ``signed`` the largest corr, eq. 9's
#: argmax of the cross-correlation (the paper's Fig. 11 simulation, no UID).
DETECTORS = ("abs", "signed")


@functools.lru_cache(maxsize=4)
def code_bits(degree: int, channels: int) -> NDArray[np.uint8]:
    """Gold members 0..channels-1 of the first preferred pair of ``degree``: (K, N) chip bits.

    Kept (read-only) for the next chunk of the same point: 76 ms at degree 15, K = 1200.
    """
    u, v = preferred_pairs(degree)[0]
    bits = gold_codes(u, v, range(channels), field="channels")
    bits.flags.writeable = False
    return bits


def mai_signal(bip: NDArray[np.int8], delays: NDArray[np.int64], s: int) -> NDArray[np.int32]:
    """Sum of the K codes ``bip`` (K, N), channel k delayed by ``delays[k]`` samples.

    Returns the N*S samples of one period (int32, each channel of amplitude 1); see the
    module docstring for the method.
    """
    k, n = bip.shape
    d = np.asarray(delays, dtype=np.int64) % (n * s)
    m, f = np.divmod(d, s)
    a = np.zeros((s, n), dtype=np.int32)
    # group the channels by sub-chip phase f; channel ch rolled by m in the chip domain
    # (a[f, j] += bip[ch, j - m]) as two slice adds, without a rolled copy
    for ch in range(k):
        row, mm = a[f[ch]], int(m[ch])
        row[mm:] += bip[ch, :n - mm]
        row[:mm] += bip[ch, n - mm:]
    p = np.cumsum(a, axis=0)                      # P_s, (S, N)
    total = p[-1]
    x = p + np.roll(total[None, :] - p, 1, axis=1)  # x[s, n] = P_s[n] + (T - P_s)[n - 1]
    return np.ascontiguousarray(x.T).reshape(-1)


def direct_signal(bip: NDArray[np.int8], delays: NDArray[np.int64], s: int) -> NDArray[np.int32]:
    """The literal sum of the delayed, S-times repeated codes (slow; the tests' reference)."""
    out = np.zeros(bip.shape[1] * s, dtype=np.int32)
    for ch in range(bip.shape[0]):
        out += np.roll(np.repeat(bip[ch].astype(np.int32), s), int(delays[ch]))
    return out


def mai_config(n_chips: int, s: int, *, adc_bits: int = 16, averages: int = 1) -> ReceiverConfig:
    """Receive chain for these signals: gate over the whole period, +-1 chip excluded.

    The gate covers every lag (the paper's peak search over the whole correlation); the
    noise floor is every lag more than one chip (S samples) from the peak; the output
    shift is the smallest whose noise accumulator fits.
    """
    ns = n_chips * s
    cfg = ReceiverConfig(adc_bits=adc_bits, samples_per_chip=s, averages=averages,
                         gate_start=0, gate_len=ns, peak_exclude=s, peaks=1)
    return smallest_out_shift(cfg, n_chips)


def gross_error(lag: NDArray[np.int64], true_lag: NDArray[np.int64], period: int,
                s: int) -> NDArray[np.bool_]:
    """A ranging error: the peak lag is more than half a chip (S/2 samples) from the truth.

    Circular distance (lags are modulo the period N*S). Within half a chip the peak is on
    the true correlation triangle and sub-sample refinement recovers the range; beyond it
    the receiver has locked on interference or noise.
    """
    diff = (np.asarray(lag, dtype=np.int64) - np.asarray(true_lag, dtype=np.int64)) % period
    dist = np.minimum(diff, period - diff)
    return dist > s // 2


def snr_per_sample_eq30(channels: int, noise_rms: float, amplitude: float = 1.0) -> float:
    """Eq. 30: P_s / (sigma^2 + sum_{i != s} P_i) for K equal channels of amplitude A (linear)."""
    return amplitude**2 / (noise_rms**2 + (channels - 1) * amplitude**2)


def snr_ss_eq43(n_chips: int, channels: int, noise_rms: float = 0.0, amplitude: float = 1.0,
                samples_per_chip: int = 1, averages: int = 1) -> float:
    """Eq. 43 (linear): N P_s / (sigma_eta^2 + 2/3 sum P_i), per chip.

    White noise of per-sample rms ``noise_rms`` is averaged over the S samples of a chip
    and the R repetitions, so per chip it is sigma^2 / (S R); the K-1 other channels count
    2/3 of their power (eq. 42).
    """
    noise = noise_rms**2 / (samples_per_chip * averages)
    return n_chips * amplitude**2 / (noise + 2.0 / 3.0 * (channels - 1) * amplitude**2)


def sga_error_rate(snr_ss: float, competitors: int, points: int = 4001,
                   detector: str = "abs") -> float:
    """Probability that the peak search misses, in the standard Gaussian approximation.

    The correlation at the true lag is Gaussian with mean sqrt(SNR_SS) and unit variance;
    ``competitors`` independent lags (one per chip outside the peak's +-1 chip: the
    correlation is smooth within a chip) are zero-mean, unit variance. The receiver picks
    the largest |out| (``detector="abs"``), so it is right with probability
    ``integral phi(x - mu) (2 Phi(|x|) - 1)^M dx`` (numerical, on a grid); eq. 9's signed
    maximum (``"signed"``) with ``integral phi(x - mu) Phi(x)^M dx``.
    """
    from scipy.integrate import trapezoid  # deferred: scipy costs 0.3 s at start-up
    from scipy.special import ndtr  # deferred (as above)

    mu = float(np.sqrt(max(snr_ss, 0.0)))
    x = np.linspace(mu - 10.0, mu + 10.0, points)
    pdf = np.exp(-0.5 * (x - mu) ** 2) / np.sqrt(2.0 * np.pi)
    if detector not in DETECTORS:
        raise out_of_range("detector", " or ".join(DETECTORS), detector)
    inside = np.clip(2.0 * ndtr(np.abs(x)) - 1.0 if detector == "abs" else ndtr(x), 0.0, 1.0)
    with np.errstate(divide="ignore"):
        log_in = competitors * np.log(inside)
    correct = float(trapezoid(pdf * np.exp(log_in), x))  # scipy: numpy 1.26 lacks trapezoid
    return float(min(max(1.0 - correct, 0.0), 1.0))


def run_trials_detectors(bits: NDArray[np.uint8], s: int, trials: int, rng: np.random.Generator,
                         *, noise_rms: float = 0.0, amplitude: int = 1, averages: int = 1,
                         adc_bits: int = 16, batch: int = 8
                         ) -> tuple[dict[str, NDArray[np.bool_]], NDArray[np.float64]]:
    """``trials`` random-delay trials through the whole receive chain; channel 0 is ranged.

    ``bits`` (K, N): every channel's code. Each trial draws K delays uniform over the
    period (whole samples), sums the K channels at ``amplitude`` LSB each, adds white
    Gaussian noise of ``noise_rms`` LSB per sample (independent in each of the R
    ``averages``), quantises (round half up, clip to ``adc_bits``) and runs the column
    through :class:`~cdma_lidar.firmware_model.receiver.FastReceiver` (``method="auto"``,
    by :func:`~cdma_lidar.firmware_model.receiver.fast_frame`, which keeps the prepared
    receiver for the next call) correlating with channel 0's code. The same trials
    are judged with each of :data:`DETECTORS`: ``abs`` is the receiver's own peak
    (largest |out|), ``signed`` the largest ``out`` over the gate (the whole period, so
    gate index = lag; ties to the lowest lag as the receiver's). Returns ({detector:
    gross error per trial}, SNR_XC dB per trial as the receiver reports it).
    """
    bip = bipolar(bits)
    k, n = bip.shape
    ns = n * s
    cfg = mai_config(n, s, adc_bits=adc_bits, averages=averages)
    lo, hi = adc_limits(adc_bits)
    errors = {d: np.zeros(trials, dtype=bool) for d in DETECTORS}
    snr = np.zeros(trials, dtype=np.float64)
    for start in range(0, trials, batch):
        count = min(batch, trials - start)
        cols = np.empty((count, averages * ns), dtype=np.int16)
        truth = np.empty(count, dtype=np.int64)
        for c in range(count):
            delays = rng.integers(0, ns, k)
            truth[c] = delays[0]
            clean = amplitude * mai_signal(bip, delays, s)
            if noise_rms > 0:
                noisy = clean[None, :] + rng.normal(0.0, noise_rms, (averages, ns))
                cols[c] = np.clip(np.floor(noisy + 0.5), lo, hi).reshape(-1)
            else:
                cols[c] = np.tile(np.clip(clean, lo, hi), averages)
        outs = fast_frame(cfg, bits[:1], cols)
        lags = np.array([int(o.peak_lag[0]) for o in outs])
        signed = np.array([int(np.argmax(o.corr[0])) for o in outs])  # gate_start 0: j = lag
        errors["abs"][start:start + count] = gross_error(lags, truth, ns, s)
        errors["signed"][start:start + count] = gross_error(signed, truth, ns, s)
        snr[start:start + count] = [float(o.snr_db()[0]) for o in outs]
    return errors, snr


def run_trial_blocks(bits: NDArray[np.uint8] | None, s: int,
                     blocks: Iterable[tuple[np.random.Generator, int]],
                     **kw: float | int) -> dict[str, list]:
    """:func:`run_trials_detectors` over a study chunk's seeded blocks (``chunk.blocks()``).

    Returns per-trial lists: ``error`` (the
    receiver's |corr|), ``error_signed`` (eq. 9's signed maximum), ``snr_xc_db`` and
    ``seconds`` (each block's time shared equally by its trials). ``kw``: the noise,
    amplitude and averages of :func:`run_trials_detectors`.
    """
    out: dict[str, list] = {"error": [], "error_signed": [], "snr_xc_db": [], "seconds": []}
    for rng, count in blocks:
        t0 = time.perf_counter()
        errors, snr = run_trials_detectors(bits, s, count, rng, **kw)  # type: ignore[arg-type]
        out["error"] += errors["abs"].tolist()
        out["error_signed"] += errors["signed"].tolist()
        out["snr_xc_db"] += snr.tolist()
        out["seconds"] += [(time.perf_counter() - t0) / count] * count
    return out
