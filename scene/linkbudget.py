r"""The physical link budget: from emitted power to echo amplitude and receiver noise.

Every quantity is per pixel (channel k, column c) or per column, in SI units. Amplitudes
are volts at the ADC input; noise is given as variance (V^2) per ADC sample.

Echo (Lambertian target, beam smaller than the target, monostatic receiver)::

    P_rx[k,c] = P_tx[k,c] * rho * cos(theta) / pi * A_rx / r^2 * eta_rx * s[k,c]   (W)
    A[k,c]    = G_tia * R_resp * M * P_rx[k,c]                                      (V)
    A_rx      = pi * (D_rx / 2)^2                                                   (m^2)

``P_tx`` is the channel's mean optical power (the POWER matrix; NRZ on/off keying, so
the AC amplitude of the detected code equals the mean), ``rho`` the target's
reflectivity, ``theta`` the incidence angle, ``eta_rx`` the receive path's optical
efficiency (grating, mirror, filter), ``s`` the speckle fading factor (1 without speckle),
``R_resp`` the responsivity (A/W), ``M`` the APD gain, ``G_tia`` the transimpedance (ohm).
The product ``G_tia R_resp M eta_rx A_rx / pi`` is the link gain (V m^2 / W); a scene may
also give it directly (``link_gain_v_m2_per_w``), which then replaces the product.
The beam divergence sets the footprint ``w0 + r * divergence`` (reported in the truth);
the ray caster treats the footprint as a point (a footprint larger than the target would
lower P_rx by the fill factor, which is not modelled).

Noise per ADC sample (white over the sampled band ``B = f_s / 2``, f_s = S * chip rate)::

    thermal     G^2 * i_n^2 * B                              TIA input noise i_n (A/sqrt(Hz))
    shot        G^2 * 2 q M^2 F (R_resp (P_sig + P_amb) + I_dark) B
                F = k_A M + (1 - k_A)(2 - 1/M)               APD excess noise (McIntyre)
                P_sig = sum_k P_rx[k,c]                      the column's mean signal power
    ASE beat    G^2 * 4 R_resp^2 M^2 B * sum_k P_rx[k,c]^2 / P_tx[k,c] * S_ase
                S_ase = n_sp h nu (g - 1),  n_sp = NF / 2    EDFA ASE density (W/Hz)
    quantisation  lsb^2 / 12                                 (made by the ADC, not drawn)

``sequential_mixing`` (Supplementary Note 4) multiplies the signal-independent terms
(thermal, dark current, ambient shot, ASE) by K: the paper recorded the 40 channels one
after another and summed the records, so each record's noise is added K times.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from cdma_lidar.scene.model import InstrumentSpec
from cdma_lidar.units import SPEED_OF_LIGHT_M_S

__all__ = [
    "ELEMENTARY_CHARGE_C",
    "PLANCK_J_S",
    "LinkBudget",
    "apd_excess_noise",
    "ase_density_w_per_hz",
    "link_gain_v_m2_per_w",
    "noise_bandwidth_hz",
]

#: Elementary charge (C), exact (SI 2019).
ELEMENTARY_CHARGE_C = 1.602176634e-19
#: Planck constant (J s), exact (SI 2019).
PLANCK_J_S = 6.62607015e-34


def link_gain_v_m2_per_w(spec: InstrumentSpec) -> float:
    """Echo amplitude (V) per (W of laser power * reflectivity * cos / r^2 in m^-2).

    ``spec.link_gain_v_m2_per_w`` when the scene gives it, else
    ``G_tia * R_resp * M * eta_rx * A_rx / pi``.
    """
    if spec.link_gain_v_m2_per_w is not None:
        return float(spec.link_gain_v_m2_per_w)
    area = np.pi * (spec.rx_aperture_m / 2) ** 2
    return float(spec.tia_gain_ohm * spec.responsivity_a_per_w * spec.apd_gain
                 * spec.rx_efficiency * area / np.pi)


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


@dataclass(frozen=True)
class LinkBudget:
    """The link budget of one instrument over the pixels of its scene.

    ``rx_per_w`` (K, C): received optical power per watt emitted (W/W), 0 where nothing is
    hit (speckle included). Echo amplitude = ``volts_per_rx_w * rx_per_w * P_tx``.
    """

    spec: InstrumentSpec
    rx_per_w: NDArray[np.float64]

    @classmethod
    def of(cls, spec: InstrumentSpec, reflectivity: NDArray[np.float64],
           cos_incidence: NDArray[np.float64], range_m: NDArray[np.float64],
           speckle: NDArray[np.float64] | None = None) -> LinkBudget:
        """Budget of the hits (K, C) (NaN range / reflectivity where nothing is hit)."""
        lit = np.isfinite(range_m)
        r = np.where(lit, range_m, 1.0)
        area = np.pi * (spec.rx_aperture_m / 2) ** 2
        rx = np.where(lit, np.nan_to_num(reflectivity) * cos_incidence / np.pi * area / r**2
                      * spec.rx_efficiency, 0.0)
        if speckle is not None:
            rx = rx * speckle
        return cls(spec=spec, rx_per_w=rx)

    @property
    def volts_per_rx_w(self) -> float:
        """ADC-input volts per watt of received optical power: G_tia R_resp M (V/W).

        With an explicit ``link_gain_v_m2_per_w`` the scene's gain is honoured:
        ``link_gain * pi / (A_rx eta_rx)``.
        """
        spec = self.spec
        area = np.pi * (spec.rx_aperture_m / 2) ** 2
        return link_gain_v_m2_per_w(spec) * np.pi / (area * spec.rx_efficiency)

    @property
    def amplitude_per_w(self) -> NDArray[np.float64]:
        """(K, C) echo amplitude (V) per watt of laser power."""
        return self.volts_per_rx_w * self.rx_per_w

    def _current_gain(self) -> float:
        """Transimpedance times APD gain (V per A of primary photocurrent)."""
        return self.volts_per_rx_w / self.spec.responsivity_a_per_w

    def coefficients(self, samples_per_chip: int) -> dict[str, float]:
        """The noise sources' variances (V^2 per sample) at sample rate S * chip rate.

        ``thermal``, ``dark``, ``ambient``, ``quantisation`` in V^2; ``signal_shot`` in
        V^2 per W of the column's received power sum_k P_rx; ``ase`` in V^2 per W of
        sum_k P_rx^2 / P_tx. Sequential mixing is included.
        """
        spec = self.spec
        b = noise_bandwidth_hz(spec, samples_per_chip)
        q = ELEMENTARY_CHARGE_C
        gm = self._current_gain()  # V per A of primary photocurrent (G_tia * M)
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

    def noise_terms(self, power_w: NDArray[np.float64], rx_per_w: NDArray[np.float64],
                    samples_per_chip: int) -> dict[str, NDArray[np.float64]]:
        """Noise variance (V^2 per sample) of each source, per column.

        ``power_w`` and ``rx_per_w`` (K, C) or (K,): laser power (W) and received power per
        emitted watt of each channel (usually ``self.rx_per_w`` or a column of it). Returns
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

    def noise_variance_v2(self, power_w: NDArray[np.float64], rx_per_w: NDArray[np.float64],
                          samples_per_chip: int,
                          coefficients: dict[str, float] | None = None,
                          axis: int = 0) -> NDArray[np.float64]:
        """Variance (V^2 per sample) of the Gaussian noise drawn per column ((C,) or ()).

        All sources but quantisation (which the ADC itself makes); arguments as
        :meth:`noise_terms` (``coefficients``: :meth:`coefficients`, if already computed;
        ``axis``: the channels' axis, 1 for (C, K) arrays).
        """
        c = coefficients or self.coefficients(samples_per_chip)
        p_rx = np.asarray(rx_per_w) * np.asarray(power_w)
        return (c["thermal"] + c["dark"] + c["ambient"]
                + c["signal_shot"] * p_rx.sum(axis=axis)
                + c["ase"] * (p_rx * rx_per_w).sum(axis=axis))
