r"""The codes' spectra and waveform tables: what every echo is made of.

``c(t)`` is the bipolar NRZ chip waveform (+1 for bit 0) of period ``n * N`` chips, AC
coupled (no DC) and filtered by the detector transfer function

    H(f) = exp(-ln(2)/2 * (f / B)^2) * T(f),   T = 1 below 0.8 f_Nyq, cos^2 taper to 0 at f_Nyq

(Gaussian with its -3 dB point at ``detector_bandwidth_hz`` = B, times an anti-alias
taper that is zero from the Nyquist frequency ``f_Nyq = chip_rate * S / 2`` up). The
filtered waveform is therefore band-limited below Nyquist, so rendering it from its
Fourier series is exact for ANY delay, fractional samples included::

    Z_q = H(f_q) * sinc(q / (nN)) * DFT(chips)[q mod nN] / (nN) * exp(-2j pi f_q tau')
    f_q = q * chip_rate / (nN),  q = 0 .. L/2,  L = n N S samples per frame
    y   = irfft(L * sum_k A_k Z_q,k)        one inverse FFT per column, all channels summed

The L/2 + 1 bins repeat the chips' nN-point DFT under one weight (H, sinc, scale), so the
per-channel work is one period of nN bins times its phase ramp (an outer product of two
short exponentials), then one scaled add per further period; the weight multiplies the
column's sum once (:meth:`Codebook.sum_delayed`), reading each term's row of one table of
the members' spectra (:class:`ChipSpectra`, K nN values: no per-column copy). :class:`Codebook`
keeps the spectra and ``accumulated`` fidelity's waveform tables of each configuration (its
own cache); the spectra tables are also kept for the process (bounded by
SHARED_SPECTRA_BYTES), so a new Instrument of the same configuration does not transform the
codes again.
"""

from __future__ import annotations

import functools
import math
import threading
from collections import OrderedDict
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, fields

import numpy as np
from numpy.typing import NDArray

from cdma_lidar.errors import ConfigError
from cdma_lidar.firmware_model.gold import gold_codes
from cdma_lidar.scene.echo_kernel import single_synthesis_kernel, synthesis_kernel
from cdma_lidar.scene.model import InstrumentSpec

__all__ = ["SHARED_SPECTRA_BYTES", "TABLE_PHASES", "ChipSpectra", "Codebook", "RenderSettings",
           "detector_response"]

#: ``accumulated`` fidelity tabulates each code's waveform at this many delays per sample
#: (:meth:`cdma_lidar.scene.echoes.Echoes.tabulated_echo`).
TABLE_PHASES = 8

#: Bytes of chip-spectrum tables (:class:`ChipSpectra`) the process keeps for every
#: :class:`Codebook`, so a new Instrument (a new connection) of the same code pair, UID
#: and members finds them transformed: the least recently used go first. paper-massive's
#: 1,200 members are 0.63 GB in complex128 (0.32 GB complex64); a larger table is built
#: and used but not kept here.
SHARED_SPECTRA_BYTES = 1 << 30

#: Gold members transformed at a time while a table is built (its float64 chips and
#: complex128 transform, 50 MB at N = 32,767, are the only temporaries).
_CHUNK_MEMBERS = 96


@dataclass(frozen=True)
class RenderSettings:
    """What the device is configured to emit and sample (may differ from the scene's defaults).

    code_index: Gold member per channel; uid_bits/uid: our UID (n periods per frame);
    samples_per_chip S; averages R (frames per column); poly_u/poly_v: the code pair.
    """

    samples_per_chip: int
    averages: int
    uid_bits: int
    uid: int
    code_index: tuple[int, ...]
    poly_u: tuple[int, ...]
    poly_v: tuple[int, ...]

    @classmethod
    def from_spec(cls, spec: InstrumentSpec) -> RenderSettings:
        """The scene's own defaults."""
        return cls(samples_per_chip=spec.samples_per_chip, averages=spec.averages,
                   uid_bits=spec.uid_bits, uid=spec.uid, code_index=spec.code_indices,
                   poly_u=spec.poly_u, poly_v=spec.poly_v)

    def __hash__(self) -> int:
        """The fields' hash, computed once (every column a frame renders looks its plan up
        under a key that holds the settings, and the code indices are 40 or more ints);
        not pickled (:meth:`__getstate__`), so a copy in another process hashes anew."""
        h = self.__dict__.get("_hash")
        if h is None:
            h = hash(tuple(getattr(self, f.name) for f in fields(self)))
            object.__setattr__(self, "_hash", h)
        return h

    def __getstate__(self) -> dict:
        """The fields, without the cached hash."""
        return {k: v for k, v in self.__dict__.items() if k != "_hash"}

    @property
    def frame_chips(self) -> int:
        """Chips per UID frame: n * N."""
        return self.uid_bits * ((1 << self.poly_u[0]) - 1)

    @property
    def frame_samples(self) -> int:
        """Samples per UID frame: n * N * S."""
        return self.frame_chips * self.samples_per_chip


