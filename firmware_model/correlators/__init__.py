"""Gated-correlation kernels of the fast receive chain, chosen through one registry.

``FastReceiver(cfg, codes, method=...)`` (and ``fast``, ``fast_frame``,
``fast_from_accumulators``) take ``method`` from :func:`correlator_methods`:
``"auto"`` (:func:`choose_correlator` over the kernels' :meth:`Correlator.estimate`,
ties to the first registered) and
every registered kernel name, in registration order. Built in:

* ``"matmul"`` (:mod:`.matmul`): exact float64 Hankel products, limbs for the 2^53 bound;
* ``"fft"`` (:mod:`.fft`): power-of-two real FFTs rounded under a rigorous error bound.

Adding a kernel (a GPU one, a bit-packed one) is one module: subclass
:class:`Correlator` (``__init__(plan)``, ``__call__(y) -> raw``, optionally ``estimate``),
then one :func:`register_correlator` call (below for a built-in one; a plug-in may
register itself). It must give the exact integers;
``tests/firmware_model/test_receiver.py`` checks every registered method against
the streaming reference.
"""

from __future__ import annotations

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

# The built-in kernels, in this order: it is auto's tie-break (equal costs -> matmul).
register_correlator("matmul", MatmulCorrelator)
register_correlator("fft", FFTCorrelator)
register_correlator("direct", DirectCorrelator)

__all__ = [
    "AUTO",
    "Correlator",
    "DirectCorrelator",
    "FFTCorrelator",
    "GatePlan",
    "MatmulCorrelator",
    "choose_correlator",
    "correlator_methods",
    "estimates",
    "make_correlator",
    "register_correlator",
    "registry_version",
    "unregister_correlator",
]
