"""One calibration for the whole paper: the unstated link fitted once to the paper's measurements.

The paper does not publish its link budget, and several of its printed measurements depend
on it. Instead of tuning one study's free terms until its row passes, this module fits
the unstated parameters once, jointly, to a named set of the paper's measurements
(:data:`USED`), in closed form, and predicts a measurement held out of the fit
(:data:`HELD_OUT`), which a Monte-Carlo study then checks (``fig2f`` at ``point=paper``,
run by the paper report at the fitted link: :func:`reflectivity_for_link`).

The closed forms (no randomness; a fit takes milliseconds):

* The correlator's output SNR of one channel (peak squared over the noise variance of a
  lag, the ``N_s x SNR`` of eq. 28)::

      1 / rho = K_mix / (rho10 g_band (N / 2047) R (10 m / d)^4) + (2/3) (K - 1) / N

  ``rho10`` the link (dB): one channel at 10 m, one record, a degree-11 code, the L-band
  EDFA; the echo's power falls as 1/d^4 (the optical power as 1/d^2, detected to a
  current squared; the toolkit's link budget gives 12.04 dB per doubling); ``K_mix`` 40
  where the channels were recorded one after another and summed (Supp. Note 4), else 1;
  ``R`` records averaged; the second term the other K - 1 channels' asynchronous
  cross-correlation (eq. 42, 2/(3N) each), absent for one channel; ``g_band`` the
  C-band EDFA's gain over the L-band's (dB), where the paper used the C-band one.
* Eq. 28: the depth resolution 2 sigma = sqrt(6 / rho) / pi x c / (2 f_c).
* The error rate (a range more than half a chip off, the 10 % threshold of Figs. 2e, 2f,
  11): the peak at sqrt(rho) against M = N independent noise lags,
  ``P_err = 1 - int phi(x - sqrt(rho)) Phi(x)^(M - 1) dx`` (:func:`error_rate`).

Each measurement gives a residual in dB of ``rho`` over its own uncertainty: a printed
value (Fig. 2c's 25.68 cm, Fig. 2f's 66 m) model minus measured; a printed "it works"
(scenes 1 and 2 imaged, Fig. 2e workable at -50 dB) a one-sided residual, zero when the
error rate is at most 10 %, else the dB missing. The fit is least squares of those
residuals (``scipy.optimize.least_squares``), with a weak pull (1/100 of a standard
residual per dB) towards the toolkit's ``paper-lab`` link, the same EDFA in both bands
and S = 50, so a parameter that only a one-sided measurement bounds sits at the edge that
explains it: the least departure from the preset. Every subset of the measurements is
fitted too (:func:`subsets`): one instrument explains a set when every residual is
within two of its uncertainties.
"""

from __future__ import annotations

import dataclasses
import functools
import itertools
import math
from dataclasses import dataclass
from typing import Any

import numpy as np
from scipy.optimize import brentq, least_squares
from scipy.special import log_ndtr

from cdma_lidar.scene import load_scene
from cdma_lidar.scene.instrument import Instrument
from cdma_lidar.units import SPEED_OF_LIGHT_M_S

__all__ = [
    "CHIP_RATE_HZ",
    "HELD_OUT",
    "MEASUREMENTS",
    "PARAMETERS",
    "USED",
    "Fit",
    "Measurement",
    "calibrate",
    "error_rate",
    "fit",
    "max_range_m",
    "output_snr",
    "preset_link_db",
    "reflectivity_for_link",
    "resolution_eq28_m",
    "rho_for_resolution",
    "subsets",
    "threshold_rho",
]

#: The paper's chip rate (Methods), Hz.
CHIP_RATE_HZ = 62.5e6
#: The error rate that marks the threshold (Figs. 2e, 2f, 11).
ERROR_LEVEL = 0.10
#: The fitted parameters, their units, and the value the weak pull starts from (None:
#: the ``paper-lab`` preset's link, computed).
PARAMETERS: tuple[tuple[str, str], ...] = (
    ("link_db", "dB: rho of one channel at 10 m, R = 1, degree 11, L-band EDFA"),
    ("c_band_db", "dB: the C-band EDFA's gain over the L-band's, in rho"),
    ("fig2e_samples_per_chip", "samples per chip behind Fig. 2e's SNR axis (R = 10)"),
)
#: The weak pull's weight (per dB, in units of a measurement's standard residual).
PULL = 0.01
#: Fig. 2e's records (assumed as the 3D scans': Methods, ten repetitions averaged).
FIG2E_RECORDS = 10


