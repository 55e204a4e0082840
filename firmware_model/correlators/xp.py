"""Array-API kernel (``method="xp"`` on numpy, ``method="gpu"`` on CuPy): one code, two devices.

Written against the array API standard through ``array-api-compat``, so that the
very same lines run on numpy (``"xp"``, always registered: CI checks it against the
streaming reference) and on CuPy (``"gpu"``, registered when CuPy imports and finds a
CUDA device). Per gated lag m (phase ``r_m``, chip offset ``q_m = (q0 + u_m) mod N``)
the window of the doubled phase row is gathered, and every column, lag and channel
is one batched product::

    win[c, m, j] = [Y_r, Y_r][c, r_m, q_m + j]           j < N  (a gather: xp.take)
    raw[c, k, m] = sum_j win[c, m, j] bip[k, j]          (C G, N) @ (N, K)

The codes are a constant (N, K) operand, the data is read once per lag: the product
has C G rows, which keeps a GPU's matrix units busy for many channels and many
columns alike. Blocks of columns and of lags keep the gathered windows within
:attr:`XPCorrelator.block_bytes`.

Exactness, the rule of the CPU kernels (every partial sum of one output is a sum of
a subset of ``+-Y[c, r, :]``, whatever the summation order):

* float32 products when ``max_{c,r} sum_j |Y[c, r, j]| < 2^min(float32_bits,
  float_bits)`` (<= 2^24), measured in int64 on the device;
* else float64 when ``N max|Y| < 2^float_bits`` (<= 2^53);
* else ``Y`` split into limbs of ``h = float_bits - bitlen(N)`` bits, each product
  exact in float64, recombined in int64.

Never TF32: CuPy's float32 ``matmul`` uses full float32 unless ``CUPY_TF32=1`` is
set, which :func:`gpu_available` refuses (the "gpu" kernel is then not registered).
"""

from __future__ import annotations

import importlib.util
import logging
import math
import os
from types import ModuleType

import numpy as np
from numpy.typing import NDArray

from cdma_lidar.errors import MissingExtra
from cdma_lidar.firmware_model.correlators.base import BLOCK_BYTES, Correlator, GatePlan
from cdma_lidar.firmware_model.correlators.costs import Coefficients, Estimate

__all__ = ["GPU_BLOCK_BYTES", "GPUCorrelator", "XPCorrelator", "gpu_available"]

log = logging.getLogger(__name__)

#: Gathered windows per block on a GPU (device memory, not host memory).
GPU_BLOCK_BYTES = 1 << 30
#: An H100-class device for the "gpu" estimate: float64 matrix-unit multiply-adds per
#: second (half the ~67 TFLOP/s peak) and host<->device bytes per second (PCIe 5 x16,
#: pageable memory), plus a fixed cost per call (launches, synchronisations).
GPU_MACS_PER_S = 2.0e13
GPU_COPY_BYTES_PER_S = 1.2e10
GPU_CALL_S = 2e-4


def _require_compat() -> ModuleType:
    try:
        import array_api_compat  # optional (extra "gpu"): only the array-API kernels need it
    except ImportError as exc:  # an optional dependency: say how to get it
        raise MissingExtra("the array-API correlators need array-api-compat: "
                           "pip install 'cdma-lidar[gpu]'") from exc
    return array_api_compat


