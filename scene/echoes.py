"""The echoes at the photodiode: our lit channels, the grating's ghosts, other users.

::

    v(t) = sum_k A_k c_k(t - tau_k)                 echoes of the lit channels
         + sum_g A_g c_k(t - tau_g)                 grating ghosts (fixed distance, own code)
         + sum_u A_u c_u(t - tau_u)                 other LiDARs (same family, their own UID)
    A_k   = G_tia R_resp M P_rx[k, col]   (cdma_lidar.scene.linkbudget)      (V)
    tau_k = 2 r / c + system_delay                                             (s)

Sampling instants: ADC sample i of a frame is taken at ``(i + 1/2) / (S * chip_rate)``
after the start of the emitted frame, so sample i of chip m lies inside chip m and an
echo with ``tau = d / (S * chip_rate)`` peaks exactly at lag d in the receive chain
(``tau' = tau + Tc/2 - Ts/2`` folds the pulse centre and the sample phase in).

Channels whose ray hits nothing are skipped entirely. ``exact`` renders a column's echo
by the Fourier synthesis (:meth:`Echoes.echo`, a batch: :meth:`Echoes.batch`),
``accumulated`` interpolates each code's tabulated waveform (:meth:`Echoes.tabulated_echo`).
The spectra and tables are the :class:`cdma_lidar.scene.codebook.Codebook`'s; the other
users' light, the same for every column that sees the same users, is kept here (its own
cache).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from numpy.typing import NDArray

from cdma_lidar.errors import ConfigError
from cdma_lidar.scene.codebook import TABLE_PHASES, Codebook, RenderSettings
from cdma_lidar.scene.echo_kernel import terms_kernel
from cdma_lidar.scene.linkbudget import link_gain_v_m2_per_w
from cdma_lidar.scene.model import Scene
from cdma_lidar.scene.sums import BLOCK_VALUES
from cdma_lidar.scene.truth import Truth
from cdma_lidar.units import range_to_delay_s

__all__ = ["ECHO_CACHE_BYTES", "Echoes"]

#: Bytes of noise-free column echoes kept between frames (a static scene's echo is the same
#: in every frame; only the noise is new).
ECHO_CACHE_BYTES = 128 << 20


class Echoes:
    """Noise-free photodiode voltage of a column's echoes, ghosts and other users.

    ``truth``: the scene's hits; ``amplitude_per_w`` (K, C): each pixel's echo amplitude
    (V) per watt of laser power (the link budget's); ``default_power_w`` (K, C) W.
    """

    def __init__(self, scene: Scene, truth: Truth, amplitude_per_w: NDArray[np.float64],
                 default_power_w: NDArray[np.float64], codebook: Codebook) -> None:
        self.scene, self.spec, self.codebook = scene, scene.instrument, codebook
        h = truth.hits
        self.channels, self.columns = h.range_m.shape
        self.default_power_w = default_power_w
        #: the channels each column lights (lit_channels), read-only
        self._lit_channels = [np.flatnonzero(h.lit[:, col]) for col in range(self.columns)]
        for chans in self._lit_channels:
            chans.flags.writeable = False
        #: per-pixel amplitude (V) per watt of laser power; 0 where nothing is hit
        self.gain_v_per_w = amplitude_per_w
        #: per-pixel round-trip delay (s) including the hidden system delay
        self.delay_s = np.where(h.lit, range_to_delay_s(np.where(h.lit, h.range_m, 1.0))
                                + self.spec.system_delay_s, np.nan)
        self._users: dict[tuple, NDArray[np.float64]] = {}
        self._users_bytes = 0

    def forget(self) -> None:
        """Drop the other users' light kept between frames."""
        self._users.clear()
        self._users_bytes = 0

    def calibration_gain_v_per_w(self) -> float:
        """Amplitude (V) per watt of one channel's echo from the zeroth-order target."""
        cal = self.scene.calibration
        return (link_gain_v_m2_per_w(self.spec) * cal.reflectivity * cal.zeroth_order_efficiency
                / cal.target_distance_m**2)

    def lit_channels(self, column: int) -> NDArray[np.int64]:
        """Channels whose ray hits an object at ``column``."""
        return self._lit_channels[column]

    def terms(self, column: int, cfg: RenderSettings, power_w: NDArray[np.float64] | None,
                    calibration: bool) -> tuple[NDArray[np.float64], NDArray[np.float64],
                                                tuple[int, ...], NDArray[np.int64]] | None:
        """(amplitudes (V), delays (s, sample shift included), Gold members, channels) of the
        column's echoes and ghosts (in that order: the echoes by ascending channel); None
        when nothing is lit."""
        power = self.default_power_w[:, column] if power_w is None else np.asarray(power_w)
        if calibration:
            cal = self.scene.calibration
            chans = np.arange(self.channels)
            amps = self.calibration_gain_v_per_w() * power
            taus = np.full(self.channels, range_to_delay_s(cal.target_distance_m)
                           + self.spec.system_delay_s)
        else:
            chans = self.lit_channels(column)
            amps = self.gain_v_per_w[chans, column] * power[chans]
            taus = self.delay_s[chans, column]
        if self.spec.ghosts:
            amps, taus, chans = self._with_ghosts(column, amps, taus, chans)
        keep = amps != 0
        if not keep.all():
            amps, taus, chans = amps[keep], taus[keep], chans[keep]
        if not amps.size:
            return None
        members = tuple(int(cfg.code_index[c]) for c in chans.tolist())
        return amps, taus + self.codebook.sample_shift_s(cfg), members, chans

    def batch_terms(self, cfg: RenderSettings,
                          items: Sequence[tuple[int, NDArray[np.float64] | None]],
                          calibration: bool) -> list[tuple | None]:
        """:meth:`terms` of each (column, power), the scan's common case (no ghosts,
        not calibration) gathered for the whole batch at once (the same values)."""
        if calibration or self.spec.ghosts or not items:
            return [self.terms(col, cfg, p, calibration) for col, p in items]
        cols = [col for col, _ in items]
        chans = [self._lit_channels[col] for col in cols]
        counts = [c.size for c in chans]
        if not sum(counts):
            return [None] * len(items)
        ch = np.concatenate(chans)
        which = np.repeat(np.arange(len(items)), counts)
        power = np.stack([self.default_power_w[:, col] if p is None else np.asarray(p)
                          for col, p in items])
        amps = self.gain_v_per_w[ch, np.repeat(cols, counts)] * power[which, ch]
        taus = self.delay_s[ch, np.repeat(cols, counts)] + self.codebook.sample_shift_s(cfg)
        keep = amps != 0
        if not keep.all():
            amps, taus, ch, which = amps[keep], taus[keep], ch[keep], which[keep]
        members = np.asarray(cfg.code_index, dtype=np.int64)[ch].tolist()
        ends = np.cumsum(np.bincount(which, minlength=len(items))).tolist()
        out: list[tuple | None] = []
        for j, end in enumerate(ends):
            start = ends[j - 1] if j else 0
            out.append((amps[start:end], taus[start:end], tuple(members[start:end]),
                        ch[start:end]) if end > start else None)
        return out

    def echo(self, column: int, cfg: RenderSettings,
             power_w: NDArray[np.float64] | None = None,
             calibration: bool = False, single: bool = False) -> NDArray[np.floating]:
        """Noise-free photodiode voltage (V) of one frame (L samples) at ``column``.

        Our own channels (lit ones only) and the ghosts configured for this column; other
        users are not periodic in our frame in general and are added by :meth:`render`.
        ``power_w``: laser power per channel (W) at this column. In ``calibration`` mode every
        channel sees the zeroth-order target. ``single``: computed in single precision
        (complex64 spectra, float32 result, relative error about 1e-7 of the largest
        echo, i.e. below 1e-4 LSB for echoes inside the ADC's range); about half the cost.
        """
        length = cfg.frame_samples
        m = length // 2 + 1
        f0 = self.spec.chip_rate_hz / cfg.frame_chips if m > 1 else 0.0  # bin spacing (Hz)
        terms = self.terms(column, cfg, power_w, calibration)
        if terms is None:
            return np.zeros(length, dtype=np.float32 if single else np.float64)
        amps, taus, members, _ = terms
        book = self.codebook
        dfts, period = book.chip_spectra(cfg, {*cfg.code_index, *members}, cfg.uid,
                                         cfg.uid_bits, single)  # one table
        total = book.sum_delayed(f0, amps, taus, *book.stack(dfts, members), period,
                                 book.spectral_weight(cfg, period))
        return np.fft.irfft(total, n=length)

    @staticmethod
    def echo_tabulated(cfg: RenderSettings) -> bool:
        """Whether ``accumulated`` renders echoes from waveform tables under ``cfg`` (the
        tables of every code member fit ECHO_CACHE_BYTES) or by the Fourier synthesis."""
        return (TABLE_PHASES + 1) * cfg.frame_samples * 8 * len(set(cfg.code_index)) \
            <= ECHO_CACHE_BYTES

    def tabulated_echo(self, column: int, cfg: RenderSettings,
                       power_w: NDArray[np.float64] | None = None,
                       calibration: bool = False, out: NDArray[np.float32] | None = None
                       ) -> NDArray[np.float32]:
        """:meth:`echo` from a table of waveforms, float32: ``accumulated`` fidelity's echo.

        Each Gold member's filtered waveform is tabulated once per configuration at
        TABLE_PHASES + 1 delays p / TABLE_PHASES of a sample, p = 0..TABLE_PHASES (float32,
        :meth:`cdma_lidar.scene.codebook.Codebook.waveform_table`). A channel at delay
        ``tau`` (d whole samples plus p + t table steps, 0 <= t < 1) adds
        ``A ((1 - t) w_p + t w_(p+1))`` rotated by d samples: no Fourier transform per
        column. Linear interpolation between phases 1/8 of a sample apart errs by about
        ``t (1 - t) (pi f / (8 f_s))^2 / 2`` of the component at frequency f: below 0.5 % of
        the echo's peak on paper-scene1 (tests/scene/test_fidelity.py), a pure low-pass with
        no delay bias to first order. ``out``: a contiguous (L,) float32 array to write into
        (its values are not read).
        """
        if out is None:
            out = np.empty(cfg.frame_samples, dtype=np.float32)
        self.tabulated_echoes(cfg, [(column, power_w)], calibration, out[None, :])
        return out

    def tabulated_echoes(self, cfg: RenderSettings,
                          items: Sequence[tuple[int, NDArray[np.float64] | None]],
                          calibration: bool, out: NDArray[np.float32], gain: float = 1.0,
                          start: float = 0.0, terms: list[tuple | None] | None = None
                          ) -> NDArray[np.float64]:
        """``start`` (float32) plus :meth:`tabulated_echo` of each (column, power) times
        ``gain``, written into the rows of ``out`` (B, L) float32 (C-contiguous; what it
        held is overwritten, a row with no echo is ``start``): the delays of the whole
        batch split into samples, table phases and fractions at once, then two saxpy calls
        per channel, in the batch's order (each row its terms in its own order), reading
        one stack of every member's table (BLAS reads and writes at offsets into the flat
        stack and batch: no view per call). With numba, :mod:`cdma_lidar.scene.echo_kernel`
        does the whole batch in one call, each row's terms in passes over the row of up to
        four terms (their eight multiply-adds in the saxpy calls' order: the same values
        where BLAS fuses its multiply-adds), so a row is read and written once per four
        terms.
        Returns (B,) each row's sum of |amplitude x gain| times its members' largest
        |table value|: a bound on the largest |value| added to the row (an interpolation
        between two phases stays within their extremes), found with no pass over the row.
        ``terms``: the items' :meth:`batch_terms`, where the caller has them."""
        if not out.flags.c_contiguous:  # (then the flat view below is a view, not a copy)
            raise ConfigError("out must be C-contiguous: BLAS adds into its flat view", "out")
        if terms is None:
            terms = self.batch_terms(cfg, items, calibration)
        lit = [j for j, t in enumerate(terms) if t is not None]
        out[[j for j, t in enumerate(terms) if t is None]] = start
        if not lit:
            return np.zeros(len(items))
        length = cfg.frame_samples
        rows = np.repeat(lit, [len(terms[j][2]) for j in lit])
        amps = np.concatenate([terms[j][0] for j in lit]) * gain
        steps = np.concatenate([terms[j][1] for j in lit]) * (
            self.spec.chip_rate_hz * cfg.samples_per_chip * TABLE_PHASES)
        members = [i for j in lit for i in terms[j][2]]
        stack, where, peak = self.codebook.waveform_table(cfg, tuple(members))
        whole = np.floor(steps)
        frac = steps - whole
        delay, phase = np.divmod(whole.astype(np.int64), TABLE_PHASES)
        # member's table, row p, rotated by the delay; the term's row of the batch
        x_at = (np.array([where[i] for i in members]) * (TABLE_PHASES + 1) + phase) * (
            2 * length) + length - delay % length
        y_at = rows * length
        first, second = amps * (1.0 - frac), amps * frac
        y, flat = out.reshape(-1), stack.reshape(-1)
        kernel = terms_kernel()
        if kernel is not None:  # the whole batch in one compiled call, rows set as reached
            kernel(flat, x_at, y_at, first.astype(np.float32), second.astype(np.float32),
                   np.float32(start), y, length)
        else:
            from scipy.linalg.blas import saxpy  # deferred, as in _normal_table

            out[lit] = start
            two = 2 * length
            for a, b, x0, y0 in zip(first.tolist(), second.tolist(), x_at.tolist(),
                                    y_at.tolist(), strict=True):
                saxpy(flat, y, length, a, x0, 1, y0)  # y[y0:y0 + L] += a w_p[rotated]
                saxpy(flat, y, length, b, x0 + two, 1, y0)  # ... + b w_(p+1)[rotated]
        largest = np.array([peak[i] for i in members])
        return np.bincount(rows, np.abs(amps) * largest, minlength=len(items))

    def _with_ghosts(self, column: int, amps: NDArray[np.float64], taus: NDArray[np.float64],
                     chans: NDArray[np.int64]) -> tuple[NDArray, NDArray, NDArray]:
        """The column's echoes plus the grating ghosts configured for it."""
        amps_l, taus_l, chans_l = [amps], [taus], [chans]
        for g in self.spec.ghosts:
            if g.columns and column not in g.columns:
                continue
            gch = np.asarray(g.channels if g.channels else range(self.channels), dtype=np.int64)
            amps_l.append(np.full(gch.size, g.amplitude_v))
            taus_l.append(np.full(gch.size, range_to_delay_s(g.distance_m)
                                  + self.spec.system_delay_s))
            chans_l.append(gch)
        return np.concatenate(amps_l), np.concatenate(taus_l), np.concatenate(chans_l)

    def other_users_signal(self, column: int, cfg: RenderSettings,
                           total_samples: int) -> NDArray[np.float64] | None:
        """Other LiDARs' light at our photodiode (V) over ``total_samples`` (None if none).

        The same for every column that sees the same users: computed once per set of
        users and settings (read-only result).
        """
        seen = tuple(i for i, u in enumerate(self.spec.other_users)
                     if not u.columns or column in u.columns)
        if not seen:
            return None
        users = [self.spec.other_users[i] for i in seen]
        key = ("users", seen, cfg, total_samples)
        hit = self._users.get(key)
        if hit is not None:
            return hit
        out = self._users_signal(users, cfg, total_samples)
        out.flags.writeable = False
        if self._users_bytes + out.nbytes > ECHO_CACHE_BYTES:
            self._users.clear()
            self._users_bytes = 0
        self._users[key] = out
        self._users_bytes += out.nbytes
        return out

    def _users_signal(self, users: list, cfg: RenderSettings,
                      total_samples: int) -> NDArray[np.float64]:
        out = np.zeros(total_samples)
        idx = np.arange(total_samples)
        for u in users:
            ucfg = RenderSettings(cfg.samples_per_chip, 1, u.uid_bits, u.uid, (u.code_index,),
                                  cfg.poly_u, cfg.poly_v)
            book = self.codebook
            f, length = book.frame_bins(ucfg)
            dfts, period = book.chip_spectra(ucfg, (u.code_index,), u.uid, u.uid_bits)
            frame = np.fft.irfft(book.sum_delayed(
                f[1], np.array([u.amplitude_v]),
                np.array([u.delay_s + book.sample_shift_s(cfg)]),
                *book.stack(dfts, (u.code_index,)), period,
                book.spectral_weight(ucfg, period)), n=length)
            out += frame[idx % length]
        return out

    def batch(self, cfg: RenderSettings, items: list[tuple[int, NDArray[np.float64]]],
                calibration: bool, gain: float = 1.0, shift: float = 0.0
                ) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """((B, L) float64 ``gain * echo + shift`` of each (column, power), (B,) the
        largest |value| of each): the spectra of about BLOCK_VALUES values at a time (one
        buffer, in the cache), their batched inverse FFT and its extremes. The gain
        multiplies the spectral weight and the shift is the DC bin's (the defaults give
        :meth:`echo`'s values bit for bit: the same operations on each value, a column's
        channels added in the same order)."""
        length = cfg.frame_samples
        m = length // 2 + 1
        f0 = self.spec.chip_rate_hz / cfg.frame_chips if m > 1 else 0.0
        terms = self.batch_terms(cfg, items, calibration)
        lit = [j for j, t in enumerate(terms) if t is not None]
        out = np.empty((len(items), length))
        out[[j for j, t in enumerate(terms) if t is None]] = shift
        peaks = np.empty(len(items))
        peaks[:] = abs(shift)
        if not lit:
            return out, peaks
        dfts, period = self.codebook.chip_spectra(
            cfg, {*cfg.code_index, *(i for j in lit for i in terms[j][2])}, cfg.uid,
            cfg.uid_bits)
        spectra, members = self.codebook.stack(dfts, [i for j in lit for i in terms[j][2]])
        first = np.cumsum([0, *(len(terms[j][2]) for j in lit)]).tolist()  # items' terms
        weight = self.codebook.spectral_weight(cfg, period)
        if gain != 1.0:
            weight = weight * gain
        step = max(1, BLOCK_VALUES // length)
        sums = np.empty((min(step, len(lit)), m), dtype=np.complex128)
        for b0 in range(0, len(lit), step):
            block = lit[b0:b0 + step]
            part = sums[:len(block)]
            self.codebook.sum_delayed(f0, np.concatenate([terms[j][0] for j in block]),
                              np.concatenate([terms[j][1] for j in block]), spectra,
                              members[first[b0]:first[b0 + len(block)]], period, weight,
                              out=part,
                              rows=[r for r, j in enumerate(block) for _ in terms[j][2]])
            part[:, 0] += shift * length  # the weight is 0 at DC (AC coupling)
            if block[-1] - block[0] == len(block) - 1:  # consecutive rows: written in place
                wave = np.fft.irfft(part, n=length, axis=1, out=out[block[0]:block[-1] + 1])
            else:
                out[block] = wave = np.fft.irfft(part, n=length, axis=1)
            peaks[block] = np.maximum(wave.max(axis=1), -wave.min(axis=1))  # in the cache
        return out, peaks

