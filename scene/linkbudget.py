r"""The physical link budget: from emitted power to echo amplitude.

Every quantity is per pixel (channel k, column c) or per column, in SI units. Amplitudes
are volts at the ADC input.

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

The receiver noise this budget sets (thermal, shot, ASE beat, per ADC sample) is
:mod:`cdma_lidar.scene.noise`'s.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from cdma_lidar.scene.model import InstrumentSpec

__all__ = [
    "LinkBudget",
    "link_gain_v_m2_per_w",
]

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
