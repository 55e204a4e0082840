"""The paper's operating point, its assumptions, and how a result is judged against the paper.

The paper: Y. Shen, Z. H. Lim and G. Zhou, "Identity-enabled CDMA LiDAR for massively
parallel ranging with a single-element receiver" (the copy this toolkit follows carries
no DOI or arXiv identifier; cite it by title and authors).

* :data:`PRESET` -- the scene preset ``paper-lab`` (``scene/presets/paper-lab.toml``):
  the instrument as the paper states it, every unstated parameter an assumption listed
  in :data:`ASSUMPTIONS` with its source.
* :data:`POINTS` -- the values of every paper study's ``point`` setting: ``default``
  (the toolkit's own instrument and settings) or ``paper`` (where the paper stood).
* :func:`entry` -- one summary.json entry of the paper contract: ``ours``, ``paper``
  (only what the paper prints: a number, or a string such as ``"> 125"``), ``unit``,
  ``paper_point``, ``ci95`` and ``verdict``.
* The 95 % intervals: :func:`wilson` (a binomial fraction), :func:`sigma_ci` (a standard
  deviation from n samples, chi-square) and :func:`crossing_ci` (where an error-rate
  curve sampled on a grid crosses a level: trial noise AND the grid step).
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass
from typing import Any

import numpy as np

from cdma_lidar.errors import out_of_range

__all__ = [
    "ASSUMPTIONS",
    "PAPER_CITATION",
    "POINTS",
    "PRESET",
    "Parameter",
    "assumptions_markdown",
    "check_point",
    "crossing_ci",
    "entry",
    "exact",
    "judge",
    "printed_value",
    "sigma_ci",
    "verdict_of",
    "wilson",
]

#: How the report and the docs cite the paper (the copy followed has no DOI or arXiv id).
PAPER_CITATION = ("Y. Shen, Z. H. Lim and G. Zhou, \"Identity-enabled CDMA LiDAR for "
                  "massively parallel ranging with a single-element receiver\" (National "
                  "University of Singapore; no DOI or arXiv identifier in the copy followed)")

#: The scene preset of the paper's laboratory set-up.
PRESET = "paper-lab"

#: Values of the ``point`` setting every paper study has.
POINTS = ("default", "paper")


@dataclass(frozen=True)
class Parameter:
    """One parameter of the paper's operating point: stated by the paper or assumed."""

    name: str
    value: str
    stated: bool
    source: str


#: The paper's operating point, parameter by parameter. ``stated=False``: an assumption,
#: with where it comes from. ``value`` here is a placeholder for the rows whose value the
#: presets and the studies' settings give: :func:`cdma_lidar.study.paper.operating_point`
#: fills them from what the studies actually run (so the table cannot disagree with them).
ASSUMPTIONS: tuple[Parameter, ...] = (
    Parameter("chip rate", "", True, "Methods: the AWG modulates at 62.5 MHz"),
    Parameter("code", "", True, "Methods: an 11th-order Gold sequence spanning 2047 bits"),
    Parameter("channels", "", True, "Results: 40 channels; Supp. Note 10: C band 1530-1565 "
              "nm and L band 1570-1605 nm"),
    Parameter("channel spacing", "", False,
              "inferred: Fig. 3b's 1587.500 and 1591.875 nm are five steps of 0.875 nm apart; "
              "the paper prints no spacing"),
    Parameter("band of each scene", "", False,
              "the paper (Methods): an L-band EDFA for scene 1 (5 m), a C-band EDFA for scene "
              "2 (10 m); the presets put both in the L band (scene 2's wavelengths set the "
              "scan geometry that fig3, note10 and the virtual device share, so moving them "
              "would move those results; its higher power per channel stands for the "
              "C-band EDFA's extra gain), and the joint calibration (papercal) gives the C "
              "band its own gain"),
    Parameter("grating", "", True, "Methods: Newport 33010FL01-550R, 600 grooves per mm, "
              "nominal blaze 28.7 deg"),
    Parameter("detector", "", True, "Methods: Thorlabs APD430C"),
    Parameter("EDFA output", "about 100 mW", True, "Methods: EDFA100P up to around 100 mW"),
    Parameter("distances", "5 m and 10 m", True, "Results: scenes 1 and 2"),
    Parameter("sequential mixing", "noise added 40 times (multi-channel results)", True,
              "Supp. Note 4; off for Fig. 2c, one channel (nothing is mixed)"),
    Parameter("repeats", "1000 single-channel ranges", True, "Results, Fig. 2c"),
    Parameter("averaging", "", True, "Results: each mixed echo is recorded 10 times and "
              "averaged"),
    Parameter("Fig. 11 and 2e simulation", "", True,
              "Supp. Note 8 (50 samples per chip); Supp. Note 2, eq. 9 (argmax)"),
    Parameter("samples per chip", "", False,
              "assumed: the oscilloscope's rate is not given; eq. 28's N_s x SNR does not "
              "depend on S for white noise, so the paper-lab runs use 4 (fast) and the "
              "single-channel runs the paper's simulation rate"),
    Parameter("power per channel", "", False,
              "assumed: the 100 mW shared over 40 channels; only power x link gain matters, "
              "and the joint calibration (papercal) fits that product"),
    Parameter("Fig. 2f channels and averaging", "", False,
              "assumed: the text of Fig. 2f names neither; the multi-channel set-up of Fig. "
              "2e and the averaging of the 3D scans (Methods)"),
    Parameter("Fig. 3b power", "half the per-channel power for each of the two lasers",
              False, "assumed: Methods: the two lasers are combined in a 50:50 coupler and "
              "amplified by the same EDFA (no power given)"),
    Parameter("Fig. 2c set-up", "", False,
              "assumed: the farther scene's distance, one record per range (the text names "
              "no averaging), the peak index without refinement (Methods)"),
    Parameter("link budget", "", False,
              "assumed: the toolkit's defaults (InstrumentSpec); the joint calibration "
              "(papercal) reports the link the paper's measurements need"),
    Parameter("reflectivity", "", False, "assumed: painted foam and cardboard (Methods)"),
    Parameter("grating incidence", "", False,
              "assumed: not stated; the eq26 study draws the angular step over incidence "
              "with the paper's 0.03 deg"),
)


