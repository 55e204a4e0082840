"""The correlator seam: what a gated-correlation kernel implements, and the one registry.

The fast receive chain reduces every column to chip sums ``Y`` (C, S, N) (see
:mod:`cdma_lidar.firmware_model.correlators.chip_domain`) and asks a kernel for the
raw correlation at ``count`` consecutive sample lags ``(lag_lo + m) mod N*S``::

    raw[c, k, m] = sum_i ref_k[i] d_c[(i + lag_m) mod NS]
                 = sum_j bip_k[j] Y[c, r_m, (j + q0 + u_m) mod N]
    lag_m = lag_lo + m = (q0 + u_m) S + r_m,   r_m in 0..S-1

A kernel is a :class:`Correlator` subclass, registered under a name with
:func:`register_correlator`; the receiver picks it by that name
(``FastReceiver(cfg, codes, method=...)``), or by :func:`choose_correlator` over
every kernel's :meth:`Correlator.estimate` with ``method="auto"``. Every kernel must
return the exact int64 integers of the definition: it is bit-identical to the
streaming reference or it is a bug.
"""

from __future__ import annotations

import contextlib
import copy
import dataclasses
import itertools
import logging
import math
import os
import threading
import time
from abc import ABC, abstractmethod
from collections.abc import Callable, Iterator
from concurrent.futures import ThreadPoolExecutor

import numpy as np
from numpy.typing import NDArray
from threadpoolctl import ThreadpoolController

from cdma_lidar.errors import ConfigError, out_of_range
from cdma_lidar.firmware_model.correlators import costs
from cdma_lidar.firmware_model.correlators.costs import Coefficients, Estimate

__all__ = [
    "AUTO",
    "BLOCK_BYTES",
    "THREADS_ENV",
    "Correlator",
    "GatePlan",
    "blas_threads",
    "choose_correlator",
    "column_threads",
    "correlator_methods",
    "default_threads",
    "estimates",
    "limbs",
    "machine_threads",
    "make_correlator",
    "measure_correlators",
    "parallel_columns",
    "register_correlator",
    "registry_version",
    "resolve_threads",
    "unregister_correlator",
]

log = logging.getLogger(__name__)

#: The method name that lets the cost estimates choose.
AUTO = "auto"

#: Working-set cap (bytes) per block of columns or channels in the kernels.
BLOCK_BYTES = 64 << 20


class GatePlan:
    """The geometry one kernel is prepared for: codes, S, the gated lags, the float budget.

    ``bip`` (K, N) int8 +-1 (chip bit 0 -> +1), ``s`` samples per chip, lags
    ``(lag_lo + m) mod N*S`` for m < ``count`` (samples), and ``float_bits``: the
    largest magnitude, in bits, a float64 kernel may let its exact integers reach
    before it splits the operands into limbs (``n.bit_length() + 2 .. 53``).
    ``y_bound``, when known, is an upper bound of ``|Y|`` the chip sums can reach
    (``S n R 2^(b-1)``): a kernel may then skip looking at the data to decide on limbs.
    ``columns`` is the number of columns expected per call; it only steers the cost
    estimates (a product over many columns amortises its constant operand).
    ``threads`` (>= 1, default 1) is how many column threads a call's columns are split
    over (the receiver's :func:`parallel_columns`: :func:`column_threads`), each calling
    the kernel on its contiguous share; it too only steers the estimates
    (:func:`estimates`, :func:`.costs.threaded`).

    Derived (all integers): ``k``, ``n``; ``q0, r0 = divmod(lag_lo, s)``; per lag m
    the chip offset ``u_m = (r0 + m) // s`` and phase ``r_m = (r0 + m) % s``;
    ``nq = u_m[-1] + 1``; ``sel[r]`` the lags m of phase r.
    ``float32_bits`` (0..24, default 24) is the same budget for a float32 product: a
    kernel may run one when every partial sum provably stays below
    ``2^min(float32_bits, float_bits)`` (0: never). ``shared_bytes``: what the rest of
    the chain holds at its peak whatever the kernel (auto compares whole calls).
    """

    def __init__(self, bip: NDArray[np.int8], s: int, lag_lo: int, count: int,
                 float_bits: int = 53, y_bound: int | None = None, columns: int = 1,
                 float32_bits: int = 24, shared_bytes: float = 0.0, threads: int = 1) -> None:
        self.shared_bytes = float(shared_bytes)
        if isinstance(threads, bool) or not isinstance(threads, int | np.integer) or threads < 1:
            raise out_of_range("threads", "an integer >= 1", threads)
        self.threads = int(threads)
        self.k, self.n = bip.shape
        self.s = s
        self.bip = bip
        self.count = count
        n = self.n
        if not n.bit_length() + 2 <= float_bits <= 53:
            raise out_of_range("float_bits", f"{n.bit_length() + 2}..53", float_bits)
        self.float_bits = float_bits
        if not (isinstance(float32_bits, int) and 0 <= float32_bits <= 24):
            raise out_of_range("float32_bits", "0..24", float32_bits)
        self.float32_bits = float32_bits
        self.y_bound = None if y_bound is None else int(y_bound)
        self.columns = max(1, int(columns))
        self.lag_lo = int(lag_lo)
        self.q0, self.r0 = divmod(self.lag_lo, s)
        m = np.arange(count)
        self.u_m = (self.r0 + m) // s
        self.r_m = (self.r0 + m) % s
        self.nq = int(self.u_m[-1]) + 1
        self.sel = [np.nonzero(self.r_m == r)[0] for r in range(s)]  # lags m of phase r

    def float32_limit(self) -> int:
        """Partial sums of a float32 product must stay below this (0: no float32 products)."""
        return 1 << min(self.float32_bits, self.float_bits) if self.float32_bits else 0

    def float32_certain(self) -> bool:
        """Whether ``N y_bound`` is below :meth:`float32_limit`: float32 whatever the data."""
        return self.y_bound is not None and self.n * self.y_bound < self.float32_limit()

    def matmul_limbs(self) -> int:
        """Limbs a float64 product kernel splits Y into (1 when ``N y_bound < 2^float_bits``)."""
        if self.y_bound is None:
            return 1
        need = (self.n * self.y_bound).bit_length() - self.float_bits
        if need <= 0:
            return 1
        h = self.float_bits - self.n.bit_length()
        return 1 + math.ceil(need / h)