@dataclass(frozen=True)
class Measurement:
    """One of the paper's printed measurements, as the closed forms see it.

    ``kind`` ``"resolution"`` (``value`` m, eq. 28's 2 sigma), ``"range"`` (``value`` m: the
    error rate crosses 10 % there), ``"works"`` (the error rate is at most 10 %; ``value``
    unused) or ``"workable_snr"`` (``value`` dB: the per-sample SNR at which the error rate
    is at most 10 %). ``uncertainty_db``: the measurement's own, in dB of rho.
    """

    name: str
    where: str
    kind: str
    value: float | None
    distance_m: float
    degree: int
    mixed: bool
    records: int
    band: str
    uncertainty_db: float
    source: str


#: The candidates (the paper's words and where each condition comes from in ``source``).
MEASUREMENTS: tuple[Measurement, ...] = (
    Measurement("fig2c_resolution", "Fig. 2c", "resolution", 0.2568, 10.0, 11, False, 1, "L",
                0.19, "25.68 cm from 1000 ranges (its chi-square 95 % on sigma is +-4.4 %, "
                "0.19 dB of rho); 10 m, one record, one channel: assumed (fig2c)"),
    Measurement("scene1_images", "Fig. 3a", "works", None, 5.0, 11, True, 10, "L", 1.0,
                "scene 1 at about 5 m imaged with order 11, an L-band EDFA, 40 channels "
                "mixed, 10 records (Methods); 'images' read as at most 10 % errors, 1 dB"),
    Measurement("scene2_images", "Fig. 3f", "works", None, 10.0, 11, True, 10, "C", 1.0,
                "scene 2 at about 10 m imaged with order 11 and a C-band EDFA (Methods), 40 "
                "channels mixed, 10 records; at most 10 % errors, 1 dB"),
    Measurement("fig2e_workable", "Fig. 2e", "workable_snr", -50.0, 10.0, 11, True,
                FIG2E_RECORDS, "L", 1.0, "'still workable in -50 dB testing environment': "
                "at most 10 % errors at a per-sample SNR of -50 dB (eq. 30, the other "
                "channels counted as noise); R = 10 assumed; 1 dB"),
    Measurement("fig2f_range", "Fig. 2f", "range", 66.0, 66.0, 13, True, 10, "L", 1.66,
                "'up to 66 m with a 13th-order code': the error rate crosses 10 % at 66 m; "
                "40 channels mixed, R = 10 and the L-band EDFA assumed; +-10 % in distance "
                "(1.66 dB; the band's width is not printed)"),
)
#: The measurements the calibration fits, and the one it holds out and predicts.
USED = ("fig2c_resolution", "scene1_images", "scene2_images", "fig2e_workable")
HELD_OUT = "fig2f_range"


def chip_range_m(chip_rate_hz: float = CHIP_RATE_HZ) -> float:
    """The range of one chip, c / (2 f_c) (m)."""
    return SPEED_OF_LIGHT_M_S / (2.0 * chip_rate_hz)


def resolution_eq28_m(rho: float, chip_rate_hz: float = CHIP_RATE_HZ) -> float:
    """Eq. 28's depth resolution 2 sigma (m) at the correlator's output SNR ``rho``."""
    return math.sqrt(6.0 / rho) / math.pi * chip_range_m(chip_rate_hz)


def rho_for_resolution(resolution_m: float, chip_rate_hz: float = CHIP_RATE_HZ) -> float:
    """The output SNR rho (linear) at which eq. 28 gives ``resolution_m``."""
    return 6.0 * (chip_range_m(chip_rate_hz) / (math.pi * resolution_m)) ** 2


_X = np.linspace(-12.0, 12.0, 4801)
_PHI = np.exp(-0.5 * _X**2) / math.sqrt(2.0 * math.pi)


def error_rate(rho: float, lags: int) -> float:
    """The probability that one of ``lags - 1`` unit Gaussian noise lags beats a peak at
    sqrt(``rho``) (the correlator's output SNR, linear): the gross-error rate."""
    a = math.sqrt(max(rho, 0.0))
    log_cdf = (lags - 1) * log_ndtr(_X + a)  # x measured from the peak
    correct = float(np.sum(_PHI * np.exp(log_cdf)) * (_X[1] - _X[0]))
    return min(max(1.0 - correct, 0.0), 1.0)


@functools.lru_cache(maxsize=64)
def threshold_rho(lags: int, level: float = ERROR_LEVEL) -> float:
    """The output SNR (linear) at which :func:`error_rate` equals ``level``."""
    return 10 ** (brentq(lambda db: error_rate(10 ** (db / 10), lags) - level, -10.0, 40.0,
                         xtol=1e-6) / 10)


