"""Firmware-model test settings: the kernel cost model uses its built-in coefficients.

A calibration cache on the machine running the tests (see
``cdma_lidar.firmware_model.correlators.costs``) must not change which kernel
``method="auto"`` picks in a test.
"""

from __future__ import annotations

import pytest

from cdma_lidar.firmware_model.correlators.costs import DEFAULT_COEFFICIENTS, set_coefficients


@pytest.fixture(autouse=True)
def _default_kernel_costs():
    set_coefficients(DEFAULT_COEFFICIENTS)
    yield
    set_coefficients(None)
