r"""Near-far closed loop: frame n's SNR_XC map and peaks set frame n+1's power matrix.

Supplementary Note 12 and Fig. 4c-e. In one column every channel shares the single
detector, so a strong near echo raises the correlation noise floor of all the other
channels and drowns the weak far ones. The remedy is per-pixel laser power: lower it
where SNR_XC is far above the threshold, raise it where SNR_XC is below, and so give
the weak pixels a lower noise floor without raising the total power. It is CDMA's
uplink power control (Foschini-Miljanic), with the one difference that a pixel's
floor is partly made by the pixels being adjusted. docs/host.md has the derivation;
in short:

What a frame measures, per pixel ``k`` of a column (all in correlator units): the
peak ``A_k`` and the floor ``sigma_k = A_k / 10^(SNR_k/20)``. The floor is the
thermal (detector, ADC) part ``n0``, which no laser power changes, plus the
interference of the echoes in the same column, proportional to their ``A_j^2``::

    sigma_k^2 = n0 + I_k,      I_k = c * sum_{j != k} A_j^2       (own sidelobes: j = k too)

The reference ``n0_hat`` is a low percentile (5 %) of ``sigma^2`` over the whole frame:
the least-interfered pixels (sky, empty columns) see the bare thermal floor, so
``n0_hat >= n0`` within the estimator's scatter, and no single pixel (nor the set of
pixels being adjusted) makes it up alone. The interference is what is left,
``I_k = max(sigma_k^2 - n0_hat, 0)``; ``c`` is never needed because only ratios of
``A^2`` sums enter. Scaling the powers by ``g`` (``A_k -> g_k A_k``) predicts::

    SNR_k' = g_k^2 A_k^2 / (n0_hat + I_k * sum_{j!=k} g_j^2 A_j^2 / sum_{j!=k} A_j^2)

Control law (pure function, :func:`next_power`), target band
``[threshold + band_low, threshold + band_high]``, centre ``T_c`` (dB):

* weak, ``SNR < threshold + band_low``: raise towards the centre,
  ``g = 10^(min(T_c - SNR, max_step_up)/20)`` (a sky pixel just climbs to its maximum
  and stays; it has no echo, so it interferes with nobody);
* strong, ``SNR > threshold + band_high``: lower to the centre *as predicted above*,
  all strong pixels of a column together (a few fixed-point sweeps of the
  prediction, each one only lowering, at most ``max_step_down`` dB);
* inside the band: unchanged (hysteresis: the band is wider than the frame-to-frame
  scatter of SNR_XC, so a settled pixel stays put).

Why it cannot run away (the bug this replaces: a reference floor made by the same
pixels fell with them, about 8 dB a frame): ``n0_hat`` overestimates ``n0``, so the
predicted floor after lowering is never below the true one, and a lowered pixel's
true SNR_XC lands at or above ``T_c``; an ADC clipped or sidelobe-limited echo loses
less than predicted, which errs the same way. Raising only moves pixels up.
Then ``P`` is clipped to ``[min_power, max_power]`` per pixel; the eye-safety cap on
each column's sum is a hard constraint applied last: raised pixels give way first
(they may be empty sky that no power lights up), then, if that is not enough, the
whole column. The device enforces the same cap. Powers are in one consistent unit
(fractions of the per-pixel maximum on the device).
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import ArrayLike, NDArray

from cdma_lidar.errors import out_of_range

__all__ = ["NearFarController", "PowerLimits", "apply_cap", "next_power"]

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class PowerLimits:
    """Power bounds (one unit throughout, W on the device).

    Attributes:
        max_power: per-pixel maximum, scalar or (K, C).
        min_power: per-pixel minimum (keeps a pixel measurable), scalar; None for
            1e-4 of the smallest maximum.
        total_cap: eye-safety cap on each column's sum over channels (all channels of a
            column are emitted together); None for no cap beyond the per-pixel maxima.
    """

    max_power: float | NDArray = 1.0
    min_power: float | None = None
    total_cap: float | None = None

    def __post_init__(self) -> None:
        mx = np.asarray(self.max_power, dtype=np.float64)
        if not (np.all(np.isfinite(mx)) and np.all(mx > 0)):
            raise out_of_range("max_power", "finite and > 0", self.max_power)
        if self.min_power is None:
            object.__setattr__(self, "min_power", 1e-4 * float(mx.min()))
        elif not (np.isfinite(self.min_power) and 0 < self.min_power <= float(mx.min())):
            raise out_of_range("min_power", f"in (0, {float(mx.min())}]", self.min_power)
        if self.total_cap is not None and not (np.isfinite(self.total_cap)
                                               and self.total_cap > 0):
            raise out_of_range("total_cap", "finite and > 0, or None", self.total_cap)


def next_power(power: ArrayLike, snr_db: ArrayLike, threshold_db: float,
               limits: PowerLimits = PowerLimits(), *, peak: ArrayLike | None = None,
               band_low_db: float = 4.0, band_high_db: float = 10.0,
               max_step_up_db: float = 12.0, max_step_down_db: float = 40.0,
               noise_percentile: float = 5.0, sweeps: int = 3) -> NDArray[np.float64]:
    """Power matrix for the next frame from this frame's power and SNR_XC (dB), both (K, C).

    ``peak`` (K, C) are the correlation peaks (correlator units) measured with
    ``power``; without them the interference cannot be told from the thermal floor and
    strong pixels are lowered as if their floor stayed put (slower, still safe).
    ``band_low_db`` .. ``band_high_db`` above the threshold is the target band (dB of
    SNR_XC, a power ratio; the power itself moves by half as many dB), ``max_step_up_db``
    and ``max_step_down_db`` bound one frame's change of a pixel's SNR_XC (dB).
    ``noise_percentile`` picks the thermal reference ``n0_hat`` among the frame's
    ``sigma^2``. Pixels whose SNR_XC is not finite (column missing) keep their power.
    """
    p = np.asarray(power, dtype=np.float64)
    s = np.asarray(snr_db, dtype=np.float64)
    if p.shape != s.shape or p.ndim != 2:
        raise out_of_range("power shape", f"equal to the SNR map's {s.shape} (K, C)", p.shape)
    if not 0 <= band_low_db < band_high_db:
        raise out_of_range("band", "0 <= band_low_db < band_high_db",
                           (band_low_db, band_high_db))
    for name, v in (("max_step_up_db", max_step_up_db), ("max_step_down_db", max_step_down_db)):
        if not (np.isfinite(v) and v > 0):
            raise out_of_range(name, "finite and > 0 dB", v)
    if not 0 <= noise_percentile <= 50:
        raise out_of_range("noise_percentile", "0 to 50", noise_percentile)
    centre = threshold_db + 0.5 * (band_low_db + band_high_db)
    finite = np.isfinite(s)
    weak = finite & (s < threshold_db + band_low_db)
    model = _Model.fit(s, peak, noise_percentile, threshold_db)
    if model is None:
        # No amplitudes: the floor is assumed to stay where it is (plain power control).
        strong = finite & (s > threshold_db + band_high_db)
        g = np.ones_like(p)
        g = np.where(strong, 10.0 ** (np.maximum(centre - s, -max_step_down_db) / 20.0), g)
        up_db = np.where(weak, np.clip(centre - s, 0.0, max_step_up_db), 0.0)
        g = np.where(weak, 10.0 ** (up_db / 20.0), g)
    else:
        # Strong, or detected in a column whose floor is mostly interference.
        lower = (model.usable & (s >= threshold_db + band_low_db)
                 & ((s > threshold_db + band_high_db) | (model.interf > model.n0)))
        g = model.lower(np.ones_like(p), lower, centre, max_step_down_db, sweeps)
        # Weak pixels gain what the lowered neighbours take off their floor for free;
        # only the rest is asked of their own power.
        drop_db = model.floor_drop_db(g)
        up_db = np.where(weak, np.clip(centre - s - drop_db, 0.0, max_step_up_db), 0.0)
        g = np.where(weak, 10.0 ** (up_db / 20.0), g)
        g = model.lower(g, lower, centre, max_step_down_db, sweeps)
        # Hysteresis on small moves inside the band: no chatter around the centre.
        small = lower & (s <= threshold_db + band_high_db) & (g > 10.0 ** (-1.0 / 20.0))
        g = np.where(small, 1.0, g)
    new = np.clip(p * g, limits.min_power, limits.max_power)
    new = np.where(finite, new, np.clip(p, limits.min_power, limits.max_power))
    if limits.total_cap is not None:
        # Likely sky (far below the threshold) gives way before likely objects.
        raised = new > p
        new = apply_cap(new, limits.total_cap, np.minimum(p, new),
                        (raised & ~(s >= threshold_db - 3.0), raised))
    return new


@dataclass(frozen=True)
class _Model:
    """The floor model of the module docstring fitted to one frame (correlator units)."""

    a2: NDArray[np.float64]          # A_k^2 of detected pixels (echoes), 0 elsewhere
    var: NDArray[np.float64]         # sigma_k^2
    interf: NDArray[np.float64]      # I_k = max(sigma_k^2 - n0_hat, 0)
    usable: NDArray[np.bool_]
    n0: float

    @classmethod
    def fit(cls, s: NDArray[np.float64], peak: ArrayLike | None, percentile: float,
            threshold_db: float) -> _Model | None:
        """Fit to a frame; None without peaks. Only detected pixels count as interferers:
        below the threshold the 'peak' is mostly the floor's own noise, not an echo."""
        if peak is None:
            return None
        a = np.abs(np.asarray(peak, dtype=np.float64))
        if a.shape != s.shape:
            raise out_of_range("peak shape", f"equal to the SNR map's {s.shape}", a.shape)
        finite = np.isfinite(s) & np.isfinite(a)
        with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
            a2 = np.where(finite, a * a, 0.0)
            var = np.where(finite & (a > 0), a2 / 10.0 ** (np.where(finite, s, 0.0) / 10.0),
                           np.nan)
        usable = np.isfinite(var) & (var > 0)
        if not np.any(usable):
            return None
        n0 = float(np.percentile(var[usable], percentile))
        interf = np.where(usable, np.maximum(var - n0, 0.0), 0.0)
        echo = usable & (s >= threshold_db)
        return cls(np.where(echo, a2, 0.0), np.where(usable, var, np.nan), interf, usable, n0)

    def floor(self, g: NDArray[np.float64]) -> NDArray[np.float64]:
        """Predicted sigma^2 of every pixel when every amplitude is scaled by ``g``."""
        others0 = self.a2.sum(axis=0, keepdims=True) - self.a2
        ga2 = self.a2 * g * g
        others = ga2.sum(axis=0, keepdims=True) - ga2
        with np.errstate(divide="ignore", invalid="ignore"):
            ratio = np.where(others0 > 0, others / others0, 1.0)
        return self.n0 + self.interf * ratio

    def floor_drop_db(self, g: NDArray[np.float64]) -> NDArray[np.float64]:
        """How many dB the floor of each pixel falls (>= 0) with gains ``g``."""
        with np.errstate(divide="ignore", invalid="ignore"):
            drop = 10.0 * np.log10(self.var / self.floor(g))
        return np.where(self.usable & np.isfinite(drop), np.maximum(drop, 0.0), 0.0)

    def lower(self, g: NDArray[np.float64], which: NDArray[np.bool_], centre: float,
              max_down_db: float, sweeps: int) -> NDArray[np.float64]:
        """Gains that bring the ``which`` pixels to ``centre`` dB as the model predicts.

        With ``x_k = g_k^2 A_k^2`` and ``b_k = T_c I_k / sum_{j!=k} A_j^2`` the targets
        ``x_k = T_c F_k`` are linear in ``x``; per column (L = the ``which`` pixels,
        R = the other echoes' ``x``, fixed)::

            x_k = (T_c n0 + b_k (R + X_L)) / (1 + b_k),   X_L = sum_L x_k
            X_L = sum_L (T_c n0 + b_k R) / (1 + b_k)  /  (1 - sum_L b_k / (1 + b_k))

        A column where ``sum_L b_k / (1 + b_k) >= 1`` cannot reach the targets at any
        power (its pixels limit each other): it is left alone. The gains are clipped to
        ``[10^(-max_down/20), 1]`` and ``sweeps`` Jacobi sweeps of ``g_k = sqrt(T_c F_k / A_k^2)``
        settle the clipped ones.
        """
        t_c = 10.0 ** (centre / 10.0)
        g_min = 10.0 ** (-max_down_db / 20.0)
        which = which & (self.a2 > 0)
        others0 = self.a2.sum(axis=0, keepdims=True) - self.a2
        with np.errstate(divide="ignore", invalid="ignore"):
            b = np.where(which & (others0 > 0), t_c * self.interf / others0, 0.0)
        x_rest = np.where(which, 0.0, self.a2 * g * g).sum(axis=0, keepdims=True)
        w = np.where(which, b / (1.0 + b), 0.0)
        load = w.sum(axis=0, keepdims=True)
        feasible = load < 1.0 - 1e-6
        with np.errstate(divide="ignore", invalid="ignore"):
            x_l = np.where(which, (t_c * self.n0 + b * x_rest) / (1.0 + b), 0.0).sum(
                axis=0, keepdims=True) / np.where(feasible, 1.0 - load, 1.0)
            x = (t_c * self.n0 + b * (x_rest + x_l)) / (1.0 + b)
            want = np.sqrt(x / self.a2)
        act = which & feasible
        gs = np.where(act, np.clip(want, g_min, 1.0), g)
        for _ in range(sweeps):
            with np.errstate(divide="ignore", invalid="ignore"):
                want = np.sqrt(t_c * self.floor(gs) / self.a2)
            gs = np.where(act, np.clip(want, g_min, 1.0), gs)
        return gs