def detector_response(f_hz: NDArray[np.float64], bandwidth_hz: float,
                      nyquist_hz: float) -> NDArray[np.float64]:
    """H(f): Gaussian (-3 dB at ``bandwidth_hz``) times the anti-alias taper; H(0) = 0 (AC)."""
    f = np.abs(np.asarray(f_hz, dtype=np.float64))
    h = np.exp(-0.5 * np.log(2.0) * (f / bandwidth_hz) ** 2)
    knee = 0.8 * nyquist_hz
    x = np.clip((f - knee) / (nyquist_hz - knee), 0.0, 1.0)
    h *= np.cos(0.5 * np.pi * x) ** 2
    h[f == 0] = 0.0
    return h


@functools.lru_cache(maxsize=8)
def _bin_weights(m: int, period: int, length: int, chip_rate_hz: float,
                 bandwidth_hz: float, nyquist_hz: float) -> NDArray[np.float64]:
    """(m,) H(f_q) sinc(q / nN) L / nN, f_q = q chip_rate / nN (read-only; nN = ``period``)."""
    q = np.arange(m)
    h = detector_response(q * chip_rate_hz / period, bandwidth_hz, nyquist_hz)
    weight = h * np.sinc(q / period) / period * length
    weight.flags.writeable = False
    return weight


def _uid_signs(uid: int, n: int) -> NDArray[np.float64]:
    """(-1)^bit_p(uid) for periods p = 0..n-1."""
    return np.where((uid >> np.arange(n)) & 1, -1.0, 1.0)


@dataclass(frozen=True, eq=False)
class ChipSpectra:
    """The nN-point DFTs of some Gold members' UID-signed bipolar chips, one table.

    ``table`` (M, A, B) read-only, complex128 or complex64: row ``row[i]`` is member i's
    DFT zero-padded to A B >= nN bins (``period`` = nN); ``spectra[i]`` is that (A, B) row.
    The table is what :meth:`Codebook.sum_delayed` reads, indexed by each term's row
    (:meth:`Codebook.stack`): no per-column copy of the members' spectra.
    """

    table: NDArray[np.complexfloating]
    row: dict[int, int]
    period: int

    def __getitem__(self, member: int) -> NDArray[np.complexfloating]:
        return self.table[self.row[member]]

    def __contains__(self, member: object) -> bool:
        return member in self.row


