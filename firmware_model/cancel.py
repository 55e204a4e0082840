"""Parallel interference cancellation (PIC): the receive chain again on the accumulators
minus the echoes the previous pass found.

With ``cancel_rounds`` > 0 (:class:`~cdma_lidar.firmware_model.receiver_config.ReceiverConfig`)
each round takes the previous pass's output and, per channel k whose first peak is found,
matches the UID and has SNR_XC >= ``cancel_snr_q8`` / 256 (integer test, :meth:`Canceller.pick`):

* its echo amplitude per period, in accumulator codes (R ADC codes per sample),
  ``b_k = sat_acc(floor(peak_k 2^out_shift / (n N S) + 1/2))``;
* its lag l_k = peak_lag_k (samples), so its rebuilt echo in period p is
  ``(-1)^bit_p(uid) b_k ref_k[(i - l_k) mod NS]`` (the device's own reference chips);
* the residual
  ``res[p][i] = sat_acc(acc[p][i] - (-1)^bit_p(uid) sum_k b_k ref_k[(i - l_k) mod NS])``,
  saturated to the accumulator's range R * [ADC min, ADC max] (so every word width of the
  chain holds);
* the chain on ``res``, with each subtracted channel's own echo added back where it is
  correlated with its own code: ``raw_k[l] += n b_k A_k(l - l_k)`` and, per period at the
  peaks, ``(-1)^bit_p(uid) b_k A_k(lag - l_k)``, where
  ``A_k(m) = sum_i ref_k[i] ref_k[(i + m) mod NS]`` is the periodic autocorrelation of
  the channel's reference (an exact integer table of the offsets -G..G,
  :func:`autocorrelation_table`).

So each channel is ranged again with every other found echo removed (Shen, Lim and Zhou,
"Identity-enabled CDMA LiDAR for massively parallel ranging with a single-element
receiver", bound the single correlation's multiple-access interference; this stage is
not in the paper). Integer throughout; the reference model
(:mod:`cdma_lidar.firmware_model.reference`) writes the same sums literally.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from cdma_lidar.firmware_model.adc import adc_limits
from cdma_lidar.firmware_model.output import ReceiverOutput
from cdma_lidar.firmware_model.receiver_config import ReceiverConfig

__all__ = ["Canceller", "Subtraction", "autocorrelation_table", "subtracts"]

#: Channels per block of FFTs in :func:`autocorrelation_table`.
_FFT_BLOCK = 64


def subtracts(cfg: ReceiverConfig, peak: int, count: int, total: int, sumsq: int) -> bool:
    """Whether a found, UID-matched peak is subtracted: SNR_XC >= cancel_snr_q8 / 256.

    SNR_XC = peak^2 / sigma^2 with sigma^2 = max((count sumsq - total^2) / count^2, 1/12)
    (:mod:`cdma_lidar.firmware_model.snr`), compared exactly in Python integers:
    ``256 peak^2 count^2 >= q8 var_num``, or ``256 * 12 peak^2 >= q8`` on the 1/12 floor.
    """
    q8, p2 = cfg.cancel_snr_q8, peak * peak
    var_num = count * sumsq - total * total
    if count == 0 or 12 * var_num < count * count:
        return 256 * 12 * p2 >= q8
    return 256 * p2 * count * count >= q8 * var_num


def amplitude(cfg: ReceiverConfig, peak: int, ns: int) -> int:
    """b = sat_acc(floor(peak 2^out_shift / (n NS) + 1/2)): the echo's amplitude per
    period in accumulator codes, from its ``out`` peak (LSB)."""
    top = cfg.averages << (cfg.adc_bits - 1)  # R 2^(b-1): the accumulators' range
    d = cfg.uid_bits * ns
    b = (2 * (peak << cfg.out_shift) + d) // (2 * d)
    return min(max(b, -top), top - cfg.averages)


def autocorrelation_table(bip: NDArray[np.int8], s: int, g: int) -> NDArray[np.int64]:
    """(K, 2g + 1) int64: ``A_k(m) = sum_i ref_k[i] ref_k[(i + m) mod NS]`` for m = -g..g
    (samples), ref_k[i] = bip[k, i // S].

    With m = q S + r (0 <= r < S), A_k(m) = (S - r) C_k(q) + r C_k(q + 1), where
    C_k(q) = sum_j c_k[j] c_k[(j + q) mod N] is the chips' periodic autocorrelation. C
    comes from one FFT per channel: every value is an integer of magnitude <= N <= 2^20,
    and a float64 FFT's error is below N log2(N) 2^-52 N < 2^-7, so rounding is exact; the
    distance to the nearest integer is checked anyway.
    """
    k, n = bip.shape
    m = np.arange(-g, g + 1)
    q, r = np.divmod(m, s)
    need = np.unique(np.concatenate([q, q + 1]) % n)
    chips = np.empty((k, need.size), dtype=np.int64)
    for k0 in range(0, k, _FFT_BLOCK):
        f = np.fft.rfft(bip[k0:k0 + _FFT_BLOCK].astype(np.float64), axis=1)
        c = np.fft.irfft(f * np.conj(f), n=n, axis=1)[:, need]
        exact = np.rint(c)
        if np.max(np.abs(c - exact), initial=0.0) >= 0.25:  # never: the bound above
            raise RuntimeError("chip autocorrelation not exact in float64")
        chips[k0:k0 + _FFT_BLOCK] = exact.astype(np.int64)
    at = np.searchsorted(need, q % n), np.searchsorted(need, (q + 1) % n)
    return (s - r) * chips[:, at[0]] + r * chips[:, at[1]]


@dataclass(frozen=True)
class Subtraction:
    """The echoes a cancellation round removes from C columns.

    ``b`` (C, K) int64 amplitude per period in accumulator codes (0: not subtracted);
    ``jp`` (C, K) int64 gate index of each echo's lag (its previous peak; 0 where b = 0).
    """

    b: NDArray[np.int64]
    jp: NDArray[np.int64]

    def rows(self, c0: int, c1: int) -> Subtraction:
        """The columns c0..c1-1."""
        return Subtraction(self.b[c0:c1], self.jp[c0:c1])


class Canceller:
    """The cancellation stage of one configuration and code set (vectorised over columns).

    ``bip`` (K, N) int8 are the codes as +-1; ``lags`` (G + 2,) the lags, in samples, of
    the chain's ``out[..., m]`` (gate_start - 1 + m mod NS); ``despread`` (n,) int64
    (-1)^bit_p(uid) per period (the chain's :class:`~.peaks.PeakSearch` holds both).
    """

    def __init__(self, cfg: ReceiverConfig, bip: NDArray[np.int8], lags: NDArray[np.int64],
                 despread: NDArray[np.int64]) -> None:
        self.cfg, self.bip = cfg, bip
        self.n_chips = bip.shape[1]
        self.ns = self.n_chips * cfg.samples_per_chip
        self.gate_lo = int(lags[1])
        self.table = autocorrelation_table(bip, cfg.samples_per_chip, cfg.gate_len)
        self.sign = despread
        lo, hi = adc_limits(cfg.adc_bits)
        self.acc_lo, self.acc_hi = cfg.averages * lo, cfg.averages * hi
        # |acc| + |echo sum| <= (K + 1) R 2^(b-1): int32 when that fits (half the traffic)
        big = (bip.shape[0] + 1) * cfg.averages << (cfg.adc_bits - 1)
        self.work_type = np.int32 if big < 2**31 else np.int64

    def pick(self, outputs: list[ReceiverOutput]) -> Subtraction:
        """The echoes to subtract, from the previous pass's outputs (one per column)."""
        cfg, k = self.cfg, self.bip.shape[0]
        b = np.zeros((len(outputs), k), dtype=np.int64)
        jp = np.zeros((len(outputs), k), dtype=np.int64)
        for c, o in enumerate(outputs):
            cand = np.flatnonzero((o.peak_lag >= 0) & o.uid_match)
            for ch, p, cnt, tot, sq, lag in zip(
                    cand.tolist(), o.peak[cand].tolist(), o.noise_count[cand].tolist(),
                    o.noise_sum[cand].tolist(), o.noise_sumsq[cand].tolist(),
                    o.peak_lag[cand].tolist(), strict=True):
                if subtracts(cfg, p, cnt, tot, int(sq)):
                    b[c, ch] = amplitude(cfg, p, self.ns)
                    jp[c, ch] = (lag - self.gate_lo) % self.ns
        return Subtraction(b, jp)

    def residual(self, acc: NDArray[np.signedinteger], sub: Subtraction,
                 out: NDArray[np.signedinteger]) -> None:
        """``out`` (C, n, NS) = the accumulators ``acc`` minus the subtracted echoes,
        saturated to the accumulator range (rows of ``sub`` match ``acc``'s columns)."""
        s, n, wt = self.cfg.samples_per_chip, self.n_chips, self.work_type
        echo = np.empty(n, dtype=wt)
        for c in range(acc.shape[0]):
            chans = np.flatnonzero(sub.b[c])
            lag = (sub.jp[c, chans] + self.gate_lo) % self.ns
            q, phase = np.divmod(lag, s)
            # E(jS + t) = sum over phases f of chip[f][j - (t < f)], where
            # chip[f][j] = sum_{k: lag_k = q_k S + f} b_k c_k[(j - q_k) mod N]
            chip = np.zeros((s, n), dtype=wt)
            for ch, qk, fk, bk in zip(chans.tolist(), q.tolist(), phase.tolist(),
                                      sub.b[c, chans].tolist(), strict=True):
                row = chip[fk]
                np.multiply(self.bip[ch], bk, out=echo, dtype=wt)
                row[qk:] += echo[:n - qk]
                row[:qk] += echo[n - qk:]
            e = np.zeros((n, s), dtype=wt)
            for f in range(s):
                e[:, f:] += chip[f][:, None]
                e[:, :f] += np.roll(chip[f], 1)[:, None]
            e = e.reshape(-1)
            for p, sign in enumerate(self.sign.tolist()):
                r = acc[c, p].astype(wt) - sign * e
                np.clip(r, self.acc_lo, self.acc_hi, out=r)
                out[c, p] = r

    def own(self, sub: Subtraction, j: NDArray[np.int64]) -> NDArray[np.int64]:
        """``b_k A_k(lag_j - l_k)`` for gate indices ``j`` (C, K, ...) of each channel: a
        subtracted echo correlated with its own code (0 where not subtracted)."""
        g = self.cfg.gate_len
        shape = (*sub.b.shape, *([1] * (j.ndim - 2)))
        off = j - sub.jp.reshape(shape) + g
        kk = np.arange(self.bip.shape[0]).reshape(1, -1, *([1] * (j.ndim - 2)))
        return sub.b.reshape(shape) * self.table[kk, off]

    def add_own(self, raw: NDArray[np.int64], sub: Subtraction) -> None:
        """raw (C, K, G + 2) += n b_k A_k(lag - l_k) at every lag of ``out[..., m]``."""
        j = np.arange(-1, self.cfg.gate_len + 1)  # gate index of out[..., m]
        jj = np.broadcast_to(j, raw.shape)
        raw += self.cfg.uid_bits * self.own(sub, jj)
