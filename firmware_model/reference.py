"""The receive chain's streaming reference: literal, sample by sample, Python integers.

:class:`ReferenceReceiver` takes one column in chunks of any size (``feed``) and
computes every output of docs/firmware.md with exact integers and fractions
(``finish``); :func:`reference` runs it on a whole column. Deliberately simple and
slow: it is what the vectorised chain (:mod:`cdma_lidar.firmware_model.chain`) is
proven bit-identical against.
"""

from __future__ import annotations

import math
from fractions import Fraction

import numpy as np
from numpy.typing import ArrayLike

from cdma_lidar.errors import out_of_range
from cdma_lidar.firmware_model.adc import adc_limits
from cdma_lidar.firmware_model.cancel import amplitude, subtracts
from cdma_lidar.firmware_model.output import FIELDS, ReceiverOutput, saturated_flags
from cdma_lidar.firmware_model.receiver_config import ReceiverConfig, as_samples, check_codes

__all__ = ["ReferenceReceiver", "reference"]

class ReferenceReceiver:
    """Streaming reference model of one column: ``feed`` chunks of any size, then ``finish``.

    Samples are consumed one by one in arrival order, exactly as the hardware
    accumulator sees them: sample t adds to ``acc[(t // NS) % n][t % NS]``.
    Deliberately simple and slow (Python integers); use small configurations.
    """

    def __init__(self, cfg: ReceiverConfig, codes: ArrayLike) -> None:
        self.cfg = cfg
        bits = check_codes(codes)
        self.n_chips = int(bits.shape[1])
        self.widths = cfg.widths(self.n_chips)
        s = cfg.samples_per_chip
        self._ns = self.n_chips * s
        self._ref = [[1 - 2 * int(row[i // s]) for i in range(self._ns)] for row in bits.tolist()]
        self._acc = [[0] * self._ns for _ in range(cfg.uid_bits)]
        self._t = 0
        self._total = cfg.column_samples(self.n_chips)
        self._lo, self._hi = adc_limits(cfg.adc_bits)

    @property
    def samples_needed(self) -> int:
        """ADC samples still expected before :meth:`finish`."""
        return self._total - self._t

    def feed(self, chunk: ArrayLike) -> None:
        """Accumulate a 1-D chunk of ADC codes (any length up to :attr:`samples_needed`)."""
        x = as_samples(chunk, 1)
        if len(x) > self.samples_needed:
            raise out_of_range(
                "samples", f"{self._total} ADC codes per column", self._t + len(x)
            )
        ns, n = self._ns, self.cfg.uid_bits
        for v in x.tolist():
            if not self._lo <= v <= self._hi:
                raise out_of_range("samples", f"ADC codes in {self._lo}..{self._hi}", v)
            t = self._t
            self._acc[(t // ns) % n][t % ns] += v
            self._t = t + 1

    def finish(self) -> ReceiverOutput:
        """Despread, correlate, scale and search; with ``cancel_rounds``, again on the
        accumulators minus the echoes the previous pass found
        (:mod:`cdma_lidar.firmware_model.cancel`); return the column's output."""
        if self._t != self._total:
            raise out_of_range("samples", f"{self._total} ADC codes per column", self._t)
        cfg, ns = self.cfg, self._ns
        out = self._pass(self._acc, {})
        lo, hi = cfg.averages * self._lo, cfg.averages * self._hi
        for _ in range(cfg.cancel_rounds):
            sub = {}  # channel -> (amplitude b in accumulator codes, lag in samples)
            for k in range(len(self._ref)):
                if out.peak_lag[k] >= 0 and out.uid_match[k] and subtracts(
                        cfg, int(out.peak[k]), int(out.noise_count[k]),
                        int(out.noise_sum[k]), int(out.noise_sumsq[k])):
                    sub[k] = (amplitude(cfg, int(out.peak[k]), ns), int(out.peak_lag[k]))
            echo = [sum(b * self._ref[k][(i - lag) % ns] for k, (b, lag) in sub.items())
                    for i in range(ns)]
            res = [[min(max(self._acc[p][i] - (-echo[i] if (cfg.uid >> p) & 1 else echo[i]),
                            lo), hi) for i in range(ns)] for p in range(cfg.uid_bits)]
            out = self._pass(res, sub)
        return out

    def _pass(self, acc: list[list[int]], sub: dict[int, tuple[int, int]]) -> ReceiverOutput:
        """One pass of the chain on the accumulators ``acc`` (n lists of NS integers); each
        channel k of ``sub`` (amplitude b, lag l) has its own echo, b ref_k[i - l] in every
        period with the UID's polarity, added back to its correlations."""
        cfg, ns = self.cfg, self._ns
        n, uid, g = cfg.uid_bits, cfg.uid, cfg.gate_len
        d = [
            sum(-acc[p][i] if (uid >> p) & 1 else acc[p][i] for p in range(n))
            for i in range(ns)
        ]
        lags = [(cfg.gate_start + j) % ns for j in range(g)]
        ghost = [
            any((lag - start) % ns < length for start, length in cfg.ghost_windows)
            for lag in lags
        ]
        w = cfg.peak_exclude
        rows: dict[str, list] = {name: [] for name in FIELDS}
        for k, ref in enumerate(self._ref):

            def own(lag: int, ref: list[int] = ref, k: int = k) -> int:
                """b A_k(lag - l): this channel's subtracted echo on its own code."""
                if k not in sub:
                    return 0
                b, l0 = sub[k]
                return b * sum(ref[i] * ref[(i + lag - l0) % ns] for i in range(ns))

            def corr_at(data: list[int], lag: int, ref: list[int] = ref, times: int = n) -> int:
                return sum(ref[i] * data[(i + lag) % ns] for i in range(ns)) + times * own(lag)

            out = [self._scale(corr_at(d, lag)) for lag in lags]
            found: list[int] = []
            for _ in range(cfg.peaks):
                best = None
                for j in range(g):
                    if ghost[j] or any(abs(j - q) <= w for q in found):
                        continue
                    if best is None or abs(out[j]) > abs(out[best]):
                        best = j
                if best is None:
                    break
                found.append(best)
            peak_lags = [lags[j] for j in found] + [-1] * (cfg.peaks - len(found))
            peak_vals = [out[j] for j in found] + [0] * (cfg.peaks - len(found))
            signs = [
                [_sign(corr_at(acc[p], lag, times=-1 if (uid >> p) & 1 else 1))
                 for p in range(n)] if lag >= 0 else [0] * n
                for lag in peak_lags
            ]
            noise = [
                out[j] for j in range(g)
                if not ghost[j] and all(abs(j - q) > w for q in found)
            ]
            if found:
                lag0 = peak_lags[0]
                nb = [self._scale(corr_at(d, (lag0 - 1) % ns)),
                      self._scale(corr_at(d, (lag0 + 1) % ns))]
            else:
                nb = [0, 0]
            observed = sum(1 << p for p in range(n) if signs[0][p] < 0)
            rows["corr"].append(out)
            rows["peak_lag"].append(peak_lags[0])
            rows["peak"].append(peak_vals[0])
            rows["neighbours"].append(nb)
            rows["noise_count"].append(len(noise))
            rows["noise_sum"].append(sum(noise))
            rows["noise_sumsq"].append(sum(v * v for v in noise))
            rows["uid_signs"].append(signs[0])
            rows["uid_observed"].append(observed)
            rows["uid_match"].append(bool(found) and 0 not in signs[0] and observed == uid)
            rows["extra_lag"].append(peak_lags[1:])
            rows["extra_peak"].append(peak_vals[1:])
            rows["extra_signs"].append(signs[1:])
        k, p1 = len(self._ref), cfg.peaks - 1
        rows["saturated"] = saturated_flags(rows["peak_lag"], rows["peak"], cfg.out_bits).tolist()
        return ReceiverOutput(
            corr=np.array(rows["corr"], dtype=np.int64).reshape(k, g),
            peak_lag=np.array(rows["peak_lag"], dtype=np.int64),
            peak=np.array(rows["peak"], dtype=np.int64),
            neighbours=np.array(rows["neighbours"], dtype=np.int64).reshape(k, 2),
            noise_count=np.array(rows["noise_count"], dtype=np.int64),
            noise_sum=np.array(rows["noise_sum"], dtype=np.int64),
            noise_sumsq=np.array(rows["noise_sumsq"], dtype=self.widths.sumsq_dtype).reshape(k),
            uid_signs=np.array(rows["uid_signs"], dtype=np.int8).reshape(k, n),
            uid_observed=np.array(rows["uid_observed"], dtype=np.int64),
            uid_match=np.array(rows["uid_match"], dtype=np.bool_),
            saturated=np.array(rows["saturated"], dtype=np.bool_),
            extra_lag=np.array(rows["extra_lag"], dtype=np.int64).reshape(k, p1),
            extra_peak=np.array(rows["extra_peak"], dtype=np.int64).reshape(k, p1),
            extra_signs=np.array(rows["extra_signs"], dtype=np.int8).reshape(k, p1, n),
        )

    def _scale(self, raw: int) -> int:
        """out = sat(round(raw / 2^s)), written with exact fractions (docs/firmware.md §3)."""
        cfg = self.cfg
        x = Fraction(raw, 1 << cfg.out_shift)
        if cfg.rounding == "truncate":
            r = math.floor(x)
        elif cfg.rounding == "half_up":
            r = math.floor(x + Fraction(1, 2))
        else:
            r = round(x)  # Fraction.__round__ without digits: half to even
        top = (1 << (cfg.out_bits - 1)) - 1
        return min(max(r, -top - 1), top)


def _sign(v: int) -> int:
    return (v > 0) - (v < 0)


def reference(cfg: ReceiverConfig, codes: ArrayLike, samples: ArrayLike) -> ReceiverOutput:
    """Run the streaming reference on one column (``samples``: 1-D, R*n*N*S ADC codes)."""
    rx = ReferenceReceiver(cfg, codes)
    rx.feed(samples)
    return rx.finish()