def assumptions_markdown(params: tuple[Parameter, ...] = ASSUMPTIONS) -> list[str]:
    """``params`` (default :data:`ASSUMPTIONS`) as a Markdown table (lines)."""
    lines = ["| parameter | value | stated by the paper? | source |", "|---|---|---|---|"]
    for p in params:
        lines.append(f"| {p.name} | {p.value} | {'stated' if p.stated else '**assumed**'} | "
                     f"{p.source} |")
    return lines


def check_point(value: str) -> str:
    """The ``point`` setting's value, or a ConfigError naming the allowed ones."""
    if value not in POINTS:
        raise out_of_range("point", " or ".join(POINTS), value)
    return value


# ------------------------------------------------------------------ intervals


def wilson(errors: int, n: int, z: float = 1.96) -> tuple[float, float]:
    """95 % Wilson score interval of a binomial fraction ``errors / n`` (nan if n = 0)."""
    if n <= 0:
        return math.nan, math.nan
    p = errors / n
    den = 1 + z * z / n
    centre = (p + z * z / (2 * n)) / den
    half = z * math.sqrt(p * (1 - p) / n + z * z / (4 * n * n)) / den
    return max(centre - half, 0.0), min(centre + half, 1.0)


def sigma_ci(sigma: float, n: int, level: float = 0.95) -> tuple[float, float]:
    """Interval of a Gaussian standard deviation estimated from ``n`` samples (chi-square)."""
    a = (1 - level) / 2
    from scipy.stats import chi2  # deferred: scipy.stats costs 0.9 s at every CLI start-up

    return (sigma * math.sqrt((n - 1) / chi2.ppf(1 - a, n - 1)),
            sigma * math.sqrt((n - 1) / chi2.ppf(a, n - 1)))


def crossing_ci(x: Any, errors: Any, trials: Any, level: float = 0.10
                ) -> tuple[float | None, float | None]:
    """95 % interval of where an error rate rising with ``x`` crosses ``level``.

    Counts the grid's step as well as the trials' noise, with no model between grid
    points (only that the rate rises with x): the crossing lies above the largest x whose
    Wilson interval is wholly below the level, and below the smallest x whose interval is
    wholly above it. ``None`` for an end that the grid does not bound (below the first
    point, above the last). ``errors`` are rates, ``trials`` the count behind each.
    """
    x = np.asarray(x, float)
    order = np.argsort(x)
    x = x[order]
    err = np.asarray(errors, float)[order]
    n = np.broadcast_to(np.asarray(trials, float), x.shape)[order]
    bounds = [wilson(round(e * m), int(m)) for e, m in zip(err, n, strict=True)]
    above = [i for i, (lo, _) in enumerate(bounds) if lo > level]
    high = float(x[above[0]]) if above else None
    stop = above[0] if above else len(x)
    below = [i for i in range(stop) if bounds[i][1] < level]
    low = float(x[below[-1]]) if below else None
    return low, high


# ------------------------------------------------------------------ judging


_PRINTED = re.compile(r"^\s*(>|<|~)?\s*(-?[0-9.]+)(?:/([0-9.]+))?\s*$")


def printed_value(paper: Any) -> tuple[str, float] | None:
    """``"> 125"`` -> ``(">", 125.0)``, ``"2/3"`` -> ``("=", 0.667)``; a number ->
    ``("=", x)``; None if not numeric."""
    if isinstance(paper, bool) or paper is None:
        return None
    if isinstance(paper, int | float):
        return "=", float(paper)
    m = _PRINTED.match(str(paper))
    if not m:
        return None
    value = float(m.group(2)) / (float(m.group(3)) if m.group(3) else 1.0)
    return (m.group(1) or "="), value


