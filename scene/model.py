"""Scene model: the instrument's true parameters and the objects in front of it.

A :class:`Scene` holds an :class:`InstrumentSpec` (the simulated board, optics and
photodiode: TRUE values, plus the ``nominal_*`` ones the device announces), the
:class:`ObjectSpec` objects in the field and the :class:`Calibration` target. Scenes are
read from TOML by :mod:`cdma_lidar.scene.scenefile` and looked up by
:mod:`cdma_lidar.scene.loader`; every default value is declared here, once, as a dataclass
field default, and the scene-file reader takes its defaults from these fields.

Units: metres, seconds, watts, volts, degrees, hertz; lags in samples, codes in chips.

Frames: the sensor frame of :mod:`cdma_lidar.optics.grating` (x forward, y left, z up, origin
at the grating) is the scene's global frame. Object orientation is ``[yaw, pitch, roll]``
in degrees, applied as R = Rz(yaw) @ Ry(pitch) @ Rx(roll) to the object's local axes.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np
from numpy.typing import NDArray

from cdma_lidar.optics.grating import GratingGeometry

__all__ = [
    "FIDELITY_LEVELS",
    "OBJECT_KINDS",
    "Calibration",
    "Ghost",
    "InstrumentSpec",
    "ObjectSpec",
    "OtherUser",
    "Scene",
    "field_default",
    "rotation_matrix",
]

#: The kinds of :class:`ObjectSpec`.
OBJECT_KINDS = ("plane", "box", "sphere", "text")

#: How faithfully the instrument renders a column (scene option ``fidelity``), most
#: faithful first: ``exact`` gives every repetition's samples their own noise and
#: quantisation (the scan draws their sum from its exact distribution,
#: :func:`cdma_lidar.scene.instrument.draw_repetition_sum`);
#: ``accumulated`` draws the sum of the R quantised repetitions directly, where the noise
#: spans at least :data:`cdma_lidar.scene.instrument.ACCUMULATED_MIN_NOISE_LSB` LSB and
#: nothing clips (other columns fall back to ``exact``). docs/scene.md gives each
#: level's validity condition and measured error.
FIDELITY_LEVELS = ("exact", "accumulated")


def field_default(cls: type, name: str) -> Any:
    """The default declared for dataclass field ``name`` of ``cls``.

    A field with a ``default_factory`` gives a fresh value from it. Raises ``KeyError``
    for a field without a default (or no such field).
    """
    for f in dataclasses.fields(cls):
        if f.name != name:
            continue
        if f.default is not dataclasses.MISSING:
            return f.default
        if f.default_factory is not dataclasses.MISSING:
            return f.default_factory()
        break
    raise KeyError(f"{cls.__name__}.{name} has no default")


def rotation_matrix(yaw_pitch_roll_deg: NDArray[np.float64]) -> NDArray[np.float64]:
    """R = Rz(yaw) @ Ry(pitch) @ Rx(roll) (deg); columns are the local axes in the scene frame."""
    y, p, r = np.deg2rad(np.asarray(yaw_pitch_roll_deg, dtype=np.float64))
    rz = np.array([[np.cos(y), -np.sin(y), 0.0], [np.sin(y), np.cos(y), 0.0], [0.0, 0.0, 1.0]])
    ry = np.array([[np.cos(p), 0.0, np.sin(p)], [0.0, 1.0, 0.0], [-np.sin(p), 0.0, np.cos(p)]])
    rx = np.array([[1.0, 0.0, 0.0], [0.0, np.cos(r), -np.sin(r)], [0.0, np.sin(r), np.cos(r)]])
    return rz @ ry @ rx


# ---------------------------------------------------------------------------------------
# the instrument

@dataclass(frozen=True, kw_only=True)
class Ghost:
    """A grating ghost: a fixed-distance spurious echo with the channel's own code (Note 5).

    Present at every pixel (channel, column) with channel in ``channels`` and column in
    ``columns`` (empty tuple: every channel / every column). Its amplitude does not fall
    with the target's distance.
    """

    distance_m: float
    amplitude_v: float
    channels: tuple[int, ...] = ()
    columns: tuple[int, ...] = ()


@dataclass(frozen=True, kw_only=True)
class OtherUser:
    """Another LiDAR whose light reaches our photodiode (Note 11).

    It emits Gold member ``code_index`` of the same pair, polarity-modulated by its own
    ``uid`` over ``uid_bits`` code periods. ``delay_s`` is the start of its UID frame
    relative to ours as seen at our ADC (its asynchronous start plus the one-way flight:
    in the TOML, ``distance_m`` gives ``delay_s = distance_m / c``); ``amplitude_v`` is its
    amplitude at our detector. Present on every column in ``columns`` (empty: all).
    """

    uid: int
    code_index: int = 0
    delay_s: float
    amplitude_v: float
    uid_bits: int = 3
    columns: tuple[int, ...] = ()


@dataclass(frozen=True, kw_only=True)
class Calibration:
    """The zeroth-order beam-trap target (Note 6): all channels see it in calibration mode."""

    target_distance_m: float = 0.5
    reflectivity: float = 0.9
    #: fraction of each channel's power that goes to the zeroth order and back (two passes)
    zeroth_order_efficiency: float = 0.02


@dataclass(frozen=True, kw_only=True)
class InstrumentSpec:
    """True parameters of the simulated instrument; ``nominal_*`` is what it announces.

    Signal chain per pixel (:mod:`cdma_lidar.scene.linkbudget` has the equations): the
    received optical power ``P_rx = P_tx * reflectivity * cos(incidence) / pi * A_rx / r**2
    * rx_efficiency`` (Lambertian target), the echo amplitude at the ADC input
    ``A = tia_gain_ohm * responsivity * apd_gain * P_rx`` (V), and white Gaussian noise
    from the TIA, the APD's shot and dark-current noise (with excess noise), ambient
    light and the EDFA's ASE, none of which depends on the scene's distance. The detector
    output is ``A * code(t - tau)`` (bipolar NRZ, AC coupled) filtered by the detector's
    transfer function; the ADC maps volts to codes with ``round(gain * v / lsb + offset)``,
    ``lsb = adc_full_scale_v / 2**(adc_bits - 1)``, clipped to ``adc_bits``.

    Overrides of the physical budget: ``link_gain_v_m2_per_w`` replaces the product of the
    receive chain's gains, ``noise_rms_v`` fixes the noise rms (V per sample) and
    ``snr_db`` sets it relative to the median lit pixel's echo (both replace the physical
    noise; ``snr_db`` rescales the noise to the scene, so a range sweep with it shows no
    range limit).

    The arrays (wavelengths, rotations, laser power) and the nominal grating have no
    default here: a scene file gives them in shorthand (a wavelength comb, a field of
    view and a column count, one power for every channel; the nominal grating defaults to
    the true one), see :mod:`cdma_lidar.scene.scenefile`.
    """

    wavelengths_m: NDArray[np.float64]
    rotations_deg: NDArray[np.float64]
    grooves_per_mm: float = 600.0
    incidence_deg: float = 60.0
    tilt_deg: float | None = None
    nominal_grooves_per_mm: float
    nominal_incidence_deg: float
    nominal_tilt_deg: float | None = None
    chip_rate_hz: float = 62.5e6
    samples_per_chip: int = 4
    averages: int = 10
    poly_u: tuple[int, ...] = (11, 2)
    poly_v: tuple[int, ...] = (11, 8, 5, 2)
    code_index: tuple[int, ...] | None = None
    uid_bits: int = 1
    uid: int = 0
    adc_bits: int = 12
    adc_gain: float = 1.0
    adc_offset: float = 0.0
    adc_full_scale_v: float = 1.0
    #: laser power per channel (W), shape (K,)
    laser_power_w: NDArray[np.float64]
    max_pixel_power_w: float = 10e-3
    total_power_cap_w: float = 0.2
    # -- the link budget (cdma_lidar.scene.linkbudget) --
    #: collimated beam diameter at the grating (m) and full divergence angle (rad): the
    #: footprint ``beam_waist_m + r * beam_divergence_rad`` reported in the truth
    beam_waist_m: float = 0.87e-3
    beam_divergence_rad: float = 2.3e-3
    #: receive aperture diameter (m; the parabolic mirror) and optical efficiency of the
    #: receive path (grating, mirror, filter; 0..1)
    rx_aperture_m: float = 25.4e-3
    rx_efficiency: float = 0.5
    #: photodiode responsivity (A/W), APD gain M and ionisation ratio k (excess noise)
    responsivity_a_per_w: float = 0.9
    apd_gain: float = 10.0
    apd_k_ratio: float = 0.5
    #: primary dark current (A)
    dark_current_a: float = 10e-9
    #: transimpedance (ohm, to the ADC input) and its input current noise (A/sqrt(Hz))
    tia_gain_ohm: float = 1.4e5
    tia_noise_a_per_rthz: float = 10e-12
    #: EDFA gain (dB) and noise figure (dB): the ASE that travels with the signal
    edfa_gain_db: float = 30.0
    edfa_noise_figure_db: float = 5.0
    # -- effects (each off by default) --
    #: ambient light reaching the photodiode (W, DC): its shot noise
    ambient_power_w: float = 0.0
    #: speckle: per-pixel power fading, Gamma distributed with this many speckle cells
    #: averaged over the aperture (mean 1, variance 1/cells); 0: no speckle
    speckle_cells: float = 0.0
    #: emulate the paper's sequential mixing (Supplementary Note 4): the channels were
    #: recorded one at a time and summed, so the signal-independent noise is added K times
    sequential_mixing: bool = False
    # -- overrides of the physical budget --
    #: echo amplitude per (W * reflectivity * cos / r^2) in V m^2/W; None: from the budget
    link_gain_v_m2_per_w: float | None = None
    #: per-sample SNR (dB) of the median lit pixel's echo (at the scene's laser power)
    #: against the Gaussian noise (rescales the noise to the scene); exclusive with
    #: noise_rms_v
    snr_db: float | None = None
    #: fixed noise rms (V per sample); None: from the budget
    noise_rms_v: float | None = None
    system_delay_s: float = 37.3e-9
    detector_bandwidth_hz: float = 200e6
    # -- the receive chain's interference cancellation (cdma_lidar.firmware_model.cancel) --
    #: rounds of parallel interference cancellation, 0..4 (0: the paper's receiver, which
    #: correlates once) and the SNR_XC (dB) at which a found echo is subtracted
    cancel_rounds: int = 0
    cancel_snr_db: float = 16.0
    min_range_m: float | None = None
    max_range_m: float | None = None
    ghosts: tuple[Ghost, ...] = ()
    other_users: tuple[OtherUser, ...] = ()

    @property
    def channels(self) -> int:
        """Number of wavelength channels K."""
        return int(self.wavelengths_m.size)

    @property
    def columns(self) -> int:
        """Number of grating rotations (columns) C."""
        return int(self.rotations_deg.size)

    @property
    def code_degree(self) -> int:
        """Degree m of the code pair (the leading exponent of ``poly_u``)."""
        return self.poly_u[0]

    @property
    def code_length(self) -> int:
        """Code period N (chips)."""
        return (1 << self.code_degree) - 1

    @property
    def code_indices(self) -> tuple[int, ...]:
        """Gold member used by each channel (default: channel k uses member k)."""
        return self.code_index if self.code_index is not None else tuple(range(self.channels))

    def geometry(self, nominal: bool = False) -> GratingGeometry:
        """The grating geometry: true (what the light does) or nominal (what the host assumes)."""
        if nominal:
            return GratingGeometry(self.nominal_grooves_per_mm, self.nominal_incidence_deg,
                                   self.nominal_tilt_deg)
        return GratingGeometry(self.grooves_per_mm, self.incidence_deg, self.tilt_deg)


@dataclass(frozen=True, kw_only=True)
class ObjectSpec:
    """One object: ``kind`` plane, box, sphere or text, posed by position and orientation.

    Local frames: a plane is the local y-z plane through ``position_m`` facing local -x
    (towards the sensor when unrotated), limited to ``size_m`` = (width along y, height along
    z) if given; a box is centred at ``position_m`` with edge lengths ``size_m`` along its
    local x, y, z; a sphere has ``radius_m``; text is drawn in the local y-z plane (reading
    along -y, i.e. left to right as the sensor sees it, up along z), its front face at
    ``position_m`` facing -x, centred there, ``height_m`` tall (ink box), extruded
    ``depth_m`` along +x. Fields of another kind keep their defaults.
    """

    kind: str
    #: unique within the scene (a scene file defaults it to kind + index, e.g. ``plane0``)
    name: str
    position_m: NDArray[np.float64]
    orientation_deg: NDArray[np.float64] = field(default_factory=lambda: np.zeros(3))
    reflectivity: float = 0.5
    size_m: NDArray[np.float64] | None = None
    radius_m: float = 0.0
    text: str = ""
    height_m: float = 0.0
    #: text only: extrusion depth (m)
    depth_m: float = 0.02
    #: text only: the font family
    font: str = "DejaVu Sans"

    @property
    def rotation(self) -> NDArray[np.float64]:
        """Local-to-scene rotation matrix."""
        return rotation_matrix(self.orientation_deg)


@dataclass(frozen=True, kw_only=True)
class Scene:
    """A validated scene: the instrument, the objects, the calibration target."""

    name: str
    instrument: InstrumentSpec
    objects: tuple[ObjectSpec, ...]
    calibration: Calibration = Calibration()
    description: str = ""
    #: one of :data:`FIDELITY_LEVELS`
    fidelity: str = "exact"

    def with_instrument(self, **changes: Any) -> Scene:
        """A copy with instrument fields replaced (no re-validation: callers pass valid values)."""
        return replace(self, instrument=replace(self.instrument, **changes))