def apply_cap(power: NDArray[np.float64], cap: float,
              previous: NDArray[np.float64] | None = None,
              give_way: Sequence[NDArray[np.bool_]] = ()) -> NDArray[np.float64]:
    """Bring every column's sum (axis 0) to at most ``cap``, a hard limit.

    The increments over ``previous`` of the pixels in ``give_way[0]`` are scaled down
    first (to nothing if need be), then those of ``give_way[1]``, and so on; if the
    column is still over the cap, the whole column is scaled. Without ``previous`` the
    masked pixels' whole power gives way.
    """
    out = np.asarray(power, dtype=np.float64).copy()
    base = np.zeros_like(out) if previous is None else np.minimum(previous, out)
    for mask in give_way:
        inc = np.where(mask, out - base, 0.0)
        up = inc.sum(axis=0)
        over = out.sum(axis=0) - cap
        with np.errstate(divide="ignore", invalid="ignore"):
            f = np.where((up > 0) & (over > 0), np.clip(1.0 - over / up, 0.0, 1.0), 1.0)
        out = np.where(mask, base + inc * f[None, :], out)
    total = out.sum(axis=0)
    with np.errstate(divide="ignore", invalid="ignore"):
        f_all = np.where(total > cap, cap / total, 1.0)
    return out * f_all[None, :]


