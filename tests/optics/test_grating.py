"""Grating geometry against the paper's equations 45 to 49."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from cdma_lidar.errors import ConfigError
from cdma_lidar.optics.grating import GratingGeometry, azimuth_elevation_deg, paper_wavelengths_m

GEOM = GratingGeometry()
WL = paper_wavelengths_m()


@settings(max_examples=200, deadline=None)
@given(
    lam=st.floats(1530e-9, 1610e-9),
    rot=st.floats(-8.0, 8.0),
    inc=st.floats(50.0, 70.0),
    grooves=st.floats(500.0, 700.0),
)
def test_wavevector_magnitude_is_two_pi_over_lambda(lam, rot, inc, grooves):
    g = GratingGeometry(grooves_per_mm=grooves, incidence_deg=inc)
    kd = g.wavevectors(lam, rot)
    assert np.linalg.norm(kd) == pytest.approx(2 * np.pi / lam, rel=1e-12)


@settings(max_examples=200, deadline=None)
@given(lam=st.floats(1530e-9, 1610e-9), inc=st.floats(40.0, 75.0))
def test_zero_rotation_is_the_grating_equation(lam, inc):
    g = GratingGeometry(incidence_deg=inc)
    d = g.grating_directions(lam, 0.0)
    sin_theta_d = -d[1]  # d = (0, -sin theta_d, cos theta_d)
    assert d[0] == 0.0
    # eq. 45: sin(theta_i) + sin(theta_d) = lambda / Lambda
    assert np.sin(np.deg2rad(inc)) + sin_theta_d == pytest.approx(lam / g.period_m, abs=1e-12)


def test_directions_are_unit_and_shaped_per_pixel():
    rot = np.linspace(-5, 5, 160)
    d = GEOM.directions(WL[:, None], rot[None, :])
    assert d.shape == (40, 160, 3)
    np.testing.assert_allclose(np.linalg.norm(d, axis=-1), 1.0, atol=1e-12)
    assert np.all(d[..., 0] > 0.99)  # everything points forward


def test_wavelength_sweeps_elevation_rotation_sweeps_azimuth():
    rot = np.linspace(-5, 5, 11)
    az, el = azimuth_elevation_deg(GEOM.directions(WL[:, None], rot[None, :]))
    # one channel per elevation: monotonic in wavelength at every column
    assert np.all(np.diff(el, axis=0) < 0)
    # rotation sweeps azimuth monotonically (positive rotation turns right)
    assert np.all(np.diff(az, axis=1) < 0)
    # vertical span of 40 channels at 0.875 nm is about 1.2 degrees (0.03 deg/channel)
    span = el[0, 5] - el[-1, 5]
    assert 1.0 < span < 1.4


def test_bow_shaped_trajectory():
    # each channel's elevation is symmetric in the rotation and rises with |rotation|
    rot = np.linspace(-6, 6, 13)
    _, el = azimuth_elevation_deg(GEOM.directions(WL[:, None], rot[None, :]))
    np.testing.assert_allclose(el, el[:, ::-1], atol=1e-9)
    centre = 6
    assert np.all(np.diff(el[:, centre:], axis=1) > 0)
    # curvature: second difference has one sign (a bow, not a straight line)
    assert np.all(np.diff(el[:, centre:], n=2, axis=1) > 0)


def test_default_tilt_levels_the_reference_channel():
    d = GEOM.directions(GEOM.reference_wavelength_m, 0.0)
    np.testing.assert_allclose(d, [1.0, 0.0, 0.0], atol=1e-12)


def test_no_propagating_order_is_a_clear_error_not_nan():
    with pytest.raises(ConfigError, match="no propagating first order"):
        GEOM.directions(1550e-9, 80.0)
    with pytest.raises(ConfigError, match="no propagating first order"):
        GratingGeometry(incidence_deg=80.0).directions(3.5e-6, 0.0)


def test_rotations_for_azimuths_inverts_directions():
    az_want = np.linspace(-5, 5, 21)
    rot = GEOM.rotations_for_azimuths(az_want)
    az, _ = azimuth_elevation_deg(GEOM.directions(GEOM.reference_wavelength_m, rot))
    np.testing.assert_allclose(az, az_want, atol=1e-5)
    with pytest.raises(ConfigError, match="azimuths_deg"):
        GEOM.rotations_for_azimuths([200.0])


@pytest.mark.parametrize(
    ("kwargs", "field"),
    [({"grooves_per_mm": 0.0}, "grooves_per_mm"), ({"incidence_deg": 95.0}, "incidence_deg"),
     ({"tilt_deg": float("nan")}, "tilt_deg")],
)
def test_bad_parameters_name_the_field(kwargs, field):
    with pytest.raises(ConfigError, match=field) as exc:
        GratingGeometry(**kwargs)
    assert exc.value.field == field