class XPCorrelator(Correlator):
    """Gathered lag windows times the codes, batched over columns, lags and channels,
    on the array-API namespace :meth:`namespace` (numpy here)."""

    whole_frame = True  # one batched call per frame: one copy each way on a device
    block_bytes = BLOCK_BYTES

    @classmethod
    def namespace(cls) -> ModuleType:
        """The array namespace the kernel computes in (``array_api_compat.numpy``)."""
        _require_compat()
        # optional dependency, checked just above with a message naming the extra
        import array_api_compat.numpy as xnp

        return xnp

    def __init__(self, plan: GatePlan) -> None:
        super().__init__(plan)
        xp = self.xp = self.namespace()
        n = plan.n
        # first element of lag m's window in the (S * 2N) doubled phase rows of a column
        self._start = plan.r_m * (2 * n) + (plan.q0 + plan.u_m) % n
        self._lags = max(1, min(plan.count, self.block_bytes // (8 * n)))  # lags per block
        self._index = [xp.asarray(np.add.outer(self._start[m0 : m0 + self._lags],
                                                np.arange(n)).reshape(-1))
                       for m0 in range(0, plan.count, self._lags)]
        self._codes = {d: xp.asarray(plan.bip.T.astype(d)) for d in (np.float32, np.float64)}

    def _limbs(self, y: object) -> tuple[list[tuple[object, int]], object]:
        """``y`` (int64, on the device) as ``[(limb, shift), ...]`` and the float dtype."""
        xp, plan, n = self.xp, self.plan, self.plan.n
        mag = xp.abs(y)
        if plan.float32_limit() and int(xp.max(xp.sum(mag, axis=-1))) < plan.float32_limit():
            return [(y, 0)], xp.float32
        limit, h = 1 << plan.float_bits, plan.float_bits - n.bit_length()
        out, shift = [], 0
        while n * int(xp.max(xp.abs(y))) >= limit:
            out.append((y & ((1 << h) - 1), shift))  # low limbs in [0, 2^h)
            y = y >> h  # arithmetic: floor, so y = limb + 2^h (y >> h) exactly
            shift += h
        out.append((y, shift))
        return out, xp.float64

    def __call__(self, y: NDArray[np.signedinteger]) -> NDArray[np.int64]:
        import array_api_compat  # optional: present, or __init__ would have raised

        xp, plan = self.xp, self.plan
        c, s, n = y.shape
        k, count, step = plan.k, plan.count, self._lags
        yd = xp.astype(xp.asarray(np.ascontiguousarray(y)), xp.int64)  # to the device
        parts, dtype = self._limbs(yd)
        codes = self._codes[np.float32 if dtype == xp.float32 else np.float64]
        item = 4 if dtype == xp.float32 else 8
        cb = max(1, self.block_bytes // (item * step * n))  # columns per block
        out = xp.zeros((c, k, count), dtype=xp.int64)
        for limb, shift in parts:
            rows = xp.astype(limb, dtype)
            rows = xp.reshape(xp.concat([rows, rows], axis=-1), (c, s * 2 * n))  # doubled
            for b, m0 in enumerate(range(0, count, step)):
                m1 = min(count, m0 + step)
                for c0 in range(0, c, cb):
                    c1 = min(c, c0 + cb)
                    win = xp.reshape(xp.take(rows[c0:c1, :], self._index[b], axis=1),
                                     (c1 - c0, m1 - m0, n))
                    prod = xp.matmul(win, codes)  # (cb, lags, K): exact integers (module doc)
                    part = xp.astype(xp.permute_dims(prod, (0, 2, 1)), xp.int64)
                    if shift:
                        part = part << shift
                    out[c0:c1, :, m0:m1] = out[c0:c1, :, m0:m1] + part
        return np.asarray(array_api_compat.to_device(out, "cpu"))


def gpu_available() -> bool:
    """Whether CuPy imports, sees a CUDA device and leaves float32 products exact
    (``CUPY_TF32`` unset or 0). Imports CuPy only when it is installed."""
    if importlib.util.find_spec("cupy") is None:
        return False
    if os.environ.get("CUPY_TF32", "0") not in ("", "0"):
        log.warning("CUPY_TF32 is set: the gpu correlator is not registered (TF32 is inexact)")
        return False
    try:
        import cupy  # optional (extra "gpu"), installed: find_spec saw it

        return cupy.cuda.runtime.getDeviceCount() > 0
    except Exception as exc:  # no driver, no device: the CPU kernels remain
        log.info("CuPy found no usable GPU: %s", exc)
        return False


class GPUCorrelator(XPCorrelator):
    """:class:`XPCorrelator` on CuPy (``method="gpu"``), in blocks of 1 GiB of windows."""

    block_bytes = GPU_BLOCK_BYTES

    @classmethod
    def namespace(cls) -> ModuleType:
        """``array_api_compat.cupy``."""
        _require_compat()
        # optional dependencies (extra "gpu"): array-api-compat checked above, CuPy
        # present since gpu_available() registered this kernel
        import array_api_compat.cupy as xcp

        return xcp

    @classmethod
    def estimate(cls, plan: GatePlan, co: Coefficients) -> Estimate:
        """Copies in (int64 chip sums) and out (int64 raw), the float64 products (times
        the limbs) on the device's matrix units, and a fixed cost per call; host memory:
        the contiguous copy of the chip sums and the output."""
        c, n, k = plan.columns, plan.n, plan.k
        moved = 8.0 * c * plan.s * n + 8.0 * c * k * plan.count
        blocks = math.ceil(plan.count / max(1, min(plan.count, cls.block_bytes // (8 * n))))
        macs = float(c) * plan.count * n * k * plan.matmul_limbs()
        seconds = moved / GPU_COPY_BYTES_PER_S + macs / GPU_MACS_PER_S + GPU_CALL_S * blocks
        return Estimate(seconds, moved)