@dataclass
class NearFarController:
    """Closed loop over frames: feed each frame's SNR_XC map, get the next power matrix.

    Keeps the history of SNR maps and power matrices so a report can show the heatmaps
    before and after.
    """

    shape: tuple[int, int]
    threshold_db: float
    limits: PowerLimits = field(default_factory=PowerLimits)
    band_low_db: float = 4.0
    band_high_db: float = 10.0
    max_step_up_db: float = 12.0
    max_step_down_db: float = 40.0
    initial_power: float = 0.5
    powers: list[NDArray[np.float64]] = field(default_factory=list)
    snr_maps: list[NDArray[np.float64]] = field(default_factory=list)

    def __post_init__(self) -> None:
        if not self.powers:
            start = np.minimum(np.full(self.shape, self.initial_power), self.limits.max_power)
            self.powers.append(start)

    @property
    def power(self) -> NDArray[np.float64]:
        """Power matrix for the frame about to be scanned."""
        return self.powers[-1]

    def update(self, snr_db: ArrayLike, peak: ArrayLike | None = None) -> NDArray[np.float64]:
        """Record the frame just scanned (with :attr:`power`) and return the next matrix."""
        s = np.asarray(snr_db, dtype=np.float64)
        self.snr_maps.append(s.copy())
        nxt = next_power(self.power, s, self.threshold_db, self.limits, peak=peak,
                         band_low_db=self.band_low_db, band_high_db=self.band_high_db,
                         max_step_up_db=self.max_step_up_db,
                         max_step_down_db=self.max_step_down_db)
        log.info("near-far frame %d: %.1f %% above threshold, power sum %.3g -> %.3g",
                 len(self.snr_maps) - 1, 100.0 * float(np.mean(s >= self.threshold_db)),
                 float(self.power.sum()), float(nxt.sum()))
        self.powers.append(nxt)
        return nxt