def _printed_tolerance(paper: Any, p: float) -> float:
    """Half a unit of the printed number's last digit (``25.68`` -> 0.005; ``2/3`` -> 0)."""
    if not isinstance(paper, str | int | float) or isinstance(paper, bool):
        return 0.0
    text = str(paper).split()[-1]
    if "/" in text:
        return 0.0  # a fraction is exact
    if isinstance(paper, float) and not isinstance(paper, str):
        text = repr(paper)
    decimals = len(text.split(".")[1]) if "." in text and not text.endswith(".0") else 0
    return 0.5 * 10.0 ** -decimals


def verdict_of(op: str, p: float, lo: float | None, hi: float | None,
               tolerance: float = 0.0) -> str:
    """The three-word verdict of a 95 % interval [lo, hi] against a printed claim.

    ``op`` ``">"`` (the paper's "more than p"): *reproduced* when the lower bound is at
    least p, *differs* when the upper bound is below p, *consistent* otherwise (the
    interval holds p). ``"<"``: the mirror image. ``"="`` (a point value, printed to
    ``tolerance`` either side): *reproduced* when the interval lies inside
    [p - tolerance, p + tolerance], *differs* when it lies wholly outside, *consistent*
    when it holds part of it. An end the run does not bound (None) is infinite.
    """
    lo = -math.inf if lo is None else float(lo)
    hi = math.inf if hi is None else float(hi)
    if op == ">":
        return "reproduced" if lo >= p else ("differs" if hi < p else "consistent")
    if op == "<":
        return "reproduced" if hi <= p else ("differs" if lo > p else "consistent")
    if p - tolerance <= lo and hi <= p + tolerance:
        return "reproduced"
    return "differs" if hi < p - tolerance or lo > p + tolerance else "consistent"


def judge(paper: Any, value: float | None, ci95: list[float | None] | None,
          *, decimals: int | None = None, tolerance: float | None = None) -> str | None:
    """The verdict of ``value`` (with its 95 % interval, or None if exact) against ``paper``.

    Three words (:func:`verdict_of`): *reproduced*, *consistent*, *differs*. An exact value
    (``ci95`` None) is its own interval, compared at the printed precision (``decimals``,
    default: as many as the printed number shows), so it is reproduced or differs. A
    point value's tolerance is half the printed last digit unless ``tolerance`` is given.
    None when the paper prints no number or we have none.
    """
    pv = printed_value(paper)
    if pv is None or value is None or (isinstance(value, float) and not math.isfinite(value)):
        return None
    op, p = pv
    if ci95 is None:
        ci95 = [value, value]
        if decimals is not None:
            tolerance = 0.5 * 10.0 ** -decimals
    if tolerance is None:
        tolerance = _printed_tolerance(paper, p) if op == "=" else 0.0
    return verdict_of(op, p, ci95[0], ci95[1], tolerance)


def _clean(x: Any) -> Any:
    if x is None or isinstance(x, str):
        return x
    if isinstance(x, bool):
        return x
    if isinstance(x, int | np.integer):
        return int(x)
    x = float(x)
    return x if math.isfinite(x) else None


def entry(ours: Any, paper: Any, unit: str, *, paper_point: Any = None,
          ci95: tuple[Any, Any] | list[Any] | None = None,
          paper_point_ci95: tuple[Any, Any] | list[Any] | None = None,
          verdict: str | None = None, exact: bool = False, **extra: Any) -> dict[str, Any]:
    """One summary.json entry of the paper contract.

    ``paper`` holds only what the paper prints (None if it prints nothing); ``ci95`` is
    ``[low, high]`` for ``ours`` (an end may be None: unbounded by the run) or None for an
    exact value. The verdict, unless given, judges ``paper_point`` (with
    ``paper_point_ci95``) when there is one, else ``ours``. ``extra`` (e.g. ``cause``)
    is kept.
    """
    ci = None if ci95 is None else [_clean(ci95[0]), _clean(ci95[1])]
    pci = None if paper_point_ci95 is None else [_clean(paper_point_ci95[0]),
                                                 _clean(paper_point_ci95[1])]
    out: dict[str, Any] = {"ours": _clean(ours), "paper": _clean(paper), "unit": unit,
                           "paper_point": _clean(paper_point), "ci95": ci}
    if pci is not None:
        out["paper_point_ci95"] = pci
    if verdict is None:
        at = out["paper_point"] if out["paper_point"] is not None else out["ours"]
        at_ci = pci if out["paper_point"] is not None else ci
        verdict = judge(paper, at, None if exact else (at_ci or [at, at]))
    out["verdict"] = verdict
    out.update({k: _clean(v) if not isinstance(v, dict | list) else v
                for k, v in extra.items()})
    return out


def exact(ours: Any, paper: Any, unit: str, **extra: Any) -> dict[str, Any]:
    """An exact result (counted or computed, no sampling): its own paper point, no interval."""
    return entry(ours, paper, unit, paper_point=ours, exact=True, **extra)
