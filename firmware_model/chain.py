"""The receive chain, vectorised: a batch of columns through R-sum, despread, chip sums,
a correlation kernel, scaling and the post passes; bit-identical to the reference.

:class:`FastReceiver` holds one configuration and code set. The correlation runs in
the chip domain through a kernel from :mod:`cdma_lidar.firmware_model.correlators`
(``method=``); the post passes (peaks, neighbours, noise floor, UID signs) are
:class:`cdma_lidar.firmware_model.peaks.PeakSearch`.
"""

from __future__ import annotations

import copy
import math
import threading
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import ArrayLike, NDArray

from cdma_lidar.checks import check_int
from cdma_lidar.errors import out_of_range
from cdma_lidar.firmware_model.adc import adc_limits
from cdma_lidar.firmware_model.cancel import Canceller, Subtraction
from cdma_lidar.firmware_model.correlators import (
    AUTO,
    Correlator,
    GatePlan,
    choose_correlator,
    make_correlator,
)
from cdma_lidar.firmware_model.correlators.base import (
    BLOCK_BYTES,
    column_threads,
    parallel_columns,
    resolve_threads,
)
from cdma_lidar.firmware_model.correlators.chip_domain import chip_sums, int_type
from cdma_lidar.firmware_model.output import ReceiverOutput
from cdma_lidar.firmware_model.peaks import PeakSearch
from cdma_lidar.firmware_model.receiver_config import (
    ReceiverConfig,
    Widths,
    as_samples,
    bitlen,
    check_codes,
    clog2,
)

__all__ = ["STEP_BYTES", "FastReceiver", "scale_out"]

#: Input bytes per step of the passes before the kernel (range check, R-sum, despread,
#: chip sums): a step stays in a core's L2 cache from one pass to the next.
STEP_BYTES = 1 << 20


@dataclass(eq=False)
class FastReceiver:
    """Vectorised receive chain for one configuration and code set; reuse it across columns.

    ``method`` names the correlation kernel, one of :func:`correlator_methods`
    (default ``"auto"``: the kernel the cost model's fixed constants predict fastest,
    :mod:`.correlators.costs`); ``float_bits`` (default 53) is the largest magnitude,
    in bits, the float64 kernels' products may reach before operands are split into
    limbs, ``float32_bits`` (0..24, default 24) the same for
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
        self._lag_lo = (cfg.gate_start - 1) % ns
        self._bip = (1 - 2 * bits.astype(np.int8)).astype(np.int8)
        self._search = PeakSearch(cfg, self.widths, self._bip)
        self._cancel = (Canceller(cfg, self._bip, self._search.lags, self._search.despread)
                        if cfg.cancel_rounds else None)
        self._despread = self._search.despread
        wd = self.widths
        s = cfg.samples_per_chip
        # integer types of the work, each the narrowest that holds its signal exactly
        self._acc_type = int_type(wd.acc)
        self._desp_type = int_type(wd.desp)
        y_bits = wd.desp + clog2(s) if s <= 8 else wd.desp + bitlen(ns + s)  # prefix sums
        self._y_type = int_type(y_bits)
        y_bound = s * cfg.uid_bits * cfg.averages * (1 << (cfg.adc_bits - 1))  # max |Y|
        check_int("columns", self.columns, 1, 1 << 30)
        self.plan = GatePlan(self._bip, s, self._lag_lo, cfg.gate_len + 2,
                             float_bits=self.float_bits, y_bound=y_bound, columns=self.columns,
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
        x = as_samples(samples, 1)
        return self.frame(x[None, :])[0]

    def frame(self, samples: ArrayLike) -> list[ReceiverOutput]:
        """Many columns at once (e.g. a scan frame): ``samples`` (C, R*n*N*S) ADC codes.

        Returns one output per column.
        """
        x = as_samples(samples, 2)
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
        """The chain after ``accumulate(c0, c1)`` has filled ``acc[c0:c1]`` (C, n, NS): one
        pass (:meth:`_pass`), then ``cancel_rounds`` passes on the accumulators minus the
        echoes the previous pass found (:mod:`cdma_lidar.firmware_model.cancel`)."""
        outs = self._pass(acc, accumulate, size, column_bytes)
        if self._cancel is None:
            return outs
        res = np.empty(acc.shape, dtype=acc.dtype)
        for _ in range(self.cfg.cancel_rounds):
            sub = self._cancel.pick(outs)
            outs = self._pass(
                res, lambda c0, c1, sub=sub: self._cancel.residual(acc[c0:c1], sub.rows(c0, c1),
                                                                   res[c0:c1]),
                size, column_bytes, sub)
        return outs

    def _pass(self, acc: NDArray[np.signedinteger], accumulate: Callable[[int, int], None],
              size: int, column_bytes: int, sub: Subtraction | None = None
              ) -> list[ReceiverOutput]:
        """One pass of the chain after ``accumulate(c0, c1)`` has filled ``acc[c0:c1]``
        (C, n, NS); ``sub``: the echoes a cancellation round subtracted, added back where
        each is correlated with its own code.

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
            own = None
            if sub is not None:
                rows = sub.rows(c0, c1)
                self._cancel.add_own(raw, rows)
                own = lambda j: self._cancel.own(rows, j)  # noqa: E731
            out = self._scale_raw(raw)
            parts[c0] = self._search(raw, out, acc[c0:c1],
                                     self._scratch(out[..., 1:-1].shape), own)

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
        return scale_out(raw, cfg.out_shift, cfg.rounding, cfg.out_bits)


def scale_out(raw: NDArray[np.int64], shift: int, rounding: str, out_bits: int
              ) -> NDArray[np.int64]:
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