class Correlator(ABC):
    """A gated-correlation kernel: prepared once per plan, then called per block of columns.

    Subclasses implement ``__init__(plan)`` (build whatever the plan allows to
    precompute: Hankel blocks, spectra, ...), ``__call__(y)`` and, to take part in
    ``method="auto"``, :meth:`estimate`.

    The receiver runs a frame's columns in contiguous ranges over its threads, each
    range through the whole chain (chip sums, this kernel, peaks) with BLAS limited to
    its share of the threads, so ``__call__`` must be thread-safe. A kernel that sets
    ``whole_frame = True`` (a GPU: one batched launch, one copy) is instead called once
    with every column, from the calling thread.
    """

    #: called once per frame with every column (else once per column range and thread)
    whole_frame: bool = False
    #: called as ``kernel(y, bound)`` with ``bound`` a (C,) integer array, ``sum_m |y[c, r,
    #: m]| <= bound[c]`` for every phase r (the receiver's ``sum_i |d_i|`` over the
    #: period), or None: a proof of a narrower exact arithmetic without a look at ``y``
    takes_bound: bool = False
    #: the fixed cost of one call (its Python: buffers, checks, dispatch) in numpy calls
    #: (:class:`.costs.Coefficients` ``call``); measured per kernel, see ``costs.py``
    fixed_calls: float = 0.0

    def __init__(self, plan: GatePlan) -> None:
        self.plan = plan
        #: the registered name it was made under (set by :func:`make_correlator`)
        self.method = ""

    @classmethod
    def estimate(cls, plan: GatePlan, co: Coefficients) -> Estimate:
        """Predicted seconds per call (``plan.columns`` columns) and peak bytes.

        Written in the machine primitives of :class:`.costs.Coefficients`. The default
        (infinite time) means "only when asked for by name".
        """
        return Estimate(math.inf, 0.0)

    @abstractmethod
    def __call__(self, y: NDArray[np.signedinteger]) -> NDArray[np.int64]:
        """Chip sums ``y`` (C, S, N), int16/32/64 -> exact ``raw`` (C, K, count) int64.

        A kernel that sets :attr:`takes_bound` is called as ``kernel(y, bound)`` instead.
        """


_REGISTRY: dict[str, type[Correlator]] = {}
_VERSION = [0]  # bumped by every (un)registration: prepared receivers keyed on it go stale


def registry_version() -> int:
    """A counter that changes whenever a kernel is registered or unregistered."""
    return _VERSION[0]


