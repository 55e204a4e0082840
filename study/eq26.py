"""The ``eq26`` study: the paper's figures that follow from the instrument's parameters.

Five results of the paper that need no trials, each computed from the ``paper-lab``
instrument (:mod:`cdma_lidar.study.paperlab`) and checked against the toolkit's model:

* ``range_resolution_eq26_m`` -- Supp. Note 7, eq. 26: dR = c / (2 B) at B = 62.5 MHz
  ("limited to 2.4 m").
* ``max_unambiguous_distance_m`` -- Supp. Note 2, eq. 9: d_max = c N / (2 w_c); the paper
  prints the formula only. The receive chain's circular correlation is checked to fold
  an echo at d_max + ``fold_m`` onto ``fold_m`` (``fold_check_m``).
* ``angular_resolution_deg`` -- the vertical step between adjacent channels through the
  grating (Supp. Note 10, eq. 47), mean over the 40 channels at rotation 0 ("an angular
  resolution of 0.03 deg").
* ``psd_main_lobe_null_hz`` -- Fig. 1e / Supp. Note 3: the first null of the power
  spectral density of the NRZ Gold code ("the boundary of the main lobe occurs at
  1/T_c"), from the code's line spectrum; the figure draws sequences 1, 2 and their mix.
* ``sequential_mixing_noise_ratio`` -- Supp. Note 4: the signal-independent noise of the
  sequentially recorded and summed channels over that of a simultaneous recording, from
  the link budget ("redundantly accounted for 40 times"; eq. 20), and measured on noise
  the instrument renders (no echo) in the cause;
* ``aligned_averaging_noise_ratio`` -- Supp. Note 4, eq. 25: the noise variance of the
  mean of 40 aligned records of the sequential sum over one simultaneous record, measured
  on rendered noise, with the F distribution's 95 % interval ("40 zeta^2 = delta^2").

``point`` is accepted for uniformity: the paper's point is this study's only one.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from cdma_lidar.errors import out_of_range
from cdma_lidar.firmware_model.gold import bipolar, gold_code
from cdma_lidar.firmware_model.pairs import preferred_pairs
from cdma_lidar.host.ranging import lag_to_range_m
from cdma_lidar.optics.grating import GratingGeometry, azimuth_elevation_deg
from cdma_lidar.scene import load_scene
from cdma_lidar.scene.instrument import Instrument
from cdma_lidar.study.engine import RunContext, Setting, Study, Table
from cdma_lidar.study.figures import new_figure, save_figure
from cdma_lidar.study.paperlab import PRESET, check_point, entry, exact
from cdma_lidar.units import SPEED_OF_LIGHT_M_S

__all__ = ["BLAZE_DEG", "REPORT_NOTE", "STUDY", "angular_step_deg", "eq26_task", "folded_range_m",
           "incidence_curve", "psd_lines", "variance_ratio_ci"]

#: Paper, Methods: the grating's nominal blaze angle (deg; its Littrow incidence).
BLAZE_DEG = 28.7
#: Paper: "a theoretical angular resolution of 0.03°" (deg), printed to two decimals.
PAPER_ANGLE_DEG = 0.03

#: Paper, Supp. Note 4, eq. 25: averaging 40 aligned repetitions before summing restores
#: the noise of a simultaneous recording.
PAPER_EQ25 = "40 zeta^2 = delta^2"

REPORT_NOTE = (
    "Exact figures of the paper's instrument. Eq. 26's 2.4 m is the chip's range (the "
    "autocorrelation's FWHM), which the paper sets aside for its own 2 sigma definition "
    "(Fig. 2c). Eq. 9 gives the unambiguous distance of one code period; the "
    "receive chain folds a farther echo back by exactly that distance (checked in the "
    "run). The angular step comes from the grating's equation at the paper's 600 "
    "grooves/mm and 0.875 nm channel spacing; its value depends on the incidence angle, "
    "which the paper does not state (60 deg assumed). The PSD's main lobe ends at the "
    "chip rate for every code and for their mix (Fig. 1e). Sequential mixing multiplies "
    "the signal-independent noise power by the channel count (Supp. Note 4)."
)


def psd_lines(code_bits: np.ndarray, chip_rate_hz: float) -> tuple[np.ndarray, np.ndarray]:
    """Line spectrum of a periodic bipolar NRZ code: frequencies (Hz) and relative power.

    The period is N chips, so lines sit at q f_c / N with power
    |DFT(chips)[q mod N]|^2 sinc^2(q / N) (the rectangular chip's envelope), q = 0..3N.
    """
    chips = bipolar(code_bits).astype(np.float64)
    n = chips.size
    q = np.arange(3 * n + 1)
    spec = np.abs(np.fft.fft(chips)) ** 2 / n**2
    power = spec[q % n] * np.sinc(q / n) ** 2
    return q * chip_rate_hz / n, power


def angular_step_deg(grooves_per_mm: float, incidence_deg: float,
                     wavelengths_m: np.ndarray) -> float:
    """Mean angle (deg) between adjacent channels' first-order beams at rotation 0."""
    d = GratingGeometry(grooves_per_mm, incidence_deg).directions(
        np.asarray(wavelengths_m), np.zeros(1)).reshape(-1, 3)
    cos = np.clip(np.sum(d[1:] * d[:-1], axis=1), -1.0, 1.0)
    return float(np.degrees(np.mean(np.arccos(cos))))


def incidence_curve(grooves_per_mm: float, wavelengths_m: np.ndarray,
                    step_deg: float = 0.25) -> tuple[np.ndarray, np.ndarray]:
    """The angular step (deg) over incidence 0..85 deg (``step_deg`` apart)."""
    inc = np.arange(0.0, 85.0 + step_deg / 2, step_deg)
    return inc, np.array([angular_step_deg(grooves_per_mm, float(i), wavelengths_m)
                          for i in inc])


def folded_range_m(distance_m: float, degree: int, chip_rate_hz: float, s: int = 4) -> float:
    """The range the circular correlation of one period gives an echo at ``distance_m``.

    The echo's delay in samples is taken modulo the period N S (what a periodic code
    does), correlated with the code over every lag, and the peak lag turned into a range.
    """
    code = gold_code(*_pair(degree), 0)
    ref = np.repeat(bipolar(code).astype(np.float64), s)
    ns = ref.size
    delay = round(distance_m * 2 / SPEED_OF_LIGHT_M_S * chip_rate_hz * s)
    echo = np.roll(ref, delay % ns)
    corr = np.fft.irfft(np.fft.rfft(echo) * np.conj(np.fft.rfft(ref)), ns)
    return float(lag_to_range_m(int(np.argmax(corr)), s, chip_rate_hz))


def variance_ratio_ci(ratio: float, n1: int, n2: int) -> tuple[float | None, float | None]:
    """95 % interval of a ratio of two independent sample variances (n1, n2 samples; F)."""
    if n1 < 2 or n2 < 2:
        return None, None
    from scipy.stats import f  # deferred: scipy.stats costs 0.9 s at every CLI start-up

    return (ratio / float(f.ppf(0.975, n1 - 1, n2 - 1)),
            ratio / float(f.ppf(0.025, n1 - 1, n2 - 1)))


def _pair(degree: int) -> tuple[tuple[int, ...], tuple[int, ...]]:
    return preferred_pairs(degree)[0]


def _grid(options: Any) -> list[dict]:
    check_point(options["point"])
    fold = float(options["fold_m"])
    if not 0.0 < fold < 1000.0:
        raise out_of_range("fold_m", "0..1000 m", fold)
    return [{"scene": PRESET, "fold_m": fold}]


def eq26_task(params: dict, seed: np.random.SeedSequence) -> dict[str, Any]:
    """Every figure of the study (no randomness: ``seed`` is unused)."""
    del seed
    inst = Instrument(load_scene(str(params["scene"])), seed=0)
    spec = inst.spec
    f_c, degree, n = spec.chip_rate_hz, spec.code_degree, spec.code_length
    d_max = SPEED_OF_LIGHT_M_S * n / (2.0 * f_c)
    fold = float(params["fold_m"])
    wl = np.asarray(spec.wavelengths_m)
    _, el = azimuth_elevation_deg(spec.geometry().directions(wl, np.zeros(1)).reshape(-1, 3))
    steps = np.abs(np.diff(el))
    freq, power = psd_lines(gold_code(spec.poly_u, spec.poly_v, 0), f_c)
    floor = 1e-9 * power[1:].max()
    nulls = freq[1:][np.flatnonzero(power[1:] <= floor)]
    null, second = float(nulls[0]), float(nulls[nulls > 1.5 * nulls[0]][0])
    mixed = Instrument(load_scene(str(params["scene"]), {"sequential_mixing": True}), seed=0)
    single = Instrument(load_scene(str(params["scene"]), {"sequential_mixing": False}), seed=0)
    ratio = [m.noise.coefficients(spec.samples_per_chip)["thermal"] for m in (mixed, single)]
    # eqs. 20 and 25 measured on rendered noise (no echo): one record of the sequential sum,
    # the mean of ``spec.channels`` aligned records of it, and one simultaneous record
    var = {}
    for name, mix, r in (("mixed_r1", True, 1), ("mixed_aligned", True, spec.channels),
                         ("single", False, 1)):
        inst = Instrument(load_scene(str(params["scene"]), {
            "reflectivity": 0.0, "sequential_mixing": mix, "averages": r}), seed=11)
        x = inst.render(0).astype(np.float64).reshape(r, -1).mean(axis=0)
        var[name] = float(np.var(x, ddof=1))
        samples = x.size
    return {"chip_rate_hz": f_c, "code_length": n, "channels": spec.channels,
            "range_resolution_eq26_m": SPEED_OF_LIGHT_M_S / (2.0 * f_c),
            "max_unambiguous_distance_m": d_max,
            "fold_check_m": folded_range_m(d_max + fold, degree, f_c),
            "angular_resolution_deg": float(np.mean(steps)),
            "angular_step_min_deg": float(steps.min()),
            "angular_step_max_deg": float(steps.max()),
            "psd_main_lobe_null_hz": null, "psd_second_null_hz": second,
            "sequential_mixing_noise_ratio": ratio[0] / ratio[1],
            "noise_samples": samples,
            "measured_mixing_ratio": var["mixed_r1"] / var["single"],
            "aligned_averaging_noise_ratio": var["mixed_aligned"] / var["single"]}


def _reduce(table: Table, ctx: RunContext) -> dict[str, Any]:
    row = table.rows[0]
    inst = Instrument(load_scene(str(row["scene"])), seed=0)
    spec = inst.spec
    fig, ax = new_figure(6.5, 4.0)
    for k, label in ((0, "sequence 1"), (1, "sequence 2")):
        f, p = psd_lines(gold_code(spec.poly_u, spec.poly_v, k), spec.chip_rate_hz)
        ax.plot(f / 1e6, 10 * np.log10(p + 1e-12), lw=0.6, label=label)
    f, p1 = psd_lines(gold_code(spec.poly_u, spec.poly_v, 0), spec.chip_rate_hz)
    _, p2 = psd_lines(gold_code(spec.poly_u, spec.poly_v, 1), spec.chip_rate_hz)
    ax.plot(f / 1e6, 10 * np.log10((p1 + p2) / 2 + 1e-12), lw=0.6, color="k", alpha=0.5,
            label="mixed")
    n = spec.code_length
    env = (n + 1) / n**2 * np.sinc(f / spec.chip_rate_hz) ** 2  # eq. 14's line weights
    ax.plot(f / 1e6, 10 * np.log10(env + 1e-12), color="k", ls="--", lw=1.0,
            label="paper: eq. 14 envelope (Supp. Fig. 6a, from the equation)")
    ax.axvline(row["psd_main_lobe_null_hz"] / 1e6, color="tab:red", ls=":",
               label="first null (1/T_c)")
    ax.set_ylim(-80, 0)
    ax.set_xlabel("frequency (MHz)")
    ax.set_ylabel("PSD (dB, relative)")
    ax.set_title("Fig. 1e: PSD of the spread-spectrum codes (ours, line spectrum)", fontsize=9)
    ax.legend(fontsize=7)
    save_figure(fig, ctx.out / "eq26.png")
    inc, step = incidence_curve(spec.grooves_per_mm, np.asarray(spec.wavelengths_m))
    rounds = np.round(step, 2) == PAPER_ANGLE_DEG  # the printed 0.03 at its precision
    lo_inc, hi_inc = float(inc[rounds].min()), float(inc[rounds].max())
    at = {name: angular_step_deg(spec.grooves_per_mm, a, np.asarray(spec.wavelengths_m))
          for name, a in (("normal", 0.0), ("blaze", BLAZE_DEG), ("preset", spec.incidence_deg))}
    fig, ax = new_figure(6.0, 3.8)
    ax.plot(inc, step, color="tab:blue", label="ours: adjacent channels' beams, grating "
            f"{spec.grooves_per_mm:g} /mm, {np.mean(np.diff(spec.wavelengths_m)) * 1e9:.3f} nm")
    ax.axhline(PAPER_ANGLE_DEG, color="k", ls="--", lw=1.0, label="paper: 0.03 deg (its text)")
    ax.axvspan(lo_inc, hi_inc, color="tab:green", alpha=0.15,
               label=f"rounds to 0.03 deg: incidence {lo_inc:g}-{hi_inc:g} deg")
    ax.axvline(BLAZE_DEG, color="tab:red", ls=":", lw=1.0,
               label=f"Littrow at the blaze {BLAZE_DEG:g} deg: {at['blaze']:.4f} deg")
    ax.axvline(spec.incidence_deg, color="tab:gray", ls="-.", lw=1.0,
               label=f"preset {spec.incidence_deg:g} deg: {at['preset']:.4f} deg")
    ax.set_xlabel("incidence angle (deg)")
    ax.set_ylabel("angular resolution (deg)")
    ax.set_title("Angular resolution over the grating's incidence (the paper states none)",
                 fontsize=9)
    ax.legend(fontsize=6)
    save_figure(fig, ctx.out / "eq26_incidence.png")
    n = int(row["noise_samples"])
    ci25 = variance_ratio_ci(float(row["aligned_averaging_noise_ratio"]), n, n)
    fold, back = float(row["fold_m"]), float(row["fold_check_m"])
    folds = math.isclose(back, fold, abs_tol=2 * lag_to_range_m(1, spec.samples_per_chip,
                                                                spec.chip_rate_hz))
    return {
        "range_resolution_eq26_m": exact(row["range_resolution_eq26_m"], 2.4, "m",
                                         cause="c / (2 B) at B = 62.5 MHz"),
        "max_unambiguous_distance_m": exact(
            row["max_unambiguous_distance_m"], None, "m",
            verdict="exact" if folds else "differs",
            derived=f"eq. 9: c N / (2 w_c), N = {row['code_length']}",
            cause=f"an echo at d_max + {fold:g} m ranges as {back:.2f} m in the circular "
                  "correlation"),
        "angular_resolution_deg": exact(
            row["angular_resolution_deg"], 0.03, "deg",
            cause=f"grating steps {row['angular_step_min_deg']:.4f}-"
                  f"{row['angular_step_max_deg']:.4f} deg over {row['channels']} channels"),
        "incidence_for_paper_angle_deg": exact(
            lo_inc, None, "deg",
            derived=f"the step rounds to the paper's 0.03 deg for incidence {lo_inc:g}-"
                    f"{hi_inc:g} deg (grid 0.25 deg); {at['normal']:.4f} deg at normal "
                    f"incidence, {at['blaze']:.4f} at Littrow on the blaze ({BLAZE_DEG:g} "
                    f"deg), {at['preset']:.4f} at the preset's {spec.incidence_deg:g} deg"),
        "bandpass_second_null_hz": exact(
            row["psd_second_null_hz"], 125e6, "Hz",
            verdict="exact" if math.isclose(row["psd_second_null_hz"], 2 * row["chip_rate_hz"])
            else "differs",
            derived="2/T_c: the PSD's second null, where the paper's band-pass 'second "
                    "sidelobe (125 MHz)' sits"),
        "psd_main_lobe_null_hz": exact(
            row["psd_main_lobe_null_hz"], None, "Hz",
            verdict="exact" if math.isclose(row["psd_main_lobe_null_hz"], row["chip_rate_hz"])
            else "differs", derived="1/T_c (Supp. Note 3)"),
        "sequential_mixing_noise_ratio": exact(
            row["sequential_mixing_noise_ratio"], 40, "1",
            cause="thermal noise power, sequential over simultaneous (link budget); measured "
                  f"on rendered noise: {row['measured_mixing_ratio']:.2f}"),
        "aligned_averaging_noise_ratio": entry(
            row["aligned_averaging_noise_ratio"], PAPER_EQ25, "1", ci95=ci25,
            paper_point=row["aligned_averaging_noise_ratio"], paper_point_ci95=ci25,
            verdict=None if ci25[0] is None else ("reproduced" if ci25[0] <= 1.0 <= ci25[1]
                                                   else "differs"),
            cause=f"rendered noise, no echo: the mean of {row['channels']} aligned records of "
                  f"the sequential sum over one simultaneous record, {n} samples each "
                  "(reproduced when the F interval holds 1, i.e. 40 zeta^2 = delta^2)"),
    }


STUDY = Study(
    name="eq26",
    description="the instrument's exact figures: eq. 26 range resolution, eq. 9 unambiguous "
                "distance, angular step, the codes' PSD (Fig. 1e), Supp. Note 4's noise factor",
    grid=_grid,
    task=eq26_task,
    reduce=_reduce,
    settings=(
        Setting("fold_m", 5.0, "range beyond d_max used to check the fold (m)"),
        Setting("point", "default", "default or paper: one point here, the paper's own"),
    ),
    version="2",
)
