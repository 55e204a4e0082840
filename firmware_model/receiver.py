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

* :func:`reference` / :class:`ReferenceReceiver`: literal, streaming (feed any
  chunking, sample by sample), Python integers and exact fractions. Slow.
* :func:`fast` / :func:`fast_frame` / :class:`FastReceiver`: vectorised; the
  correlation runs in the chip domain through a kernel from the registry in
  :mod:`cdma_lidar.firmware_model.correlators` (``method=``, one of
  :func:`correlator_methods`: ``"auto"``, an exact float64 matrix product
  ``"matmul"``, an FFT rounded under a rigorous error bound ``"fft"``, or any kernel
  registered since).
"""

from __future__ import annotations

import copy
import dataclasses
import hashlib
import logging
import math
import threading
from collections import OrderedDict
from collections.abc import Callable
from dataclasses import dataclass, field
from fractions import Fraction

import numpy as np
from numpy.typing import ArrayLike, NDArray

from cdma_lidar.checks import check_int, is_int
from cdma_lidar.errors import out_of_range
from cdma_lidar.firmware_model.adc import adc_limits
from cdma_lidar.firmware_model.correlators import (
    AUTO,
    Correlator,
    GatePlan,
    choose_correlator,
    correlator_methods,
    make_correlator,
    registry_version,
)
from cdma_lidar.firmware_model.correlators.base import (
    BLOCK_BYTES,
    column_threads,
    parallel_columns,
    resolve_threads,
)
from cdma_lidar.firmware_model.correlators.chip_domain import chip_sums, correlate_at, int_type
from cdma_lidar.firmware_model.output import ReceiverOutput, saturated_flags
from cdma_lidar.rounding import ROUNDING_MODES, Rounding

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

log = logging.getLogger(__name__)

MAX_CODE_LENGTH = 2**20 - 1  # degree 20; any length 3..MAX_CODE_LENGTH is accepted
MIN_CODE_LENGTH = 3
MAX_CHANNELS = 2048
MAX_GHOST_WINDOWS = 8
INT64_BITS = 63  # magnitude bits of an int64
#: Input bytes per step of the passes before the kernel (range check, R-sum, despread,
#: chip sums): a step stays in a core's L2 cache from one pass to the next.
STEP_BYTES = 1 << 20


def _bitlen(x: int) -> int:
    """Bits of the unsigned integer x (floor(log2 x) + 1; 0 for x = 0)."""
    return int(x).bit_length()


def _clog2(x: int) -> int:
    """ceil(log2 x) for x >= 1 (clog2(1) = 0)."""
    return (int(x) - 1).bit_length()


@dataclass(frozen=True)
class Widths:
    """Derived word widths in bits for one configuration and code length (docs/firmware.md §3).

    Signed widths (s(w)): ``adc``, ``acc``, ``desp``, ``raw``, ``uid``, ``rounded``,
    ``out``, ``noise_sum``. Unsigned (u(w)): ``noise_count``, ``noise_sumsq``.
    ``out`` is the effective output width min(out_bits, rounded); the output word
    itself is ``out_bits`` wide. ``float_exact`` says whether N*S*R*n*2^(b-1) < 2^53,
    i.e. whether a float64 correlation is exact without splitting.
    """

    adc: int
    acc: int
    desp: int
    raw: int
    uid: int
    rounded: int
    out: int
    noise_count: int
    noise_sum: int
    noise_sumsq: int
    float_exact: bool

    @property
    def wide_sumsq(self) -> bool:
        """True when ``noise_sumsq`` may exceed int64 (> 63 bits): the receivers then report
        it as an object array of exact Python integers instead of int64."""
        return self.noise_sumsq > INT64_BITS

    @property
    def sumsq_dtype(self) -> type:
        """dtype of the reported ``noise_sumsq``: ``np.int64``, or ``object`` when wide."""
        return object if self.wide_sumsq else np.int64


@dataclass(frozen=True)
class ReceiverConfig:
    """Parameters of the receive chain (ranges in docs/firmware.md §2).

    Lags, gate and ghost windows are in samples; ``ghost_windows`` holds
    ``(start_lag, length)`` pairs of absolute lags (mod N*S). Checks that need the
    code length N (gate inside the period, derived widths) run in :meth:`widths`,
    which ``reference``/``fast`` call with ``codes.shape[1]``.

    ``uid_bits`` may be 1..16 here (and in ``hdl_ref``); a device is narrower: the
    protocol carries 1..``max_uid_bits`` and the virtual device announces 8 in INFO.
    """

    adc_bits: int = 12
    samples_per_chip: int = 4
    averages: int = 10
    uid_bits: int = 1
    uid: int = 0
    gate_start: int = 0
    gate_len: int = 64
    peak_exclude: int = 8
    ghost_windows: tuple[tuple[int, int], ...] = ()
    out_shift: int = 0
    rounding: Rounding = "truncate"
    out_bits: int = 32
    peaks: int = 1

    def __post_init__(self) -> None:
        check_int("adc_bits", self.adc_bits, 8, 16)
        check_int("samples_per_chip", self.samples_per_chip, 1, 64)
        check_int("averages", self.averages, 1, 1024)
        check_int("uid_bits", self.uid_bits, 1, 16)
        check_int("uid", self.uid, 0, (1 << self.uid_bits) - 1)
        check_int("gate_start", self.gate_start, 0, MAX_CODE_LENGTH * 64 - 1)
        check_int("gate_len", self.gate_len, 1, MAX_CODE_LENGTH * 64)
        check_int("peak_exclude", self.peak_exclude, 0, MAX_CODE_LENGTH * 64)
        check_int("out_shift", self.out_shift, 0, 62)
        check_int("out_bits", self.out_bits, 8, 32)
        check_int("peaks", self.peaks, 1, 8)
        if self.rounding not in ROUNDING_MODES:
            raise out_of_range("rounding", "one of " + ", ".join(ROUNDING_MODES), self.rounding)
        try:
            ghosts = tuple((s, n) for s, n in self.ghost_windows)
        except (TypeError, ValueError):
            ghosts = None
        if ghosts is None or not all(is_int(v) for w in ghosts for v in w):
            raise out_of_range(
                "ghost_windows", "a sequence of (start, len) integer pairs", self.ghost_windows
            )
        ghosts = tuple((int(s), int(n)) for s, n in ghosts)
        if len(ghosts) > MAX_GHOST_WINDOWS:
            raise out_of_range("ghost_windows", f"at most {MAX_GHOST_WINDOWS} windows", len(ghosts))
        for s, n in ghosts:
            if s < 0 or n < 1:
                raise out_of_range(
                    "ghost_windows", "(start >= 0, len >= 1) pairs", self.ghost_windows
                )
        object.__setattr__(self, "ghost_windows", ghosts)

    def replace(self, **changes: object) -> ReceiverConfig:
        """Return a copy with some fields changed (validated again)."""
        return dataclasses.replace(self, **changes)

    def period_samples(self, n_chips: int) -> int:
        """NS = N * S, samples per code period."""
        return int(n_chips) * self.samples_per_chip

    def column_samples(self, n_chips: int) -> int:
        """Samples in one column: R * n * N * S."""
        return self.averages * self.uid_bits * self.period_samples(n_chips)

    def widths(self, n_chips: int) -> Widths:
        """Check the config against code length ``n_chips`` and derive every width.

        Raises ConfigError when the gate or a ghost window does not fit in the
        period. Every configuration of the parameter ranges is accepted: the only
        width that can exceed int64, ``noise_sumsq`` (up to 89 bits), is carried
        exactly as Python integers (:attr:`Widths.wide_sumsq`).
        """
        check_int("code length (codes.shape[1])", n_chips, MIN_CODE_LENGTH, MAX_CODE_LENGTH)
        ns = self.period_samples(n_chips)
        if self.gate_start >= ns:
            raise out_of_range("gate_start", f"0..{ns - 1} (N*S - 1)", self.gate_start)
        if self.gate_len > ns:
            raise out_of_range("gate_len", f"1..{ns} (N*S)", self.gate_len)
        for s, n in self.ghost_windows:
            if s >= ns or n > ns:
                raise out_of_range(
                    "ghost_windows", f"(start 0..{ns - 1}, len 1..{ns}) pairs", self.ghost_windows
                )
        b, r, n_uid = self.adc_bits, self.averages, self.uid_bits
        s = self.out_shift
        raw = b + _bitlen(ns * r * n_uid)
        rounded = raw if s == 0 else max(raw - s + 1, 2)
        out = min(self.out_bits, rounded)
        g = self.gate_len
        w = Widths(
            adc=b,
            acc=b + _clog2(r),
            desp=b + _bitlen(n_uid * r),
            raw=raw,
            uid=b + _bitlen(ns * r),
            rounded=rounded,
            out=out,
            noise_count=_bitlen(g),
            noise_sum=out + _clog2(g),
            noise_sumsq=2 * out - 2 + _bitlen(g),
            float_exact=ns * r * n_uid * (1 << (b - 1)) < 2**53,
        )
        return w


def check_codes(codes: ArrayLike) -> NDArray[np.uint8]:
    """Validate a (K, N) array of chip bits (0/1) and return it as uint8."""
    c = np.asarray(codes)
    if c.ndim != 2:
        raise out_of_range("codes", "a 2-D (K, N) array of chip bits", f"{c.ndim}-D")
    if c.dtype.kind not in "iub":
        raise out_of_range("codes", "an integer or bool array of chip bits", f"dtype {c.dtype}")
    k, n = c.shape
    if not 1 <= k <= MAX_CHANNELS:
        raise out_of_range("codes.shape[0] (channels K)", f"1..{MAX_CHANNELS}", k)
    if not MIN_CODE_LENGTH <= n <= MAX_CODE_LENGTH:
        raise out_of_range(
            "codes.shape[1] (code length N)", f"{MIN_CODE_LENGTH}..{MAX_CODE_LENGTH}", n
        )
    if c.dtype.kind != "b" and c.size and (int(c.min()) < 0 or int(c.max()) > 1):
        raise out_of_range("codes", "chip bits 0 or 1", f"values {int(c.min())}..{int(c.max())}")
    return c.astype(np.uint8)


def _as_samples(samples: ArrayLike, ndim: int) -> NDArray[np.integer]:
    x = np.asarray(samples)
    if x.ndim != ndim:
        what = "a 1-D integer array" if ndim == 1 else "a 2-D (columns, samples) integer array"
        raise out_of_range("samples", what, f"{x.ndim}-D")
    if x.dtype.kind not in "iu":
        raise out_of_range("samples", "an integer array of ADC codes", f"dtype {x.dtype}")
    return x


# --------------------------------------------------------------------------------------
# Reference: literal, streaming, Python integers.
# --------------------------------------------------------------------------------------


class ReferenceReceiver:
    """Streaming reference model of one column: ``feed`` chunks of any size, then ``finish``.

    Samples are consumed one by one in arrival order, exactly as the hardware
    accumulator sees them: sample t adds to ``acc[(t // NS) % n][t % NS]``.
    Deliberately simple and slow (Python integers); use small configurations.
    """

    def __init__(self, cfg: ReceiverConfig, codes: ArrayLike) -> None:
        self.cfg = cfg
        bits = check_codes(codes)
        self.n_chips = int(bits.shape[1])
        self.widths = cfg.widths(self.n_chips)
        s = cfg.samples_per_chip
        self._ns = self.n_chips * s
        self._ref = [[1 - 2 * int(row[i // s]) for i in range(self._ns)] for row in bits.tolist()]
        self._acc = [[0] * self._ns for _ in range(cfg.uid_bits)]
        self._t = 0
        self._total = cfg.column_samples(self.n_chips)
        self._lo, self._hi = adc_limits(cfg.adc_bits)

    @property
    def samples_needed(self) -> int:
        """ADC samples still expected before :meth:`finish`."""
        return self._total - self._t

    def feed(self, chunk: ArrayLike) -> None:
        """Accumulate a 1-D chunk of ADC codes (any length up to :attr:`samples_needed`)."""
        x = _as_samples(chunk, 1)
        if len(x) > self.samples_needed:
            raise out_of_range(
                "samples", f"{self._total} ADC codes per column", self._t + len(x)
            )
        ns, n = self._ns, self.cfg.uid_bits
        for v in x.tolist():
            if not self._lo <= v <= self._hi:
                raise out_of_range("samples", f"ADC codes in {self._lo}..{self._hi}", v)
            t = self._t
            self._acc[(t // ns) % n][t % ns] += v
            self._t = t + 1

    def finish(self) -> ReceiverOutput:
        """Despread, correlate, scale and search; return the column's output."""
        if self._t != self._total:
            raise out_of_range("samples", f"{self._total} ADC codes per column", self._t)
        cfg, ns = self.cfg, self._ns
        n, uid, g = cfg.uid_bits, cfg.uid, cfg.gate_len
        d = [
            sum(-self._acc[p][i] if (uid >> p) & 1 else self._acc[p][i] for p in range(n))
            for i in range(ns)
        ]
        lags = [(cfg.gate_start + j) % ns for j in range(g)]
        ghost = [
            any((lag - start) % ns < length for start, length in cfg.ghost_windows)
            for lag in lags
        ]
        w = cfg.peak_exclude
        rows: dict[str, list] = {name: [] for name in _FIELDS}
        for ref in self._ref:

            def corr_at(data: list[int], lag: int, ref: list[int] = ref) -> int:
                return sum(ref[i] * data[(i + lag) % ns] for i in range(ns))

            out = [self._scale(corr_at(d, lag)) for lag in lags]
            found: list[int] = []
            for _ in range(cfg.peaks):
                best = None
                for j in range(g):
                    if ghost[j] or any(abs(j - q) <= w for q in found):
                        continue
                    if best is None or abs(out[j]) > abs(out[best]):
                        best = j
                if best is None:
                    break
                found.append(best)
            peak_lags = [lags[j] for j in found] + [-1] * (cfg.peaks - len(found))
            peak_vals = [out[j] for j in found] + [0] * (cfg.peaks - len(found))
            signs = [
                [_sign(corr_at(self._acc[p], lag)) for p in range(n)] if lag >= 0 else [0] * n
                for lag in peak_lags
            ]
            noise = [
                out[j] for j in range(g)
                if not ghost[j] and all(abs(j - q) > w for q in found)
            ]
            if found:
                lag0 = peak_lags[0]
                nb = [self._scale(corr_at(d, (lag0 - 1) % ns)),
                      self._scale(corr_at(d, (lag0 + 1) % ns))]
            else:
                nb = [0, 0]
            observed = sum(1 << p for p in range(n) if signs[0][p] < 0)
            rows["corr"].append(out)
            rows["peak_lag"].append(peak_lags[0])
            rows["peak"].append(peak_vals[0])
            rows["neighbours"].append(nb)
            rows["noise_count"].append(len(noise))
            rows["noise_sum"].append(sum(noise))
            rows["noise_sumsq"].append(sum(v * v for v in noise))
            rows["uid_signs"].append(signs[0])
            rows["uid_observed"].append(observed)
            rows["uid_match"].append(bool(found) and 0 not in signs[0] and observed == uid)
            rows["extra_lag"].append(peak_lags[1:])
            rows["extra_peak"].append(peak_vals[1:])
            rows["extra_signs"].append(signs[1:])
        k, p1 = len(self._ref), cfg.peaks - 1
        rows["saturated"] = saturated_flags(rows["peak_lag"], rows["peak"], cfg.out_bits).tolist()
        return ReceiverOutput(
            corr=np.array(rows["corr"], dtype=np.int64).reshape(k, g),
            peak_lag=np.array(rows["peak_lag"], dtype=np.int64),
            peak=np.array(rows["peak"], dtype=np.int64),
            neighbours=np.array(rows["neighbours"], dtype=np.int64).reshape(k, 2),
            noise_count=np.array(rows["noise_count"], dtype=np.int64),
            noise_sum=np.array(rows["noise_sum"], dtype=np.int64),
            noise_sumsq=np.array(rows["noise_sumsq"], dtype=self.widths.sumsq_dtype).reshape(k),
            uid_signs=np.array(rows["uid_signs"], dtype=np.int8).reshape(k, n),
            uid_observed=np.array(rows["uid_observed"], dtype=np.int64),
            uid_match=np.array(rows["uid_match"], dtype=np.bool_),
            saturated=np.array(rows["saturated"], dtype=np.bool_),
            extra_lag=np.array(rows["extra_lag"], dtype=np.int64).reshape(k, p1),
            extra_peak=np.array(rows["extra_peak"], dtype=np.int64).reshape(k, p1),
            extra_signs=np.array(rows["extra_signs"], dtype=np.int8).reshape(k, p1, n),
        )

    def _scale(self, raw: int) -> int:
        """out = sat(round(raw / 2^s)), written with exact fractions (docs/firmware.md §3)."""
        cfg = self.cfg
        x = Fraction(raw, 1 << cfg.out_shift)
        if cfg.rounding == "truncate":
            r = math.floor(x)
        elif cfg.rounding == "half_up":
            r = math.floor(x + Fraction(1, 2))
        else:
            r = round(x)  # Fraction.__round__ without digits: half to even
        top = (1 << (cfg.out_bits - 1)) - 1
        return min(max(r, -top - 1), top)


_FIELDS = tuple(f.name for f in dataclasses.fields(ReceiverOutput))


def _sign(v: int) -> int:
    return (v > 0) - (v < 0)


def reference(cfg: ReceiverConfig, codes: ArrayLike, samples: ArrayLike) -> ReceiverOutput:
    """Run the streaming reference on one column (``samples``: 1-D, R*n*N*S ADC codes)."""
    rx = ReferenceReceiver(cfg, codes)
    rx.feed(samples)
    return rx.finish()


# --------------------------------------------------------------------------------------
# Fast path: vectorised, bit-identical to the reference.
# --------------------------------------------------------------------------------------


@dataclass(eq=False)
class FastReceiver:
    """Vectorised receive chain for one configuration and code set; reuse it across columns.

    ``method`` names the correlation kernel, one of :func:`correlator_methods`
    (default ``"auto"``: the kernel the calibrated cost model predicts fastest among
    those within 2x of the leanest memory, :mod:`.correlators.costs`); ``float_bits``
    (default 53) is the largest magnitude, in bits, the float64 kernels' products may reach before
    operands are split into limbs, ``float32_bits`` (0..24, default 24) the same for
    float32 products (0: never float32). All three only choose how the same integers are
    computed. An unknown ``method`` raises ConfigError listing the registered names.
    ``columns`` (default 1) is how many columns a call of :meth:`frame` is expected to
    carry: it only steers ``"auto"`` (a product over many columns amortises more).
    ``plan`` is the :class:`GatePlan` the kernel was prepared for. ``prepare=False``
    defers building the kernel to the first call (e.g. to look at ``plan`` and the
    estimates of a configuration too large to prepare).
    ``threads`` (an integer >= 1; default None: :func:`.correlators.base.default_threads`,
    i.e. ``$CDMA_LIDAR_THREADS``, else ``$OMP_NUM_THREADS``, else the CPUs this process may
    run on, looked up at every call) is how many threads a call uses in all: column
    threads times BLAS threads (:func:`.correlators.base.parallel_columns`).
    """

    cfg: ReceiverConfig
    codes: ArrayLike
    method: str = AUTO
    float_bits: int = 53
    columns: int = 1
    float32_bits: int = 24
    prepare: bool = True
    threads: int | None = None
    widths: Widths = field(init=False)

    def __post_init__(self) -> None:
        bits = check_codes(self.codes)
        self.codes = bits
        if self.threads is not None:
            self.threads = resolve_threads(self.threads)
        cfg = self.cfg
        self.n_chips = int(bits.shape[1])
        self.widths = cfg.widths(self.n_chips)
        self._ns = ns = self.n_chips * cfg.samples_per_chip
        g = cfg.gate_len
        self._lag_lo = (cfg.gate_start - 1) % ns
        self._lags = (self._lag_lo + np.arange(g + 2, dtype=np.int64)) % ns  # lags of out[m]
        gate_lags = self._lags[1:-1]
        ghost = np.zeros(g, dtype=bool)
        for start, length in cfg.ghost_windows:
            ghost |= (gate_lags - start) % ns < length
        self._ghost = ghost
        self._has_ghost = bool(ghost.any())  # tested twice per _post call
        # the peak exclusion |j - j_peak| <= W as rows of a table, when it is small
        w = cfg.peak_exclude
        jj = np.arange(g)
        self._window = (np.abs(jj[:, None] - jj[None, :]) <= w) if g <= 2048 else None
        self._despread = np.array(
            [-1 if (cfg.uid >> p) & 1 else 1 for p in range(cfg.uid_bits)], dtype=np.int64
        )
        self._bip = (1 - 2 * bits.astype(np.int8)).astype(np.int8)
        wd = self.widths
        s = cfg.samples_per_chip
        # integer types of the work, each the narrowest that holds its signal exactly
        self._acc_type = int_type(wd.acc)
        self._desp_type = int_type(wd.desp)
        y_bits = wd.desp + _clog2(s) if s <= 8 else wd.desp + _bitlen(ns + s)  # prefix sums
        self._y_type = int_type(y_bits)
        y_bound = s * cfg.uid_bits * cfg.averages * (1 << (cfg.adc_bits - 1))  # max |Y|
        check_int("columns", self.columns, 1, 1 << 30)
        self.plan = GatePlan(self._bip, s, self._lag_lo, g + 2, float_bits=self.float_bits,
                             y_bound=y_bound, columns=self.columns,
                             float32_bits=self.float32_bits,
                             shared_bytes=self._shared_bytes(self.columns))
        # the float32 rule depends on the data: the chain hands the kernels sum |d| per column
        self._data_bound = bool(self.plan.float32_limit()) and not self.plan.float32_certain()
        d_max = cfg.uid_bits * cfg.averages << (cfg.adc_bits - 1)  # max |d|
        self._l1_type = np.uint32 if ns * d_max < 1 << 32 else np.uint64
        self._kernels: dict[str, Correlator] = {}  # prepared kernels by name
        self._auto: dict[tuple[int, int], str] = {}  # auto's choice per (bucket, threads)
        if self.prepare:
            self.kernel_for(self.columns)
        self._lo, self._hi = adc_limits(cfg.adc_bits)
        # out = raw exactly (no copy) when there is no shift and saturation cannot happen
        self._identity_scale = cfg.out_shift == 0 and wd.raw <= cfg.out_bits
        self._local = threading.local()  # per-thread scratch of the post passes

    def _scratch(self, shape: tuple[int, ...], dtype: type = np.int64,
                 name: str = "post") -> NDArray[np.signedinteger]:
        """A reused work array of ``shape`` and ``dtype`` for this thread, one per ``name``
        (never returned to callers): a fresh one would fault its pages in on every frame."""
        size = math.prod(shape)
        bufs = self._local.__dict__.setdefault("bufs", {})
        key = (name, np.dtype(dtype))
        buf = bufs.get(key)
        if buf is None or buf.size < size:
            buf = bufs[key] = np.empty(size, dtype=dtype)
        return buf[:size].reshape(shape)

    def _shared_bytes(self, columns: int) -> float:
        """Bytes the chain around the kernel holds at its peak for ``columns`` columns
        (estimate for auto's memory rule): the (C, K, G + 2) int64 outputs and their
        post-processing copies, the accumulators and chip sums, and with n > 1 the
        per-period UID dots at the peaks (one (K, P, N) int64 gather and product per
        block of columns)."""
        cfg = self.cfg
        k, n, ns = self._bip.shape[0], self.n_chips, self._ns
        out = 8.0 * columns * k * (cfg.gate_len + 2) * 4
        work = 16.0 * columns * cfg.uid_bits * ns
        dots = 0.0
        if cfg.uid_bits > 1:
            one = 16.0 * k * cfg.peaks * n  # one column's gather and product
            dots = max(one, min(float(BLOCK_BYTES), one * columns)) + 8.0 * columns * \
                cfg.uid_bits * ns
        return out + work + dots

    @property
    def correlator_method(self) -> str:
        """The kernel a frame of ``columns`` columns uses ("matmul", "fft", "direct", ...)."""
        return self.kernel_for(self.columns).method

    def kernel_for(self, columns: int, size: int | None = None) -> Correlator:
        """The prepared kernel for calls of ``columns`` columns (built on first use).

        A named ``method`` is used for every call; ``"auto"`` asks the cost model once
        per power-of-two bucket of columns (one column and a 160-column frame may want
        different kernels) and number of column threads the call runs on
        (:func:`.correlators.base.column_threads` of ``size``, the elements the call
        touches; default a frame's ADC samples), and keeps each kernel it prepared.
        """
        if self.method == AUTO:
            bucket = 1 << (max(1, int(columns)) - 1).bit_length()
            if size is None:
                size = columns * self.cfg.column_samples(self.n_chips)
            threads = column_threads(columns, size, self.threads)
            name = self._auto.get((bucket, threads))
            if name is None:
                plan = copy.copy(self.plan)
                plan.columns, plan.threads = bucket, threads
                plan.shared_bytes = self._shared_bytes(bucket)
                name = self._auto[bucket, threads] = choose_correlator(plan)
        else:
            name = self.method
        kernel = self._kernels.get(name)
        if kernel is None:
            kernel = self._kernels[name] = make_correlator(name, self.plan)
        return kernel

    def column(self, samples: ArrayLike) -> ReceiverOutput:
        """One column: ``samples`` 1-D, R*n*N*S ADC codes."""
        x = _as_samples(samples, 1)
        return self.frame(x[None, :])[0]

    def frame(self, samples: ArrayLike) -> list[ReceiverOutput]:
        """Many columns at once (e.g. a scan frame): ``samples`` (C, R*n*N*S) ADC codes.

        Returns one output per column.
        """
        x = _as_samples(samples, 2)
        self._check_samples(x, values=False)
        c = x.shape[0]
        acc_type = self._acc_type
        if x.dtype.itemsize > np.dtype(acc_type).itemsize:
            acc_type = np.int64  # a narrower sum would need a converted copy of the input
        acc = np.empty((c, self.cfg.uid_bits, self._ns), dtype=acc_type)
        info = np.iinfo(x.dtype)
        check = info.min < self._lo or info.max > self._hi  # else the dtype is the range

        def accumulate(c0: int, c1: int) -> None:  # range check and R-sum, columns c0..c1-1
            xb = x[c0:c1]
            if check and xb.size:
                self._check_range(xb)
            self._accumulate_into(xb, acc[c0:c1])

        return self._chain(acc, accumulate, x.size, x.shape[1] * x.dtype.itemsize)

    def _check_samples(self, samples: NDArray[np.integer], shape: bool = True,
                       values: bool = True) -> None:
        """The column length, and every code inside the ADC range (unless its dtype is)."""
        need = self.cfg.column_samples(self.n_chips)
        if shape and samples.shape[1] != need:
            raise out_of_range("samples", f"{need} ADC codes per column", samples.shape[1])
        info = np.iinfo(samples.dtype)
        if values and samples.size and (info.min < self._lo or info.max > self._hi):
            self._check_range(samples)

    def _check_range(self, samples: NDArray[np.integer]) -> None:
        """Every code inside the ADC range (a non-empty array)."""
        lo, hi = int(samples.min()), int(samples.max())
        if lo < self._lo or hi > self._hi:
            bad = lo if lo < self._lo else hi
            raise out_of_range("samples", f"ADC codes in {self._lo}..{self._hi}", bad)

    def _accumulate_into(self, x: NDArray[np.integer], acc: NDArray[np.signedinteger]) -> None:
        cfg = self.cfg
        xr = x.reshape(x.shape[0], cfg.averages, cfg.uid_bits * self._ns)
        np.add.reduce(xr, axis=1, dtype=acc.dtype, out=acc.reshape(x.shape[0], -1))

    def accumulate(self, samples: NDArray[np.integer]) -> NDArray[np.signedinteger]:
        """Sum the R repetitions: (C, R*n*NS) ADC codes -> acc (C, n, NS).

        The dtype is the narrowest of int16/int32/int64 holding ``W_acc`` bits (or the
        input's, if wider): every partial sum of R codes fits it, so no overflow.
        """
        self._check_samples(samples)
        acc_type = self._acc_type
        if samples.dtype.itemsize > np.dtype(acc_type).itemsize:
            acc_type = np.int64  # a narrower sum would need a converted copy of the input
        acc = np.empty((samples.shape[0], self.cfg.uid_bits, self._ns), dtype=acc_type)
        self._accumulate_into(samples, acc)
        return acc

    def from_accumulators(self, acc: ArrayLike) -> list[ReceiverOutput]:
        """Finish the chain from accumulated periods ``acc`` (C, n, NS) integers.

        ``acc[c, p, i]`` is the sum over the R repetitions of sample i of period p;
        each entry must lie in the range R ADC codes can reach.
        """
        cfg = self.cfg
        a = np.asarray(acc)
        if a.ndim != 3 or a.shape[1:] != (cfg.uid_bits, self._ns) or a.dtype.kind not in "iu":
            raise out_of_range(
                "acc", f"a (C, {cfg.uid_bits}, {self._ns}) integer array", f"{a.shape} {a.dtype}"
            )
        if a.dtype.kind == "u" or a.dtype.itemsize > 8:
            a = a.astype(np.int64)
        r = cfg.averages
        if a.size and (int(a.min()) < r * self._lo or int(a.max()) > r * self._hi):
            raise out_of_range("acc", f"sums of {r} ADC codes", f"{int(a.min())}..{int(a.max())}")
        return self._finish(a)

    def _finish(self, a: NDArray[np.signedinteger]) -> list[ReceiverOutput]:
        return self._chain(a, lambda c0, c1: None, a.size, a[0].nbytes if len(a) else 1)

    def _chain(self, acc: NDArray[np.signedinteger], accumulate: Callable[[int, int], None],
               size: int, column_bytes: int) -> list[ReceiverOutput]:
        """The chain after ``accumulate(c0, c1)`` has filled ``acc[c0:c1]`` (C, n, NS).

        The columns are split into :attr:`threads` contiguous ranges, each run through
        the whole chain (R-sum, despread, chip sums, the kernel, scaling, peaks) in its
        own thread with BLAS limited to its share of the threads: no pass waits for
        another range, and column threads times BLAS threads never exceed
        :attr:`threads`. A ``whole_frame`` kernel (one batched call, a GPU) runs once
        between the two halves instead.

        ``accumulate``, the despread and the chip sums run in steps of about
        :data:`STEP_BYTES` of input (``column_bytes`` per column), so that each pass
        reads the step from the cache the previous one left it in.
        """
        c, s, n = acc.shape[0], self.cfg.samples_per_chip, self.n_chips
        w = np.empty((c, self._ns), dtype=self._y_type)
        kernel = self.kernel_for(c, size)
        # sum_i |d_i| per column: the kernel's proof of float32 products, where the data decide
        wants = kernel.takes_bound and self._data_bound
        l1 = np.empty(c, dtype=self._l1_type) if wants else None
        parts: dict[int, list[ReceiverOutput]] = {}
        step = max(1, STEP_BYTES // max(1, column_bytes))

        def chips(c0: int, c1: int) -> NDArray[np.signedinteger]:
            for b0 in range(c0, c1, step):
                b1 = min(c1, b0 + step)
                accumulate(b0, b1)
                self._chip_domain(acc[b0:b1], w[b0:b1], None if l1 is None else l1[b0:b1])
            return w[c0:c1].reshape(c1 - c0, n, s).transpose(0, 2, 1)  # (C, S, N), a view

        def post(c0: int, c1: int, raw: NDArray[np.int64]) -> None:
            parts[c0] = self._post(raw, self._scale_raw(raw), acc[c0:c1])

        def run(y: NDArray[np.signedinteger], c0: int, c1: int) -> NDArray[np.int64]:
            if kernel.takes_bound:
                return kernel(y, None if l1 is None else l1[c0:c1])
            return kernel(y)

        if kernel.whole_frame:
            parallel_columns(chips, c, size, self.threads)
            raw_all = run(w.reshape(c, n, s).transpose(0, 2, 1), 0, c)
            parallel_columns(lambda c0, c1: post(c0, c1, raw_all[c0:c1]), c, size, self.threads)
        else:
            parallel_columns(lambda c0, c1: post(c0, c1, run(chips(c0, c1), c0, c1)), c, size,
                             self.threads)
        return [o for c0 in sorted(parts) for o in parts[c0]]

    def _chip_domain(self, a: NDArray[np.signedinteger], w: NDArray[np.signedinteger],
                     l1: NDArray[np.unsignedinteger] | None = None) -> None:
        """Despread the accumulators ``a`` (C, n, NS) and write the window sums into ``w``
        and, if given, ``sum_i |d_i|`` per column into ``l1``."""
        cfg = self.cfg
        if cfg.uid_bits == 1:  # d = (-1)^uid acc[0]: the sign is folded into the chip sums
            d, sign = a[:, 0, :], int(self._despread[0])
        else:
            d, sign = np.zeros((a.shape[0], self._ns), dtype=self._desp_type), 1
            for p, q in enumerate(self._despread.tolist()):
                if q > 0:
                    d += a[:, p, :]
                else:
                    d -= a[:, p, :]
        chip_sums(d, cfg.samples_per_chip, sign, self._y_type, out=w,
                  scratch=self._scratch(w.shape, self._y_type, "chips"))
        if l1 is not None:
            # data too large for float32 usually shows on the first column's first 4096
            # samples: then every column gets the trivial bound (the type's largest, >=
            # any sum) and the kernel decides from Y as without one, the pass skipped
            if int(np.abs(d[0, :4096].astype(np.int64)).sum()) >= self.plan.float32_limit():
                l1[...] = np.iinfo(l1.dtype).max
                return
            # |d| in d's own type, read as unsigned: |min| wraps to min, whose unsigned
            # reading is its magnitude 2^(bits-1), so every |d_i| is exact; summed in
            # uint32 when NS |d| fits (2x faster than int64 for int16 d), else uint64
            mag = np.abs(d, out=self._scratch(d.shape, d.dtype, "abs"))
            np.add.reduce(mag.view(mag.dtype.str.replace("i", "u")), axis=-1,
                          dtype=self._l1_type, out=l1)

    def _scale_raw(self, raw: NDArray[np.int64]) -> NDArray[np.int64]:
        """``out`` of the kernel's ``raw``: ``raw`` itself when the scaling is the identity."""
        if self._identity_scale:
            return raw
        cfg = self.cfg
        return _scale(raw, cfg.out_shift, cfg.rounding, cfg.out_bits)

    # -- peak search, neighbours, noise floor, UID signs (vectorised over columns and channels)

    def _post(
        self, raw: NDArray[np.int64], out: NDArray[np.int64], acc: NDArray[np.int64]
    ) -> list[ReceiverOutput]:
        cfg = self.cfg
        c, k, _ = out.shape
        g, w, npk, n = cfg.gate_len, cfg.peak_exclude, cfg.peaks, cfg.uid_bits
        corr = out[:, :, 1:-1]  # the gate; the returned traces are views of it
        mag = np.abs(corr, out=self._scratch((c, k, g)))  # |out| <= 2^31: no overflow
        if self._has_ghost:
            mag[..., self._ghost] = -1
        jj = np.arange(g)
        pk_j = np.full((c, k, npk), -1, dtype=np.int64)
        near_any = None
        for p in range(npk):
            j = np.argmax(mag, axis=-1)  # first (lowest j) among equal maxima
            ok = np.take_along_axis(mag, j[..., None], axis=-1)[..., 0] >= 0
            pk_j[..., p] = np.where(ok, j, -1)
            if self._window is not None:  # rows |jj - j| <= W of a precomputed table
                near = self._window[j]
                near &= ok[..., None]
            else:  # two comparisons straight to bool: no (C, K, G) integer temporaries
                jc = j[..., None]
                near = jj >= jc - w
                near &= jj <= jc + w
                near &= ok[..., None]
            if near_any is None:
                near_any = near
            else:
                near_any |= near
            if p + 1 < npk:  # the last peak's window only matters to the noise mask
                np.putmask(mag, near, -1)
        found = pk_j >= 0
        jsafe = np.where(found, pk_j, 0)
        pk_lag = np.where(found, self._lags[1:-1][jsafe], -1)
        pk_val = np.where(found, np.take_along_axis(corr, jsafe, axis=-1), 0)
        # neighbours of the first peak: out[m] with m = j (lag-1) and j + 2 (lag+1)
        j0 = jsafe[..., :1]
        nb = np.concatenate(
            [np.take_along_axis(out, j0, axis=-1), np.take_along_axis(out, j0 + 2, axis=-1)],
            axis=-1,
        )
        nb = np.where(found[..., :1], nb, 0)
        noise = np.logical_not(near_any, out=near_any)
        if self._has_ghost:
            noise &= ~self._ghost
        cnt = np.count_nonzero(noise, axis=-1).astype(np.int64)
        cz = np.multiply(corr, noise, out=mag)  # out over the noise lags, 0 elsewhere
        nsum = cz.sum(axis=-1, dtype=np.int64)
        if self.widths.wide_sumsq:
            np.multiply(cz, cz, out=cz)  # |out| <= 2^31: each square fits int64
            nsq = _sum_squares(cz, None, True)
        else:  # every square and their sum fit int64 (noise_sumsq <= 63 bits): one pass
            nsq = np.einsum("ckj,ckj->ck", cz, cz)
        signs = self._uid_signs(raw, acc, jsafe, found)  # (C, K, P, n)
        observed = ((signs[:, :, 0, :] < 0).astype(np.int64) << np.arange(n)).sum(axis=-1)
        match = found[..., 0] & np.all(signs[:, :, 0, :] != 0, axis=-1) & (observed == cfg.uid)
        uid0 = np.ascontiguousarray(signs[:, :, 0, :])
        extra_signs = np.ascontiguousarray(signs[:, :, 1:, :])
        lag0, val0 = np.ascontiguousarray(pk_lag[..., 0]), np.ascontiguousarray(pk_val[..., 0])
        lag1, val1 = np.ascontiguousarray(pk_lag[..., 1:]), np.ascontiguousarray(pk_val[..., 1:])
        sat = saturated_flags(lag0, val0, cfg.out_bits)
        batch = {"corr": corr, "peak_lag": lag0, "peak": val0, "neighbours": nb,
                 "noise_count": cnt, "noise_sum": nsum, "noise_sumsq": nsq, "uid_signs": uid0,
                 "uid_observed": observed, "uid_match": match, "saturated": sat,
                 "extra_lag": lag1, "extra_peak": val1, "extra_signs": extra_signs}
        # per-column views into the batch's arrays (``corr``: of the kernel's output),
        # positional in field order: list(a) makes the views faster than a[ci]
        return [ReceiverOutput(*v) for v in zip(*(list(batch[f]) for f in _FIELDS), strict=True)]

    def _uid_signs(
        self,
        raw: NDArray[np.int64],
        acc: NDArray[np.int64],
        jsafe: NDArray[np.int64],
        found: NDArray[np.bool_],
    ) -> NDArray[np.int8]:
        """sign(sum_i ref_k[i] acc[p][(i + lag) mod NS]) at each peak lag -> (C, K, P, n) int8."""
        cfg = self.cfg
        if cfg.uid_bits == 1:
            # d = (-1)^uid * acc[0], so the period's correlation is (-1)^uid * raw at the lag.
            r = np.take_along_axis(raw, jsafe + 1, axis=-1) * self._despread[0]
            s = np.sign(r)[..., None]
        else:
            lags = self._lags[1:-1][jsafe]  # (C, K, P)
            s = np.sign(correlate_at(self._bip, acc, lags, cfg.samples_per_chip))
        return np.where(found[..., None], s, 0).astype(np.int8)


def _sum_squares(sq: NDArray[np.int64], where: NDArray[np.bool_] | None, wide: bool) -> NDArray:
    """Exact ``sum(sq, axis=-1, where=where)`` of squares ``sq`` (each < 2^63).

    When ``wide`` (Widths.noise_sumsq > 63) the sum may not fit int64: the squares are
    split at bit 31, ``sq = hi 2^31 + lo``, both halves summed in int64 (at most 2^26
    lags of < 2^32: no overflow) and recombined as Python integers (object array).
    """
    kw = {} if where is None else {"where": where}
    if not wide:
        return sq.sum(axis=-1, dtype=np.int64, **kw)  # exact: noise_sumsq <= 63 bits
    lo = (sq & ((1 << 31) - 1)).sum(axis=-1, dtype=np.int64, **kw)
    hi = (sq >> 31).sum(axis=-1, dtype=np.int64, **kw)
    out = np.empty(lo.shape, dtype=object)
    flat = out.reshape(-1)
    for i, (h, v) in enumerate(zip(hi.ravel().tolist(), lo.ravel().tolist(), strict=True)):
        flat[i] = (h << 31) + v
    return out


def _scale(raw: NDArray[np.int64], shift: int, rounding: str, out_bits: int) -> NDArray[np.int64]:
    """out = sat(round(raw / 2^shift)) with integer shifts (docs/firmware.md §3)."""
    if shift == 0:
        r = raw
    elif rounding == "truncate":
        r = raw >> shift
    elif rounding == "half_up":
        r = (raw + (1 << (shift - 1))) >> shift
    else:
        q = raw >> shift
        rem = raw - (q << shift)
        half = 1 << (shift - 1)
        r = q + ((rem > half) | ((rem == half) & ((q & 1) == 1)))
    top = (1 << (out_bits - 1)) - 1
    return np.clip(r, -top - 1, top)


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
