"""The FPGA receive chain, bit-exact: accumulate, despread, correlate, scale, peaks, noise floor.

Everything here is integer arithmetic; docs/firmware.md is the full reference
(block diagram, parameter ranges, every signal's fixed-point format). In short,
for one column of ``R * n * N * S`` signed ADC codes (repetition r = 0..R-1 of the
n-period UID sequence, then UID period p, then sample i)::

    acc[p][i] = sum_r x[(r*n + p)*NS + i]                 s(b + clog2 R)
    d[i]      = sum_p (-1)^bit_p(uid) * acc[p][i]         s(b + bitlen(n R))
    ref_k[i]  = +1 if code_k[i // S] == 0 else -1         chip bit 0 -> +1
    raw_k[l]  = sum_i ref_k[i] * d[(i + l) mod NS]        s(b + bitlen(N S R n))
                (an echo delayed by d samples peaks at lag l = d)
    out_k[l]  = sat_out_bits(round(raw_k[l] / 2^out_shift))
    gate:       lag_j = (gate_start + j) mod NS, j = 0..gate_len-1   (lags in samples)

then per channel the peak (largest |out| outside ghost windows, ties to the
lowest j), up to ``peaks`` peaks at least W+1 gate lags apart, the neighbours
``out`` at peak_lag -+ 1, the noise floor (count, sum, sum of squares of ``out``
over the gate minus peaks +-W and ghost lags) and the per-period UID signs.

Two implementations give the same integers:

* :func:`reference` / :class:`ReferenceReceiver` (:mod:`.reference`): literal,
  streaming (feed any chunking, sample by sample), Python integers and exact
  fractions. Slow.
* :func:`fast` / :func:`fast_frame` / :class:`FastReceiver` (:mod:`.chain`, its post
  passes in :mod:`.peaks`): vectorised; the
  correlation runs in the chip domain through a kernel from the registry in
  :mod:`cdma_lidar.firmware_model.correlators` (``method=``, one of
  :func:`correlator_methods`: ``"auto"``, an exact float64 matrix product
  ``"matmul"``, an FFT rounded under a rigorous error bound ``"fft"``, or any kernel
  registered since).

This module is the chain's front door: the configuration (:mod:`.receiver_config`),
both receivers and the functions that keep prepared receivers, importable from one place.
"""

from __future__ import annotations

import hashlib
import threading
from collections import OrderedDict

from numpy.typing import ArrayLike

from cdma_lidar.errors import out_of_range
from cdma_lidar.firmware_model.chain import FastReceiver
from cdma_lidar.firmware_model.correlators import AUTO, correlator_methods, registry_version
from cdma_lidar.firmware_model.output import ReceiverOutput
from cdma_lidar.firmware_model.receiver_config import (
    MAX_CHANNELS,
    MAX_CODE_LENGTH,
    ReceiverConfig,
    Widths,
    check_codes,
)
from cdma_lidar.firmware_model.reference import ReferenceReceiver, reference

__all__ = [
    "MAX_CHANNELS",
    "MAX_CODE_LENGTH",
    "RECEIVER_CACHE_SIZE",
    "FastReceiver",
    "ReceiverConfig",
    "ReceiverOutput",
    "ReferenceReceiver",
    "Widths",
    "check_codes",
    "clear_receiver_cache",
    "correlator_methods",
    "fast",
    "fast_frame",
    "fast_from_accumulators",
    "reference",
]

#: Receivers kept by :func:`fast`, :func:`fast_frame` and :func:`fast_from_accumulators`.
RECEIVER_CACHE_SIZE = 4
_CACHE: OrderedDict[tuple, FastReceiver] = OrderedDict()
_CACHE_LOCK = threading.Lock()


def _receiver(cfg: ReceiverConfig, codes: ArrayLike, method: str) -> FastReceiver:
    """A prepared receiver for (cfg, codes, method): the plan (Hankel blocks, spectra)
    costs tens of ms, so the last :data:`RECEIVER_CACHE_SIZE` are kept, keyed by the
    configuration, the method and a digest of the chip bits."""
    bits = check_codes(codes)
    if not isinstance(method, str) or method not in correlator_methods():
        raise out_of_range("method", "one of " + ", ".join(correlator_methods()), method)
    key = (cfg, method, registry_version(), bits.shape,
           hashlib.blake2b(bits.tobytes(), digest_size=16).digest())
    with _CACHE_LOCK:
        rx = _CACHE.get(key)
        if rx is not None:
            _CACHE.move_to_end(key)
            return rx
    rx = FastReceiver(cfg, bits, method=method)
    with _CACHE_LOCK:
        _CACHE[key] = rx
        while len(_CACHE) > RECEIVER_CACHE_SIZE:
            _CACHE.popitem(last=False)
    return rx


def clear_receiver_cache() -> None:
    """Forget the receivers :func:`fast` and friends kept (frees their plans' memory)."""
    with _CACHE_LOCK:
        _CACHE.clear()


def fast(cfg: ReceiverConfig, codes: ArrayLike, samples: ArrayLike, *,
         method: str = AUTO) -> ReceiverOutput:
    """One column through the vectorised chain; bit-identical to :func:`reference`.

    The prepared receiver is kept (:func:`clear_receiver_cache`), so repeated calls with
    the same configuration and codes do not rebuild the plan.

    ``method``: the correlation kernel, one of :func:`correlator_methods`.
    """
    return _receiver(cfg, codes, method).column(samples)


def fast_frame(cfg: ReceiverConfig, codes: ArrayLike, samples: ArrayLike, *,
               method: str = AUTO) -> list[ReceiverOutput]:
    """C columns at once (``samples`` shape (C, R*n*N*S)); one :class:`ReceiverOutput` each.

    ``method``: the correlation kernel, one of :func:`correlator_methods`.
    """
    return _receiver(cfg, codes, method).frame(samples)


def fast_from_accumulators(
    cfg: ReceiverConfig, codes: ArrayLike, acc: ArrayLike, *, method: str = AUTO
) -> list[ReceiverOutput]:
    """Finish the chain from accumulated periods ``acc`` (C, n, N*S): see FastReceiver."""
    return _receiver(cfg, codes, method).from_accumulators(acc)