def register_correlator(name: str, factory: type[Correlator], *, replace: bool = False) -> None:
    """Make kernel ``factory`` (a :class:`Correlator` subclass) usable as ``method=name``.

    Registration order is the tie-break of ``"auto"`` (the first of equal costs wins)
    and the order of :func:`correlator_methods`. Raises ConfigError for a name that is
    taken (unless ``replace``) or reserved (``"auto"``).
    """
    if not isinstance(name, str) or not name.isidentifier() or name == AUTO:
        raise out_of_range("name", f"an identifier other than {AUTO!r}", name)
    if not (isinstance(factory, type) and issubclass(factory, Correlator)):
        raise out_of_range("factory", "a Correlator subclass", factory)
    if name in _REGISTRY and not replace:
        raise ConfigError(f"correlator {name!r} is already registered", field="name")
    _REGISTRY[name] = factory
    _VERSION[0] += 1


def unregister_correlator(name: str) -> None:
    """Remove a registered kernel (tests and plug-ins that register temporarily)."""
    if name not in _REGISTRY:
        raise out_of_range("name", "one of " + ", ".join(_REGISTRY), name)
    del _REGISTRY[name]
    _VERSION[0] += 1


def correlator_methods() -> tuple[str, ...]:
    """Valid ``method=`` values: ``"auto"`` first, then the kernels in registration order."""
    return (AUTO, *_REGISTRY)


def estimates(plan: GatePlan, co: Coefficients | None = None) -> dict[str, Estimate]:
    """Every registered kernel's :class:`.costs.Estimate` for ``plan`` (registration order);
    ``co``: the seconds per primitive (default :data:`.costs.COEFFICIENTS`).

    On ``plan.threads`` column threads (a ``whole_frame`` kernel is called once whatever
    the threads) a kernel's time is :func:`.costs.threaded` of one thread's call on its
    share of the columns. What cannot overlap is read off the estimate, which is linear
    in the coefficients: its ``call`` terms (the GIL-held Python) and its ``ram`` terms
    (streams from main memory: the estimate less the one with ``call = 0``, and less
    the one with ``ram = 0``); its calls less its ``fixed_calls`` (Python, no call into
    numpy) release the GIL. The threads share the last-level cache
    (``Coefficients.llc_bytes`` split between them). The peak is the whole plan's.
    """
    co = costs.COEFFICIENTS if co is None else co
    return {name: _estimate(cls, plan, co) for name, cls in _REGISTRY.items()}


