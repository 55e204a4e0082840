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


#: The paper's operating point, parameter by parameter (``paper-lab`` and the studies'
#: ``point=paper``). ``stated=False``: an assumption, with where it comes from.
ASSUMPTIONS: tuple[Parameter, ...] = (
    Parameter("chip rate", "62.5 Mchip/s", True, "Methods: AWG modulating at 62.5 MHz"),
    Parameter("code", "Gold, degree 11 (2047 chips)", True, "Methods: 11th-order Gold sequence"),
    Parameter("channels", "40, L-band 1570 nm + 0.875 nm steps", True,
              "Results (40 channels), Supp. Note 10 (L-band 1570-1605 nm)"),
    Parameter("grating", "600 grooves/mm, ruled", True, "Methods: Newport 33010FL01-550R"),
    Parameter("detector", "InGaAs APD, 400 MHz bandwidth", True,
              "Methods: Thorlabs APD430C (DC-400 MHz)"),
    Parameter("EDFA output", "about 100 mW", True, "Methods: EDFA100P up to around 100 mW"),
    Parameter("distances", "5 m and 10 m", True, "Results: scenes 1 and 2"),
    Parameter("sequential mixing", "noise added 40 times (multi-channel results)", True,
              "Supp. Note 4; off for Fig. 2c, one channel (nothing is mixed)"),
    Parameter("repeats", "1000 single-channel ranges", True, "Results, Fig. 2c"),
    Parameter("averaging", "10 records for the 3D scans", True,
              "Methods: 3D imaging averaged over ten repetitions"),
    Parameter("Fig. 11 simulation", "50 samples per chip, 1000 random delays, eq. 9's "
              "signed-maximum detector", True, "Supp. Note 8; Supp. Note 2, eq. 9 (argmax)"),
    Parameter("power per channel", "2.5 mW", False,
              "assumed: the 100 mW shared over 40 channels, the power the toolkit's link "
              "budget was set for (Fig. 3 scans); the paper's sequential recording gave each "
              "wavelength the whole EDFA output, which the unpublished link budget absorbs: "
              "only power x link gain matters, and Fig. 2c's 25.68 cm at 10 m (reproduced at "
              "this point) checks that product"),
    Parameter("Fig. 2f channels and averaging", "40 channels sequentially mixed, R = 10",
              False, "assumed: the text of Fig. 2f names neither; the multi-channel set-up "
              "of Fig. 2e and the averaging of the 3D scans (Methods)"),
    Parameter("Fig. 3b power", "half the per-channel power for each of the two lasers",
              False, "assumed: Methods: the two lasers are combined in a 50:50 coupler and "
              "amplified by the same EDFA (no power given)"),
    Parameter("Fig. 2c averaging", "R = 1", False,
              "assumed: each of the 1000 measurements one record (the text names no "
              "averaging for Fig. 2c)"),
    Parameter("Fig. 2c distance", "10 m", False,
              "assumed: the farther of the paper's two scenes (not stated for Fig. 2c)"),
    Parameter("samples per chip", "50", False,
              "assumed: the paper's own simulation rate (Supp. Note 8); the oscilloscope's "
              "rate is not given"),
    Parameter("peak refinement", "none (peak index)", False,
              "assumed: Methods describe the circular correlation's peak, no interpolation"),
    Parameter("link budget", "aperture 25.4 mm, APD gain 10, TIA 140 kohm, 10 pA/rtHz, "
              "EDFA NF 5 dB", False,
              "assumed: the toolkit's defaults (InstrumentSpec), chosen for the Fig. 3 scans"),
    Parameter("reflectivity", "0.5", False, "assumed: painted foam and cardboard (Methods)"),
    Parameter("grating incidence", "60 deg", False, "assumed: not stated"),
)


def assumptions_markdown() -> list[str]:
    """:data:`ASSUMPTIONS` as a Markdown table (lines)."""
    lines = ["| parameter | value | stated by the paper? | source |", "|---|---|---|---|"]
    for p in ASSUMPTIONS:
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


def judge(paper: Any, value: float | None, ci95: list[float | None] | None,
          *, decimals: int | None = None) -> str | None:
    """The verdict of ``value`` (with its 95 % interval, or None if exact) against ``paper``.

    Exact values (``ci95`` None): ``"exact"`` when ``value`` rounds to the printed number
    (``decimals``: the printed precision; default: as many as the printed number shows),
    else ``"differs"``. Measured values: ``"reproduced"`` when the printed number lies in
    the interval (for ``"> P"``: when the interval reaches P; an unbounded end counts as
    reaching), else ``"differs"``. None when the paper prints no number, we have none,
    or the run bounds neither end of the interval.
    """
    pv = printed_value(paper)
    if pv is None or value is None or (isinstance(value, float) and not math.isfinite(value)):
        return None
    op, p = pv
    if ci95 is None:
        if decimals is None:
            text = str(paper).split()[-1] if isinstance(paper, str) else repr(float(p))
            decimals = len(text.split(".")[1]) if "." in text else 0
            if text.endswith(".0"):
                decimals = 0
        return "exact" if round(float(value), decimals) == round(p, decimals) else "differs"
    lo, hi = ci95
    if lo is None and hi is None:
        return None  # the run bounds nothing: no verdict either way
    lo = -math.inf if lo is None else lo
    hi = math.inf if hi is None else hi
    if op == ">":
        return "reproduced" if hi >= p else "differs"
    if op == "<":
        return "reproduced" if lo <= p else "differs"
    return "reproduced" if lo <= p <= hi else "differs"


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
