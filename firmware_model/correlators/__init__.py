"""Gated-correlation kernels of the fast receive chain, chosen through one registry.

``FastReceiver(cfg, codes, method=...)`` (and ``fast``, ``fast_frame``,
``fast_from_accumulators``) take ``method`` from :func:`correlator_methods`:
``"auto"`` (:func:`choose_correlator` over the kernels' :meth:`Correlator.estimate`,
ties to the first registered) and
every registered kernel name, in registration order. Built in:

* ``"matmul"`` (:mod:`.matmul`): exact float64 Hankel products, limbs for the 2^53 bound;
* ``"fft"`` (:mod:`.fft`): power-of-two real FFTs rounded under a rigorous error bound;
* ``"direct"`` (:mod:`.direct`): one thin product per gated lag, little memory;
* ``"windows"`` (:mod:`.windows`): per phase, the lags' windows of the data as rows of
  one product with the codes (long codes with many channels);
* ``"xp"`` (:mod:`.xp`, when ``array-api-compat`` is installed): the array-API kernel
  on numpy, never chosen by ``"auto"``: the CI twin of ``"gpu"``;
* ``"gpu"`` (:mod:`.xp`, when CuPy imports and finds a CUDA device): the same code on
  CuPy, one batched call per frame; ``"auto"`` takes it where its estimate is faster.

Adding a kernel (a GPU one, a bit-packed one) is one module: subclass
:class:`Correlator` (``__init__(plan)``, ``__call__(y) -> raw``, optionally ``estimate``),
then one :func:`register_correlator` call (below for a built-in one; a plug-in may
register itself). It must give the exact integers;
``tests/firmware_model/test_receiver.py`` checks every registered method against
the streaming reference.
"""

from __future__ import annotations

import importlib.util

from cdma_lidar.firmware_model.correlators.base import (
    AUTO,
    Correlator,
    GatePlan,
    choose_correlator,
    correlator_methods,
    estimates,
    make_correlator,
    register_correlator,
    registry_version,
    unregister_correlator,
)
from cdma_lidar.firmware_model.correlators.direct import DirectCorrelator
from cdma_lidar.firmware_model.correlators.fft import FFTCorrelator
from cdma_lidar.firmware_model.correlators.matmul import MatmulCorrelator
from cdma_lidar.firmware_model.correlators.windows import WindowsCorrelator
from cdma_lidar.firmware_model.correlators.xp import GPUCorrelator, XPCorrelator, gpu_available

# The built-in kernels, in this order: it is auto's tie-break (equal costs -> matmul).
register_correlator("matmul", MatmulCorrelator)
register_correlator("fft", FFTCorrelator)
register_correlator("direct", DirectCorrelator)
register_correlator("windows", WindowsCorrelator)
if importlib.util.find_spec("array_api_compat") is not None:  # the optional extra [gpu]
    register_correlator("xp", XPCorrelator)
    if gpu_available():
        register_correlator("gpu", GPUCorrelator)

__all__ = [
    "AUTO",
    "Correlator",
    "DirectCorrelator",
    "FFTCorrelator",
    "GPUCorrelator",
    "GatePlan",
    "MatmulCorrelator",
    "WindowsCorrelator",
    "XPCorrelator",
    "choose_correlator",
    "correlator_methods",
    "estimates",
    "gpu_available",
    "make_correlator",
    "register_correlator",
    "registry_version",
    "unregister_correlator",
]