def _estimate(cls: type[Correlator], plan: GatePlan, co: Coefficients) -> Estimate:
    """``cls.estimate`` of ``plan`` on its ``plan.threads`` column threads."""
    whole = cls.estimate(plan, co)
    threads = min(plan.threads, plan.columns)
    if threads <= 1 or cls.whole_frame or not math.isfinite(whole.seconds):
        return whole
    share = copy.copy(plan)  # one thread's call: the largest share of the columns
    share.columns, share.threads = -(-plan.columns // threads), 1
    co = dataclasses.replace(co, llc_bytes=co.llc_bytes / threads)  # the L3 is shared
    one = cls.estimate(share, co).seconds
    held = one - cls.estimate(share, dataclasses.replace(co, call=0.0)).seconds
    streamed = one - cls.estimate(share, dataclasses.replace(co, ram=0.0)).seconds
    calls = held / co.call - cls.fixed_calls if co.call > 0 else 0.0
    return Estimate(costs.threaded(one, held + streamed, calls, threads), whole.peak_bytes)


#: ``measure=True`` times only the kernels predicted at most this many times slower
#: than the best prediction (the others are not worth minutes of a hopeless kernel).
MEASURE_SPAN = 10.0


def measure_correlators(plan: GatePlan, repeats: int = 3, seed: int = 0) -> dict[str, float]:
    """Seconds per call of each kernel worth timing on ``plan`` (best of ``repeats``).

    The kernels with a finite estimate within :data:`MEASURE_SPAN` of the best one are
    prepared and called on random chip sums of the plan's shape (``plan.columns``
    columns, ``|Y|`` up to ``plan.y_bound``, or 2^11 when unknown), split over
    ``plan.threads`` column threads as the receiver splits them (one call otherwise).
    """
    est = {k: e for k, e in estimates(plan).items() if math.isfinite(e.seconds)}
    if not est:
        return {}
    fastest = min(e.seconds for e in est.values())
    bound = plan.y_bound if plan.y_bound is not None else 1 << 11
    y = np.random.default_rng(seed).integers(-bound, bound + 1,
                                             (plan.columns, plan.s, plan.n), dtype=np.int64)
    times: dict[str, float] = {}
    for name, e in est.items():
        if e.seconds > MEASURE_SPAN * fastest:
            continue
        kernel = _REGISTRY[name](plan)

        def call(kernel: Correlator = kernel) -> None:
            if plan.threads > 1 and not kernel.whole_frame:
                parallel_columns(lambda c0, c1: kernel(y[c0:c1]), plan.columns,
                                 _PARALLEL_MIN, plan.threads)
            else:
                kernel(y)

        call()  # warm up: buffers, plans, threads
        best = math.inf
        for _ in range(max(1, repeats)):
            t0 = time.perf_counter()
            call()
            best = min(best, time.perf_counter() - t0)
        times[name] = best
    return times


def choose_correlator(plan: GatePlan, co: Coefficients | None = None, *,
                      measure: bool = False) -> str:
    """The kernel ``"auto"`` picks: the smallest predicted time (:func:`.costs.choose`,
    fixed constants, ties to the first registered), or, with ``measure=True``, the
    fastest by :func:`measure_correlators` on this machine (opt-in, takes the kernels'
    time; nothing is stored).

    ``co``: the seconds per primitive (default :data:`.costs.COEFFICIENTS`).
    """
    if measure:
        times = measure_correlators(plan)
        best = min(times, key=times.__getitem__) if times else ""
    else:
        best = costs.choose(estimates(plan, co))
    if not best:
        raise ConfigError("no registered correlator has a finite cost for this plan",
                          field="method")
    return best


def make_correlator(method: str, plan: GatePlan) -> Correlator:
    """Prepare the kernel ``method`` (a registered name or ``"auto"``) for ``plan``.

    Raises ConfigError naming ``method`` and listing the registered names otherwise.
    """
    if not isinstance(method, str) or (method != AUTO and method not in _REGISTRY):
        raise out_of_range("method", "one of " + ", ".join(correlator_methods()), method)
    name = choose_correlator(plan) if method == AUTO else method
    kernel = _REGISTRY[name](plan)
    kernel.method = name
    log.debug("gate correlator: N=%d S=%d K=%d lags=%d via %s",
              plan.n, plan.s, plan.k, plan.count, name)
    return kernel


#: Environment variable that sets the receive chain's thread count (an integer >= 1).
THREADS_ENV = "CDMA_LIDAR_THREADS"
#: Below this many elements per call the column work runs in the calling thread.
_PARALLEL_MIN = 1 << 18
_POOL: list[tuple[ThreadPoolExecutor, int]] = []  # (the pool, its size): made, grown on demand
_POOL_LOCK = threading.Lock()
_WORKER = threading.local()  # .inside: this thread is running a column task
_BLAS: list = []  # the threadpoolctl controller, made on first use


def machine_threads() -> int:
    """The CPUs this process may run on (its affinity mask; ``os.cpu_count`` elsewhere)."""
    count = getattr(os, "process_cpu_count", None)  # Python 3.13+
    if count is not None:
        return max(1, count() or 1)
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # not on Linux
        return max(1, os.cpu_count() or 1)


def default_threads() -> int:
    """Threads of the receive chain: ``$CDMA_LIDAR_THREADS`` when set (ConfigError naming
    it unless an integer >= 1), else the first entry of ``$OMP_NUM_THREADS`` when it is
    one (the share Dask's nanny, joblib and batch schedulers give a worker process),
    else :func:`machine_threads`."""
    env = os.environ.get(THREADS_ENV, "").strip()
    if env:
        if not env.isdigit() or int(env) < 1:
            raise out_of_range(THREADS_ENV, "an integer >= 1", env)
        return int(env)
    omp = os.environ.get("OMP_NUM_THREADS", "").split(",")[0].strip()
    if omp.isdigit() and int(omp) >= 1:  # another library's variable: never an error here
        return int(omp)
    return machine_threads()


def resolve_threads(threads: int | None) -> int:
    """``threads`` checked (an integer >= 1), or :func:`default_threads` for None."""
    if threads is None:
        return default_threads()
    if isinstance(threads, bool) or not isinstance(threads, int | np.integer) or threads < 1:
        raise out_of_range("threads", "an integer >= 1 or None (the machine's)", threads)
    return int(threads)


@contextlib.contextmanager
def blas_threads(n: int) -> Iterator[None]:
    """Limit the BLAS libraries (OpenBLAS, MKL, ...) to ``n`` threads for the duration
    (threadpoolctl; restored after). Process-wide: BLAS has no per-thread setting."""
    if not _BLAS:  # made on first use: it lists the BLAS libraries loaded by then
        _BLAS.append(ThreadpoolController())
    with _BLAS[0].limit(limits=n, user_api="blas"):
        yield


def column_threads(columns: int, size: int, threads: int | None = None) -> int:
    """How many column threads :func:`parallel_columns` runs ``columns`` columns over:
    ``min(threads, columns)`` when ``size`` (the elements the call touches) is at least
    2^18, else 1, as from inside a column task (no nesting)."""
    if getattr(_WORKER, "inside", False) or size < _PARALLEL_MIN:
        return 1
    return max(1, min(resolve_threads(threads), columns))


def parallel_columns(task: Callable[[int, int], None], columns: int, size: int,
                     threads: int | None = None) -> None:
    """Run ``task(c0, c1)`` over contiguous column ranges covering 0..columns-1.

    :func:`column_threads` ranges in as many threads (``min(threads, columns)`` when
    ``size``, the elements the call touches, is at least 2^18), else one call in the
    calling thread, as is a call from inside a task (no nesting). The BLAS libraries are
    limited to ``threads // ranges`` threads meanwhile, so that column threads times BLAS
    threads never exceed ``threads`` (default :func:`default_threads`), and to one
    thread for a call under 2^18 elements: its products last milliseconds, and a
    threaded BLAS call waits for its other threads for a scheduler slice whenever
    another process holds a core (one degree-11 column with a 256-lag gate, S = 16:
    matmul's one product took 32.7 ms on 2 BLAS threads of a loaded 2-core machine,
    1.3 ms of CPU on one). Exceptions propagate.
    """
    threads = resolve_threads(threads)
    if getattr(_WORKER, "inside", False):
        task(0, columns)
        return
    parts = column_threads(columns, size, threads)
    blas = max(1, threads // max(1, parts)) if size >= _PARALLEL_MIN else 1
    with blas_threads(blas):
        if parts <= 1:
            _in_worker(task, 0, columns)
            return
        with _POOL_LOCK:
            if not _POOL or _POOL[0][1] < parts:
                if _POOL:
                    _POOL.pop()[0].shutdown(wait=False)
                _POOL.append((ThreadPoolExecutor(parts, thread_name_prefix="cdma-rx"), parts))
            pool = _POOL[0][0]
        bounds = np.linspace(0, columns, parts + 1).astype(int).tolist()
        futures = [pool.submit(_in_worker, task, c0, c1)
                   for c0, c1 in itertools.pairwise(bounds)]
        for f in futures:
            f.result()


def _in_worker(task: Callable[[int, int], None], c0: int, c1: int) -> None:
    """``task(c0, c1)`` marked as a column task (a nested parallel_columns runs inline)."""
    _WORKER.inside = True
    try:
        task(c0, c1)
    finally:
        _WORKER.inside = False


def limbs(
    y: NDArray[np.int64], fits: Callable[[NDArray[np.int64]], bool], h: int
) -> list[tuple[NDArray[np.int64], int]]:
    """Split ``y = sum limb * 2^shift`` until ``fits(limb)``; low limbs are in [0, 2^h).

    The generic half of the float kernels' exactness guard; each kernel supplies its
    own ``fits`` (its error bound) and limb width ``h``.
    """
    out: list[tuple[NDArray[np.int64], int]] = []
    shift = 0
    if not fits(y):
        y = y.astype(np.int64)  # the masks and shifts below are int64 constants
    while not fits(y):
        out.append((y & ((1 << h) - 1), shift))
        y = y >> h
        shift += h
    out.append((y, shift))
    return out


def product_limbs(plan: GatePlan, y: NDArray[np.int64]) -> list[tuple[NDArray[np.int64], int]]:
    """:func:`limbs` of chip sums ``y`` (..., N) under the per-lag products' rule: a float
    product with +-1 codes is exact when ``N max|limb| < 2^plan.float_bits`` (proven
    without a look when ``plan.y_bound`` allows it); low limbs are ``float_bits -
    bit_length(N)`` bits wide."""
    n = y.shape[-1]
    limit = 1 << plan.float_bits
    if plan.y_bound is not None and n * plan.y_bound < limit:
        return [(y, 0)]
    return limbs(y, lambda v: n * int(np.abs(v).max(initial=0)) < limit,
                 plan.float_bits - n.bit_length())