def output_snr(link_db: float, m: Measurement, c_band_db: float = 0.0,
               distance_m: float | None = None) -> float:
    """rho (linear) of measurement ``m``'s set-up at ``distance_m`` (default its own)."""
    n = (1 << m.degree) - 1
    d = m.distance_m if distance_m is None else distance_m
    band = c_band_db if m.band == "C" else 0.0
    noise = 10 ** ((link_db + band) / 10) * n / 2047 * m.records * (10.0 / d) ** 4
    inv = (40 if m.mixed else 1) / noise + (2 / 3 * 39 / n if m.mixed else 0.0)
    return 1.0 / inv


def max_range_m(link_db: float, m: Measurement, c_band_db: float = 0.0) -> float:
    """Where the error rate of ``m``'s set-up crosses 10 % (m); inf if never."""
    n = (1 << m.degree) - 1
    need = 1.0 / threshold_rho(n) - (2 / 3 * 39 / n if m.mixed else 0.0)
    if need <= 0:
        return math.nan  # the other channels alone exceed the threshold
    at10 = output_snr(link_db, m, c_band_db, 10.0)
    noise_at10 = 1.0 / (1.0 / at10 - (2 / 3 * 39 / n if m.mixed else 0.0))
    return 10.0 * (noise_at10 * need) ** 0.25


def _db(x: float) -> float:
    return 10 * math.log10(x)


def residual_db(m: Measurement, p: dict[str, float]) -> float:
    """Model minus measurement in dB of rho (one-sided for "works" and "workable")."""
    n = (1 << m.degree) - 1
    if m.kind == "resolution":
        return _db(output_snr(p["link_db"], m, p["c_band_db"])) - _db(rho_for_resolution(m.value))
    if m.kind == "range":
        return _db(output_snr(p["link_db"], m, p["c_band_db"])) - _db(threshold_rho(n))
    if m.kind == "works":
        return min(0.0, _db(output_snr(p["link_db"], m, p["c_band_db"]))
                   - _db(threshold_rho(n)))
    # workable_snr: rho = N S R SNR (the other channels inside the per-sample SNR)
    rho = n * p["fig2e_samples_per_chip"] * m.records * 10 ** (m.value / 10)
    return min(0.0, _db(rho) - _db(threshold_rho(n)))


@dataclass(frozen=True)
class Fit:
    """A fit's parameters, each measurement's residual (dB and in its uncertainties)."""

    used: tuple[str, ...]
    parameters: dict[str, float]
    residuals_db: dict[str, float]
    residuals_sigma: dict[str, float]

    @property
    def explains(self) -> bool:
        """One instrument explains the set: every residual within two uncertainties."""
        return all(abs(self.residuals_sigma[n]) <= 2.0 for n in self.used)


def _by_name() -> dict[str, Measurement]:
    return {m.name: m for m in MEASUREMENTS}


def fit(used: tuple[str, ...], preset_db: float, *,
        measurements: dict[str, Measurement] | None = None) -> Fit:
    """Fit :data:`PARAMETERS` to ``used`` (names of :data:`MEASUREMENTS`), least squares of
    the residuals over their uncertainties plus the weak pull towards ``preset_db``
    (the link), 0 dB (the C band) and 50 samples per chip. Residuals of every
    measurement (used or not) at the fitted point."""
    ms = measurements or _by_name()
    start = np.array([preset_db, 0.0, _db(50.0)])

    def unpack(x: np.ndarray) -> dict[str, float]:
        return {"link_db": float(x[0]), "c_band_db": float(x[1]),
                "fig2e_samples_per_chip": float(10 ** (x[2] / 10))}

    def res(x: np.ndarray) -> np.ndarray:
        p = unpack(x)
        r = [residual_db(ms[n], p) / ms[n].uncertainty_db for n in used]
        return np.array([*r, *(PULL * (x - start))])

    sol = least_squares(res, start, method="lm", xtol=1e-12, ftol=1e-12)
    p = unpack(sol.x)
    rdb = {n: residual_db(m, p) for n, m in ms.items()}
    return Fit(tuple(used), p, rdb, {n: rdb[n] / ms[n].uncertainty_db for n in ms})


def subsets(preset_db: float, names: tuple[str, ...] | None = None) -> list[Fit]:
    """Every subset of ``names`` (default all :data:`MEASUREMENTS`) with two or more
    members that one instrument explains and no explained superset contains (the
    largest consistent sets), largest first."""
    names = names or tuple(m.name for m in MEASUREMENTS)
    ok: list[Fit] = []
    for k in range(len(names), 1, -1):
        for combo in itertools.combinations(names, k):
            if any(set(combo) <= set(f.used) for f in ok):
                continue
            f = fit(combo, preset_db)
            if f.explains:
                ok.append(f)
    return ok


