r"""Receiver noise: the link budget's sources per ADC sample, per column and calibration shot.

Noise per ADC sample (white over the sampled band ``B = f_s / 2``, f_s = S * chip rate),
drawn as one Gaussian ``e`` per sample of every repetition::

    thermal     G^2 * i_n^2 * B                              TIA input noise i_n (A/sqrt(Hz))
    shot        G^2 * 2 q M^2 F (R_resp (P_sig + P_amb) + I_dark) B
                F = k_A M + (1 - k_A)(2 - 1/M)               APD excess noise (McIntyre)
                P_sig = sum_k P_rx[k,c]                      the column's mean signal power
    ASE beat    G^2 * 4 R_resp^2 M^2 B * sum_k P_rx[k,c]^2 / P_tx[k,c] * S_ase
                S_ase = n_sp h nu (g - 1),  n_sp = NF / 2    EDFA ASE density (W/Hz)
    quantisation  lsb^2 / 12                                 (made by the ADC, not drawn)

``P_rx`` is the link budget's (:mod:`cdma_lidar.scene.linkbudget`), ``G`` its
transimpedance and ``M`` the APD gain. The signal's own shot noise and the ASE beat
depend on what a column receives; the other sources do not. ``sequential_mixing``
(Supplementary Note 4) multiplies the signal-independent terms (thermal, dark current,
ambient shot, ASE) by K: the paper recorded the 40 channels one after another and summed
the records, so each record's noise is added K times. A scene may fix the noise instead
(``noise_rms_v``, ``snr_db``: :func:`fixed_noise_v`). Speckle fades each pixel's
received power (:func:`speckle_factors`). :class:`Noise` keeps the sources' coefficients
per samples-per-chip (its own cache).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from numpy.typing import NDArray

from cdma_lidar.scene.codebook import RenderSettings
from cdma_lidar.scene.linkbudget import LinkBudget
from cdma_lidar.scene.model import InstrumentSpec
from cdma_lidar.units import SPEED_OF_LIGHT_M_S

__all__ = [
    "ELEMENTARY_CHARGE_C",
    "PLANCK_J_S",
    "STREAM_CALIBRATE",
    "STREAM_SCAN",
    "Noise",
    "apd_excess_noise",
    "ase_density_w_per_hz",
    "fixed_noise_v",
    "noise_bandwidth_hz",
    "noise_coefficients",
    "speckle_factors",
]

#: Noise streams of a scene seed: scan columns, calibration shots, the speckle pattern.
STREAM_SCAN = 0
STREAM_CALIBRATE = 1
_STREAM_SPECKLE = 2

#: Elementary charge (C), exact (SI 2019).
ELEMENTARY_CHARGE_C = 1.602176634e-19
#: Planck constant (J s), exact (SI 2019).
PLANCK_J_S = 6.62607015e-34


def apd_excess_noise(gain: float, k_ratio: float) -> float:
    """McIntyre excess noise factor F = k M + (1 - k)(2 - 1/M) (1 for a PIN, M = 1)."""
    return float(k_ratio * gain + (1 - k_ratio) * (2 - 1 / gain))


def ase_density_w_per_hz(spec: InstrumentSpec) -> float:
    """EDFA ASE power spectral density (W/Hz, one polarisation) at its output.

    ``n_sp h nu (g - 1)`` with ``n_sp = NF / 2``, nu at the channels' mean wavelength.
    """
    g = 10 ** (spec.edfa_gain_db / 10)
    nsp = 10 ** (spec.edfa_noise_figure_db / 10) / 2
    nu = SPEED_OF_LIGHT_M_S / float(np.mean(spec.wavelengths_m))
    return float(nsp * PLANCK_J_S * nu * max(g - 1.0, 0.0))


def noise_bandwidth_hz(spec: InstrumentSpec, samples_per_chip: int) -> float:
    """Noise bandwidth B (Hz) of white noise drawn independently per sample: f_s / 2."""
    return spec.chip_rate_hz * samples_per_chip / 2


def noise_coefficients(budget: LinkBudget, samples_per_chip: int) -> dict[str, float]:
    """The noise sources' variances (V^2 per sample) at sample rate S * chip rate.

    ``thermal``, ``dark``, ``ambient``, ``quantisation`` in V^2; ``signal_shot`` in
    V^2 per W of the column's received power sum_k P_rx; ``ase`` in V^2 per W of
    sum_k P_rx^2 / P_tx. Sequential mixing is included.
    """
    spec = budget.spec
    b = noise_bandwidth_hz(spec, samples_per_chip)
    q = ELEMENTARY_CHARGE_C
    gm = budget.volts_per_rx_w / spec.responsivity_a_per_w  # V per A of primary photocurrent
    g_tia = gm / spec.apd_gain
    f = apd_excess_noise(spec.apd_gain, spec.apd_k_ratio)
    resp = spec.responsivity_a_per_w
    mix = float(spec.channels) if spec.sequential_mixing else 1.0
    lsb = spec.adc_full_scale_v / (1 << (spec.adc_bits - 1)) / spec.adc_gain
    return {
        "thermal": mix * (g_tia * spec.tia_noise_a_per_rthz) ** 2 * b,
        "dark": mix * gm**2 * 2 * q * f * spec.dark_current_a * b,
        "ambient": mix * gm**2 * 2 * q * f * resp * spec.ambient_power_w * b,
        "signal_shot": gm**2 * 2 * q * f * resp * b,
        "ase": mix * gm**2 * 4 * resp**2 * b * ase_density_w_per_hz(spec),
        "quantisation": lsb**2 / 12,
    }


def speckle_factors(cells: float, shape: tuple[int, ...], seed: int) -> NDArray[np.float64]:
    """Per-pixel speckle power fading: Gamma(cells, 1/cells) (mean 1, variance 1/cells).

    Fully developed speckle integrated over ``cells`` correlation cells of the aperture;
    fixed for a static scene (seeded by the noise seed only, not the frame), so averaging
    frames does not remove it.
    """
    rng = np.random.default_rng([seed, _STREAM_SPECKLE])
    return rng.gamma(cells, 1.0 / cells, size=shape)


def fixed_noise_v(spec: InstrumentSpec, amplitude_v: NDArray[np.float64],
                  lit: NDArray[np.bool_], calibration_amplitude_v: NDArray[np.float64],
                  unit_signal_power: float) -> float | None:
    """The noise rms (V) a scene fixes (``noise_rms_v``; ``snr_db`` against the median lit
    pixel's signal power, or the calibration echo's where nothing is lit), None: physical.
    ``amplitude_v`` (K, C) every pixel's echo amplitude at the default power."""
    if spec.noise_rms_v is not None:
        return float(spec.noise_rms_v)
    if spec.snr_db is None:
        return None
    if not np.any(lit):
        mean_a2 = float(np.mean(calibration_amplitude_v ** 2))
    else:
        mean_a2 = float(np.median(amplitude_v[lit] ** 2))
    return float(np.sqrt(mean_a2 * unit_signal_power / 10 ** (spec.snr_db / 10)))


