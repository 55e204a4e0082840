"""The receive chain's parameters and derived word widths: :class:`ReceiverConfig`,
:class:`Widths`, and the checks of a code set and of a block of ADC samples.

docs/firmware.md §2 lists the parameter ranges and §3 every signal's fixed-point
format; :mod:`cdma_lidar.firmware_model.receiver` is the chain itself.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from cdma_lidar.checks import check_int, is_int
from cdma_lidar.errors import out_of_range
from cdma_lidar.rounding import ROUNDING_MODES, Rounding

__all__ = [
    "INT64_BITS",
    "MAX_CANCEL_GATE",
    "MAX_CANCEL_ROUNDS",
    "MAX_CANCEL_SNR_Q8",
    "MAX_CHANNELS",
    "MAX_CODE_LENGTH",
    "MAX_GHOST_WINDOWS",
    "MIN_CODE_LENGTH",
    "ReceiverConfig",
    "Widths",
    "as_samples",
    "bitlen",
    "check_codes",
    "clog2",
]

MAX_CODE_LENGTH = 2**20 - 1  # degree 20; any length 3..MAX_CODE_LENGTH is accepted
MIN_CODE_LENGTH = 3
MAX_CHANNELS = 2048
MAX_GHOST_WINDOWS = 8
MAX_CANCEL_ROUNDS = 4
#: The longest gate (lags) cancellation runs with: its own-echo table is K (2G + 1) words.
MAX_CANCEL_GATE = 4096
MAX_CANCEL_SNR_Q8 = 2**32 - 1  # a u32 register: up to 72.2 dB
INT64_BITS = 63  # magnitude bits of an int64


def bitlen(x: int) -> int:
    """Bits of the unsigned integer x (floor(log2 x) + 1; 0 for x = 0)."""
    return int(x).bit_length()


def clog2(x: int) -> int:
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

    ``cancel_rounds`` (0..MAX_CANCEL_ROUNDS; 0: the paper's receiver) repeats the chain that
    many times on the accumulators minus the echoes the previous pass found (parallel
    interference cancellation, :mod:`cdma_lidar.firmware_model.cancel`); a found peak is
    subtracted when its SNR_XC is at least ``cancel_snr_q8`` / 256 (a power ratio in
    Q8: 10192 = 16.0 dB, 5731 = 13.5 dB: :func:`cdma_lidar.firmware_model.snr.snr_q8`).
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
    cancel_rounds: int = 0
    cancel_snr_q8: int = 10192

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
        check_int("cancel_rounds", self.cancel_rounds, 0, MAX_CANCEL_ROUNDS)
        check_int("cancel_snr_q8", self.cancel_snr_q8, 0, MAX_CANCEL_SNR_Q8)
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
        period, or the gate is longer than :data:`MAX_CANCEL_GATE` with cancellation.
        Every other configuration of the parameter ranges is accepted: the only width
        that can exceed int64, ``noise_sumsq`` (up to 89 bits), is carried exactly as
        Python integers (:attr:`Widths.wide_sumsq`).
        """
        check_int("code length (codes.shape[1])", n_chips, MIN_CODE_LENGTH, MAX_CODE_LENGTH)
        ns = self.period_samples(n_chips)
        if self.gate_start >= ns:
            raise out_of_range("gate_start", f"0..{ns - 1} (N*S - 1)", self.gate_start)
        if self.gate_len > ns:
            raise out_of_range("gate_len", f"1..{ns} (N*S)", self.gate_len)
        if self.cancel_rounds and self.gate_len > MAX_CANCEL_GATE:
            raise out_of_range("gate_len", f"1..{MAX_CANCEL_GATE} lags with cancel_rounds > 0",
                               self.gate_len)
        for s, n in self.ghost_windows:
            if s >= ns or n > ns:
                raise out_of_range(
                    "ghost_windows", f"(start 0..{ns - 1}, len 1..{ns}) pairs", self.ghost_windows
                )
        b, r, n_uid = self.adc_bits, self.averages, self.uid_bits
        s = self.out_shift
        # cancellation adds each subtracted echo back at its own lags: |raw| at most doubles
        cancel = 1 if self.cancel_rounds else 0
        raw = b + bitlen(ns * r * n_uid) + cancel
        rounded = raw if s == 0 else max(raw - s + 1, 2)
        out = min(self.out_bits, rounded)
        g = self.gate_len
        w = Widths(
            adc=b,
            acc=b + clog2(r),
            desp=b + bitlen(n_uid * r),
            raw=raw,
            uid=b + bitlen(ns * r) + cancel,
            rounded=rounded,
            out=out,
            noise_count=bitlen(g),
            noise_sum=out + clog2(g),
            noise_sumsq=2 * out - 2 + bitlen(g),
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


def as_samples(samples: ArrayLike, ndim: int) -> NDArray[np.integer]:
    """``samples`` as an integer array of ``ndim`` dimensions (1: a column; 2: (C, samples)),
    else ConfigError naming ``samples``; values are checked by the receivers."""
    x = np.asarray(samples)
    if x.ndim != ndim:
        what = "a 1-D integer array" if ndim == 1 else "a 2-D (columns, samples) integer array"
        raise out_of_range("samples", what, f"{x.ndim}-D")
    if x.dtype.kind not in "iu":
        raise out_of_range("samples", "an integer array of ADC codes", f"dtype {x.dtype}")
    return x