def preset_link_db(scene: str = "paper-lab", reflectivity: float | None = None) -> float:
    """rho (dB) of the toolkit's ``scene`` link: one channel at 10 m, one record, no mixing,
    N S times the per-sample SNR of eq. 30 from the instrument's link budget; the wall's
    ``reflectivity`` (the scene's shortcut) if given, else the preset's."""
    overrides: dict[str, Any] = {"sequential_mixing": False, "distance": 10.0, "averages": 1}
    if reflectivity is not None:
        overrides["reflectivity"] = reflectivity
    inst = Instrument(load_scene(scene, overrides), seed=0)
    p = np.zeros_like(inst.default_power_w)
    k = inst.channels // 2
    p[k, 0] = inst.default_power_w[k, 0]
    snr = float(inst.link_figures(power_w=p)["snr_db"][k, 0])
    spec = inst.spec
    return snr + _db(spec.code_length * spec.samples_per_chip)


def reflectivity_for_link(link_db: float, scene: str = "paper-lab") -> float | None:
    """The wall's reflectivity at which ``scene``'s link (:func:`preset_link_db`) is
    ``link_db``: how a Monte-Carlo run realises a fitted link with the preset's other terms
    (the reflectivity is an assumed term). None when no reflectivity up to 1 reaches it."""
    if preset_link_db(scene, 1.0) < link_db:
        return None
    return float(10 ** brentq(lambda lg: preset_link_db(scene, 10 ** lg) - link_db, -4.0, 0.0,
                              xtol=1e-7))


def calibrate(preset_db: float) -> dict[str, Any]:
    """The calibration of the paper report: the fit to :data:`USED`, its residuals (of every
    measurement), the held-out prediction, the fit to all, and the largest consistent sets.

    The returned dict is the ``calibration`` of the paper's ``summary.json``: ``parameters``,
    ``used``, ``residuals`` (name -> {``db``, ``sigma``, ``used``}), ``held_out`` (name,
    the paper's value, the prediction with its 95 % interval), ``all`` (the fit to every
    measurement, ``explains``), ``subsets`` (the largest consistent sets, what each
    leaves out and the dB each left-out measurement would need).
    """
    ms = _by_name()
    main = fit(USED, preset_db)
    held = ms[HELD_OUT]
    p = main.parameters
    sigma_link = ms["fig2c_resolution"].uncertainty_db  # the link is pinned by Fig. 2c
    pred = max_range_m(p["link_db"], held, p["c_band_db"])
    lo = max_range_m(p["link_db"] - 1.96 * sigma_link, held, p["c_band_db"])
    hi = max_range_m(p["link_db"] + 1.96 * sigma_link, held, p["c_band_db"])
    every = fit(tuple(ms), preset_db)
    sets = subsets(preset_db)
    scene1 = [resolution_eq28_m(output_snr(p["link_db"] + dl, ms["scene1_images"]))
              for dl in (0.0, 1.96 * sigma_link, -1.96 * sigma_link)]
    res = {n: {"db": round(main.residuals_db[n], 4), "sigma": round(main.residuals_sigma[n], 4),
               "used": n in USED} for n in ms}
    alt = fit(tuple(ms), preset_db, measurements={
        **ms, HELD_OUT: dataclasses.replace(held, band="C")})
    return {
        "method": "least squares in dB of the correlator's output SNR, each residual over the "
                  "measurement's own uncertainty; closed forms",
        "preset_link_db": round(preset_db, 4),
        "parameters": {k: round(v, 4) for k, v in p.items()},
        "used": list(USED),
        "measurements": {m.name: {"where": m.where, "value": m.value, "source": m.source,
                                  "uncertainty_db": m.uncertainty_db} for m in MEASUREMENTS},
        "residuals": res,
        "explains_used": main.explains,
        "held_out": {"name": HELD_OUT, "where": held.where, "paper": held.value,
                     "predicted": round(pred, 3), "ci95": [round(lo, 3), round(hi, 3)],
                     "unit": "m"},
        "resolution_scene1_m": round(scene1[0], 5),
        "resolution_scene1_ci95": [round(scene1[1], 5), round(scene1[2], 5)],
        "threshold_rho_db": {"order11": round(_db(threshold_rho(2047)), 3),
                             "order13": round(_db(threshold_rho(8191)), 3)},
        "all": {"parameters": {k: round(v, 4) for k, v in every.parameters.items()},
                "residuals_db": {k: round(v, 4) for k, v in every.residuals_db.items()},
                "explains": every.explains},
        "fig2f_on_c_band": {"parameters": {k: round(v, 4) for k, v in alt.parameters.items()},
                            "explains": alt.explains},
        "subsets": [{"members": list(f.used),
                     "left_out": {n: round(f.residuals_db[n], 3) for n in ms
                                  if n not in f.used},
                     "parameters": {k: round(v, 4) for k, v in f.parameters.items()}}
                    for f in sets],
    }