class Noise:
    """Per-sample noise rms (V) of columns and calibration shots.

    ``budget``: the pixels' link budget; ``default_power_w`` (K, C) W;
    ``calibration_rx_per_w`` the received power per watt of one channel's calibration
    echo; ``fixed_v`` a noise the scene fixes (:func:`fixed_noise_v`, None: the link
    budget's).
    """

    def __init__(self, budget: LinkBudget, default_power_w: NDArray[np.float64],
                 calibration_rx_per_w: float, fixed_v: float | None) -> None:
        self.budget = budget
        self.default_power_w = default_power_w
        self.channels, self.columns = default_power_w.shape
        self.calibration_rx_per_w = calibration_rx_per_w
        self.fixed_v = fixed_v
        self._coefficients: dict[int, dict[str, float]] = {}

    def coefficients(self, samples_per_chip: int) -> dict[str, float]:
        """:func:`noise_coefficients` at ``samples_per_chip`` (computed once per S)."""
        coef = self._coefficients.get(samples_per_chip)
        if coef is None:
            coef = self._coefficients[samples_per_chip] = noise_coefficients(
                self.budget, samples_per_chip)
        return coef

    def terms(self, power_w: NDArray[np.float64], rx_per_w: NDArray[np.float64],
              samples_per_chip: int) -> dict[str, NDArray[np.float64]]:
        """Noise variance (V^2 per sample) of each source, per column.

        ``power_w`` and ``rx_per_w`` (K, C) or (K,): laser power (W) and received power per
        emitted watt of each channel (usually ``budget.rx_per_w`` or a column of it). Returns
        arrays of the columns' shape, (C,) or (), for ``thermal``, ``dark``, ``ambient``,
        ``signal_shot``, ``ase`` (signal-ASE beat) and ``quantisation``.
        """
        c = self.coefficients(samples_per_chip)
        p = np.asarray(power_w, dtype=np.float64)
        rx = np.asarray(rx_per_w, dtype=np.float64)
        p_rx = rx * p  # W
        shape = p_rx.shape[1:]
        out = {k: np.full(shape, v) for k, v in c.items()}
        out["signal_shot"] = c["signal_shot"] * p_rx.sum(axis=0)
        out["ase"] = c["ase"] * (p_rx * rx).sum(axis=0)  # sum P_rx^2 / P_tx
        return out

    def variance_v2(self, power_w: NDArray[np.float64], rx_per_w: NDArray[np.float64],
                    samples_per_chip: int, axis: int = 0) -> NDArray[np.float64]:
        """Variance (V^2 per sample) of the Gaussian noise drawn per column ((C,) or ()).

        All sources but quantisation (which the ADC itself makes); arguments as
        :meth:`terms` (``axis``: the channels' axis, 1 for (C, K) arrays).
        """
        c = self.coefficients(samples_per_chip)
        p_rx = np.asarray(rx_per_w) * np.asarray(power_w)
        return (c["thermal"] + c["dark"] + c["ambient"]
                + c["signal_shot"] * p_rx.sum(axis=axis)
                + c["ase"] * (p_rx * rx_per_w).sum(axis=axis))

    def rms_columns_v(self, cfg: RenderSettings,
                      power_w: NDArray[np.float64] | None = None) -> NDArray[np.float64]:
        """(C,) per-sample noise rms (V) of every column at laser power ``power_w`` (K, C)."""
        if self.fixed_v is not None:
            return np.full(self.columns, self.fixed_v)
        p = self.default_power_w if power_w is None else np.asarray(power_w, dtype=np.float64)
        return np.sqrt(self.variance_v2(p, self.budget.rx_per_w, cfg.samples_per_chip))

    def rms_v_at(self, column: int, cfg: RenderSettings,
                 power_w: NDArray[np.float64] | None = None,
                 calibration: bool = False) -> float:
        """Per-sample noise rms (V) of one column (or calibration shot) at power ``power_w``
        (K,). A fixed ``noise_rms_v`` or ``snr_db`` replaces every source."""
        if self.fixed_v is not None:
            return self.fixed_v
        p = self.default_power_w[:, column] if power_w is None else np.asarray(power_w)
        if calibration:
            rx = np.full(self.channels, self.calibration_rx_per_w)
        else:
            rx = self.budget.rx_per_w[:, column]
        return float(np.sqrt(self.variance_v2(p, rx, cfg.samples_per_chip)))

    def rms_items(self, cfg: RenderSettings,
                  items: Sequence[tuple[int, NDArray[np.float64] | None]],
                  calibration: bool) -> NDArray[np.float64]:
        """(B,) :meth:`rms_v_at` of each (column, power), for the batch at once: the
        same values (each column's sums over its channels run along one contiguous row,
        as a column's alone does; tests/scene/test_noise_blocks.py)."""
        if self.fixed_v is not None:
            return np.full(len(items), self.fixed_v)
        p = np.stack([self.default_power_w[:, col] if pw is None else np.asarray(pw)
                      for col, pw in items])
        if calibration:
            rx = np.full(p.shape, self.calibration_rx_per_w)
        else:
            rx = np.ascontiguousarray(self.budget.rx_per_w[:, [col for col, _ in items]].T)
        return np.sqrt(self.variance_v2(p, rx, cfg.samples_per_chip, axis=1))