def _transform(poly_u: tuple[int, ...], poly_v: tuple[int, ...], members: tuple[int, ...],
               uid: int, uid_bits: int, single: bool) -> ChipSpectra:
    """:class:`ChipSpectra` of ``members`` (sorted, distinct), transformed _CHUNK_MEMBERS
    at a time straight into the table (each member's DFT is numpy's FFT of its own row,
    whatever the chunk: the same values as one transform of all)."""
    period = uid_bits * ((1 << poly_u[0]) - 1)
    b = math.isqrt(period - 1) + 1
    a = -(-period // b)
    table = np.zeros((len(members), a, b), dtype=np.complex64 if single else np.complex128)
    flat = table.reshape(len(members), a * b)
    signs = _uid_signs(uid, uid_bits)
    for lo in range(0, len(members), _CHUNK_MEMBERS):
        part = members[lo:lo + _CHUNK_MEMBERS]
        codes = gold_codes(poly_u, poly_v, part, field="code_index")
        chips = (np.where(codes, -1.0, 1.0)[:, None, :] * signs[None, :, None]
                 ).reshape(len(part), period)  # bipolar, +1 for bit 0
        into = flat[lo:lo + len(part), :period]
        if single:
            into[...] = np.fft.fft(chips, axis=1)  # rounded to complex64 as astype does
        else:
            np.fft.fft(chips, axis=1, out=into)
    table.flags.writeable = False
    return ChipSpectra(table, {i: n for n, i in enumerate(members)}, period)


class _SharedSpectra:
    """The process's chip-spectrum tables by (code pair, UID, members, precision), at most
    SHARED_SPECTRA_BYTES of them (least recently used dropped first); thread-safe."""

    def __init__(self) -> None:
        self._tables: OrderedDict[tuple, ChipSpectra] = OrderedDict()
        self._lock = threading.Lock()

    def get(self, poly_u: tuple[int, ...], poly_v: tuple[int, ...], members: tuple[int, ...],
            uid: int, uid_bits: int, single: bool) -> ChipSpectra:
        key = (poly_u, poly_v, members, uid, uid_bits, single)
        with self._lock:
            hit = self._tables.get(key)
            if hit is not None:
                self._tables.move_to_end(key)
                return hit
        built = _transform(poly_u, poly_v, members, uid, uid_bits, single)
        if built.table.nbytes <= SHARED_SPECTRA_BYTES:
            with self._lock:
                self._tables[key] = built
                while sum(t.table.nbytes for t in self._tables.values()) > SHARED_SPECTRA_BYTES:
                    self._tables.popitem(last=False)
        return built


_SHARED = _SharedSpectra()


class Codebook:
    """Filtered spectra and waveform tables of the Gold members an instrument emits, kept
    per configuration (settings, member, UID): ``spec`` gives the chip rate and the
    detector's bandwidth."""

    def __init__(self, spec: InstrumentSpec) -> None:
        self.spec = spec
        self._spectra: dict[tuple, dict] = {}

    def forget(self) -> None:
        """Drop every configuration's spectra and tables."""
        self._spectra.clear()

    def frame_bins(self, cfg: RenderSettings) -> tuple[NDArray[np.float64], int]:
        length = cfg.frame_samples
        m = length // 2 + 1
        f = np.arange(m) * self.spec.chip_rate_hz / cfg.frame_chips
        return f, length

    def code_spectra(self, cfg: RenderSettings, indices: tuple[int, ...], uid: int,
                      uid_bits: int) -> NDArray[np.complex128]:
        """(len(indices), L/2+1) filtered NRZ spectra of Gold members with a UID, scaled by L."""
        rows = self.spectrum_rows(cfg, indices, uid, uid_bits)
        return np.stack([rows[i] for i in indices])

    def spectrum_rows(self, cfg: RenderSettings, indices: tuple[int, ...], uid: int,
                       uid_bits: int) -> dict[int, NDArray[np.complex128]]:
        """Whole spectra by Gold member (L/2 + 1 bins: ``dft[q % nN] * weight[q]`` of
        :meth:`chip_spectra`), computed once per (settings, member, UID) and dropped
        with the settings."""
        rows = self._book(("rows", cfg.samples_per_chip, cfg.poly_u, cfg.poly_v, uid, uid_bits))
        missing = tuple(sorted({i for i in indices if i not in rows}))
        if missing:
            dfts, period = self.chip_spectra(cfg, missing, uid, uid_bits)
            weight = self.spectral_weight(cfg, period)
            q = np.arange(weight.size) % period
            for i in missing:
                rows[i] = dfts[i].reshape(-1)[q] * weight
        return rows

    def chip_spectra(self, cfg: RenderSettings, indices: Iterable[int], uid: int,
                      uid_bits: int, single: bool = False) -> tuple[ChipSpectra, int]:
        """(the :class:`ChipSpectra` of (at least) Gold members ``indices``: the nN-point
        DFTs of their UID-signed bipolar chips; the period nN in bins). A member's spectrum
        at bin q is ``dft[q % nN] * weight[q]`` (:meth:`spectral_weight`): the L/2 + 1 bins
        of an S-samples-per-chip frame repeat the chips' DFT S/2 times under one smooth
        weight, which :meth:`sum_delayed` exploits. ``single``: complex64 (rounded from
        complex128). One table per (code pair, UID, precision), the members asked for so
        far; a member not in it makes a new table of all of them. Tables are shared by
        every Codebook in the process (at most SHARED_SPECTRA_BYTES kept)."""
        key = ("chips", single, cfg.poly_u, cfg.poly_v, uid, uid_bits)
        book = self._book(key)
        have, wanted = book.get("spectra"), set(indices)
        if have is None or not wanted.issubset(have.row):
            members = tuple(sorted(wanted.union(have.row) if have else wanted))
            have = book["spectra"] = _SHARED.get(cfg.poly_u, cfg.poly_v, members, uid,
                                                 uid_bits, single)
        return have, have.period

    def _book(self, key: tuple) -> dict:
        """The codebook's entry ``key``: a dict (spectra by Gold member; the waveform
        tables' stack, rows and peaks), new and empty the first time; the whole codebook
        is dropped when it holds 16 entries (the settings changed that often)."""
        book = self._spectra.get(key)
        if book is None:
            if len(self._spectra) >= 16:
                self._spectra.clear()
            book = self._spectra[key] = {}
        return book

    def spectral_weight(self, cfg: RenderSettings, period: int) -> NDArray[np.float64]:
        """(L/2 + 1,) real weight of every member's spectrum: the detector's H(f), the NRZ
        chip's sinc and the scale L / (nN) (``period`` = nN chips per frame)."""
        length = period * cfg.samples_per_chip
        return _bin_weights(length // 2 + 1, period, length, self.spec.chip_rate_hz,
                            self.spec.detector_bandwidth_hz,
                            self.spec.chip_rate_hz * cfg.samples_per_chip / 2)

    def sample_shift_s(self, cfg: RenderSettings) -> float:
        tc = 1.0 / self.spec.chip_rate_hz
        return tc / 2 - tc / cfg.samples_per_chip / 2

    def waveform_table(self, cfg: RenderSettings, members: tuple[int, ...]
                        ) -> tuple[NDArray[np.float32], dict[int, int], dict[int, float]]:
        """((M, TABLE_PHASES + 1, 2 L) float32 waveforms: row p of a member's table is its
        filtered, unit-amplitude echo delayed by p / TABLE_PHASES of a sample (before the
        sample shift), one frame written twice (so any rotation is a slice); each Gold
        member's table in it; each member's largest |value| there). Built once per
        (settings, member) from the spectra and kept with them (TABLE_PHASES + 1 inverse
        FFTs per member); members not tabulated before are appended to the stack, so a
        batch's terms all read one array."""
        book = self._book(("table", cfg.samples_per_chip, cfg.poly_u, cfg.poly_v, cfg.uid,
                           cfg.uid_bits))
        where, peak = book.setdefault("row", {}), book.setdefault("peak", {})
        missing = tuple(sorted({i for i in members if i not in where}))
        if missing:
            # every member's chips transformed in one table (not one table per batch's new ones)
            self.chip_spectra(cfg, {*cfg.code_index, *missing}, cfg.uid, cfg.uid_bits)
            spectra = self.spectrum_rows(cfg, missing, cfg.uid, cfg.uid_bits)
            import scipy.fft  # deferred, as in _normal_table

            length = cfg.frame_samples
            m = length // 2 + 1
            step = 1.0 / (self.spec.chip_rate_hz * cfg.samples_per_chip * TABLE_PHASES)
            f = np.arange(m) * (self.spec.chip_rate_hz / cfg.frame_chips)
            ramps = np.exp(-2j * np.pi * np.outer(np.arange(TABLE_PHASES + 1) * step, f))
            new = np.empty((len(missing), TABLE_PHASES + 1, 2 * length), dtype=np.float32)
            for table, i in zip(new, missing, strict=True):
                table[:, :length] = scipy.fft.irfft((ramps * spectra[i]).astype(np.complex64),
                                                    n=length, axis=1, overwrite_x=True)
                table[:, length:] = table[:, :length]  # a rotation is one slice
                peak[i] = float(np.abs(table[:, :length]).max())
            book["stack"] = np.concatenate([book["stack"], new]) if where else new
            where.update({i: len(where) + n for n, i in enumerate(missing)})
        return book["stack"], where, peak

    @staticmethod
    def stack(dfts: ChipSpectra, members: Sequence[int]
               ) -> tuple[NDArray[np.complexfloating], NDArray[np.int64]]:
        """(the spectra table of ``dfts``, (M, A, B), read-only; each member's row there,
        (T,)): the two arguments :meth:`sum_delayed` takes (the table itself, not a copy
        of the members' rows)."""
        row = dfts.row
        return dfts.table, np.array([row[i] for i in members], dtype=np.int64)

    @staticmethod
    def sum_delayed(f0_hz: float, amps: NDArray[np.float64], taus: NDArray[np.float64],
                     spectra: NDArray[np.complexfloating], members: NDArray[np.int64],
                     period: int, weight: NDArray[np.float64],
                     out: NDArray[np.complexfloating] | None = None,
                     rows: Sequence[int] | None = None) -> NDArray[np.complexfloating]:
        """weight[q] sum_k amps_k dft_k[q % period] exp(-2j pi q f0 tau_k), q < m = weight.size:
        the per-channel work of the Fourier synthesis. Term k's chip spectrum dft_k is
        ``spectra[members[k]]`` (:meth:`chip_spectra`'s (A, B) arrays stacked,
        :meth:`stack`); their dtype, complex128 or complex64, is the sum's.

        With q = j period + p, the term is ``u_k[p] exp(-2j pi f0 tau_k j period)``, u_k =
        amps_k dft_k[p] exp(-2j pi p f0 tau_k) over one period (p < period), its ramp the
        outer product of two short exponentials (p = alpha B + beta): two complex
        multiplies over a period, then one multiply and add per further period of bins,
        where multiplying every bin by its own ramp and the member's whole spectrum costs
        three passes over all m bins (1.5x the work at S = 4, 2.4x at S = 16). The weight
        multiplies each sum once at the end. ``out``: an (m,) array of the spectra's
        dtype to write the sum into (overwritten). ``rows``: several sums at once, term k
        added into ``out[rows[k]]`` ((R, m) ``out``), the terms in the order given.

        Every complex product is numpy's (one rounding per part: ``re = fma(xr, yr,
        -(xi yi))``, ``im = fma(xr, yi, xi yr)``) and every sum a plain add, in this
        order; with numba (the ``fast`` extra), the sums run in one compiled call doing the
        same operations (:func:`cdma_lidar.scene.echo_kernel.synthesis_kernel`, complex64:
        ``single_synthesis_kernel``; the same values bit for bit,
        tests/scene/test_echo_kernel.py).
        """
        m = weight.size
        a, b = spectra.shape[1:]
        dtype = spectra.dtype  # complex64 in single precision
        w = -2.0 * np.pi * f0_hz * taus
        hi = (np.exp(1j * np.outer(w, b * np.arange(a))) * amps[:, None]).astype(dtype,
                                                                                  copy=False)
        lo = np.exp(1j * np.outer(w, np.arange(b))).astype(dtype, copy=False)
        starts = range(0, m, period)  # the first bin of each period of bins
        turns = np.exp(1j * np.outer(w, starts[1:])).astype(dtype, copy=False)
        total = np.empty(m, dtype=dtype) if out is None else out
        kernel = synthesis_kernel() if dtype == np.complex128 else single_synthesis_kernel()
        if kernel is not None:
            if not total.flags.c_contiguous:  # (the kernel writes into its 2-D view)
                raise ConfigError("out must be C-contiguous", "out")
            kernel(spectra.reshape(len(spectra), -1), np.asarray(members, dtype=np.int64),
                   np.zeros(len(members), dtype=np.int64) if rows is None
                   else np.asarray(rows, dtype=np.int64), lo, hi, turns, period,
                   total.reshape(-1, m))
            total *= weight
            return total
        sums = [total] if rows is None else list(total)
        # each sum's periods of bins, and the same lengths of one period's terms
        parts = [[row[q0:q0 + period] for q0 in starts] for row in sums]
        tmp = np.empty((a, b), dtype=dtype)
        scratch = np.empty(period, dtype=dtype)
        heads = [tmp.reshape(-1)[:part.size] for part in parts[0]]
        written = [False] * len(sums)  # a sum's first term is written, not added
        for k, i in enumerate(np.asarray(members).tolist()):
            np.multiply(spectra[i], lo[k], out=tmp)
            np.multiply(tmp, hi[k][:, None], out=tmp)
            r = 0 if rows is None else rows[k]
            (first, *rest), add = parts[r], written[r]
            written[r] = True
            if not add:
                first[...] = heads[0]
            else:
                np.add(first, heads[0], out=first)
            for part, head, turn in zip(rest, heads[1:], turns[k], strict=True):
                if not add:
                    np.multiply(head, turn, out=part)
                    continue
                product = scratch[:part.size]
                np.multiply(head, turn, out=product)
                np.add(part, product, out=part)
        for row, done in zip(sums, written, strict=True):
            if not done:
                row[...] = 0
        total *= weight
        return total

    def unit_signal_power(self, cfg: RenderSettings) -> float:
        """Mean square (V^2) of one channel's filtered waveform at amplitude 1 V."""
        spectra = self.code_spectra(cfg, (int(cfg.code_index[0]),), 0, 1)
        y = np.fft.irfft(spectra[0], n=cfg.samples_per_chip * ((1 << cfg.poly_u[0]) - 1))
        return float(np.mean(y * y))
