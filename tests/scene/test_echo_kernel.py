"""The compiled echo kernels (numba, the ``fast`` extra) against the paths they replace,
bit for bit: accumulated's against the two BLAS saxpy calls per term it fuses, wherever
BLAS's saxpy fuses its multiply-adds (a probe decides; elsewhere the two paths round
differently, both valid); exact's Fourier synthesis against numpy's complex products and
sums, wherever numpy fuses its complex product (a probe decides, as above)."""

from __future__ import annotations

import numpy as np
import pytest
from fma_probes import blas_fuses
from hypothesis import given, settings
from hypothesis import strategies as st

from cdma_lidar.scene import codebook, echoes, sums
from cdma_lidar.scene.codebook import Codebook
from cdma_lidar.scene.echo_kernel import (
    single_synthesis_kernel,
    synthesis_kernel,
    terms_kernel,
)
from cdma_lidar.scene.instrument import Instrument

#: The module whose compiled kernel of each name the rendering calls.
KERNEL_HOMES = {"synthesis_kernel": codebook, "single_synthesis_kernel": codebook,
                "terms_kernel": echoes, "repetition_kernel": sums, "row_kernel": sums}


needs_kernel = pytest.mark.skipif(
    terms_kernel() is None or not blas_fuses(),
    reason="numba (extra 'fast') not installed, or this BLAS's saxpy does not fuse")


def _saxpy_terms(table, x_at, y_at, a, b, start, y, length):
    """The numpy path: the rows the terms reach set to ``start``, then two saxpy calls per
    term."""
    from scipy.linalg.blas import saxpy

    for y0 in y_at.tolist():
        y[y0:y0 + length] = start
    for x0, y0, ak, bk in zip(x_at.tolist(), y_at.tolist(), a.tolist(), b.tolist(),
                              strict=True):
        saxpy(table, y, length, ak, x0, 1, y0)
        saxpy(table, y, length, bk, x0 + 2 * length, 1, y0)


@needs_kernel
@settings(max_examples=80, deadline=None)
@given(length=st.integers(1, 70), rows=st.integers(1, 4), terms=st.integers(0, 12),
       seed=st.integers(0, 2**32 - 1), zeros=st.sampled_from(["none", "a", "b", "both"]),
       scale=st.sampled_from([1e-3, 1.0, 3e5]), by_row=st.booleans())
def test_the_kernel_sets_rows_then_adds_each_term_as_its_two_saxpy_calls(
        length, rows, terms, seed, zeros, scale, by_row):
    """Random tables, rotations, rows and coefficients (zero ones included: BLAS skips
    them, so does the kernel), lengths across the SIMD widths and their tails; terms
    in any row order, or row by row (``by_row``: the runs of one row's terms that the
    kernel adds in passes of up to four, as a batch does)."""
    rng = np.random.default_rng(seed)
    table = (rng.standard_normal(9 * 2 * length) * scale).astype(np.float32)
    x_at = rng.integers(0, 7 * 2 * length + length + 1, terms).astype(np.int64)
    y_at = (rng.integers(0, rows, terms) * length).astype(np.int64)
    if by_row:
        y_at.sort()
    a = (rng.standard_normal(terms) * scale).astype(np.float32)
    b = (rng.standard_normal(terms) * scale).astype(np.float32)
    if zeros in ("a", "both"):
        a[::2] = 0
    if zeros == "b":
        b[1::2] = 0
    if zeros == "both":
        b[::2] = 0  # terms that add nothing
    # -0.0: what a skipped zero coefficient leaves and an added 0 w would not
    start = np.float32(rng.choice([-0.0, rng.standard_normal() * scale]))
    before = (rng.standard_normal((rows + 1) * length) * scale).astype(np.float32)
    want, got = before.copy(), before.copy()  # (rows no term reaches are left as they are)
    _saxpy_terms(table, x_at, y_at, a, b, start, want, length)
    for arr in (table, x_at, y_at, a, b):
        arr.flags.writeable = False
    terms_kernel()(table, x_at, y_at, a, b, start, got, length)
    np.testing.assert_array_equal(got.view(np.uint32), want.view(np.uint32))  # -0.0 too


@needs_kernel
def test_the_kernel_refuses_terms_outside_the_table_or_the_batch_and_other_types():
    kernel = terms_kernel()
    table, y = np.zeros(3 * 4 + 8, dtype=np.float32), np.zeros(8, dtype=np.float32)
    one = np.ones(1, dtype=np.float32)
    zero = np.float32(0)
    for x0, y0 in ((9, 0), (-1, 0), (0, 5), (0, -1), (0, 2)):
        with pytest.raises(RuntimeError, match="outside"):
            kernel(table, np.array([x0]), np.array([y0]), one, one, zero, y, 4)
    with pytest.raises(TypeError):
        kernel(table.astype(np.float64), np.array([0]), np.array([0]), one, one, zero, y, 4)


def _with_and_without(name, level, url, take):
    """``take(inst, cfg, columns)`` of a fresh instrument on ``url`` at ``level``, with
    the compiled kernel ``name`` and with it set aside (the plans keep the echoes, so
    each run needs its own instrument)."""
    from cdma_lidar.scene import load_scene
    from cdma_lidar.scene.instrument import RenderSettings

    scene = load_scene(f"{url}?fidelity={level}")
    out = []
    home = KERNEL_HOMES[name]
    for kernel in (getattr(home, name), lambda: None):
        with pytest.MonkeyPatch.context() as mp:
            mp.setattr(home, name, kernel)
            inst = Instrument(scene, 3)
            out.append(take(inst, RenderSettings.from_spec(inst.spec), list(range(inst.columns))))
    return out


@needs_kernel
@pytest.mark.parametrize("url", ["paper-scene1", "near-far", "multi-user"])
def test_accumulated_render_is_the_same_with_or_without_the_echo_kernel(url):
    """Whole frames (a batch out of order with a repeat, calibration shots) and one echo:
    the same sums and echoes bit for bit."""
    def take(inst, cfg, cols):
        return [*inst.render_sums(cols, cfg, 1), *inst.render_sums([2, 0, 2], cfg, 1),
                *inst.render_sums([0, 1], cfg, 1, calibration=True), inst.tabulated_echo(1, cfg)]

    for got, want in zip(*_with_and_without("terms_kernel", "accumulated", url, take),
                         strict=True):
        np.testing.assert_array_equal(got, want)


def _numpy_fuses_complex_products(dtype: type = np.complex128, h: int = 30) -> bool:
    """Whether numpy's complex product (of ``dtype``) rounds each part once, in its SIMD
    body, its tail and its loop over one scalar: with x = (1 + 2^-h)(1 + i), the real part
    of x x is fma(xr, xr, -(xi xi)) = xr^2 - round(xr^2) = 2^-2h, the rounding error of
    xr^2 (exact product 1 + 2^(1-h) + 2^-2h; h = 30 for float64, 12 for float32), and 0
    when both products are rounded first."""
    x = dtype(complex(1 + 2.0**-h, 1 + 2.0**-h))
    for n in (3, 67):
        row = np.full(n, x)
        if not (np.all((row * row).real == 2.0**(-2 * h))
                and np.all((row * x).real == 2.0**(-2 * h))):
            return False
    return True


needs_synthesis = pytest.mark.skipif(
    synthesis_kernel() is None or not _numpy_fuses_complex_products(),
    reason="numba (extra 'fast') not installed, or numpy's complex product does not fuse")


@needs_synthesis
@settings(max_examples=80, deadline=None)
@given(a=st.integers(1, 9), b=st.integers(1, 9), cut=st.integers(0, 8),
       bins=st.integers(1, 200), rows=st.integers(1, 4), terms=st.integers(0, 12),
       members=st.integers(1, 3), seed=st.integers(0, 2**32 - 1),
       scale=st.sampled_from([1e-300, 1e-3, 1.0, 1e150]), zero=st.booleans())
def test_the_synthesis_kernel_is_numpys_complex_products_and_sums(a, b, cut, bins, rows,
                                                                  terms, members, seed,
                                                                  scale, zero):
    """Random chip spectra, delays, amplitudes (zero ones included), rows (repeated, out
    of order, some never written) and lengths: every period shape (one period shorter
    than the bins, several, a last one of one bin), magnitudes near both ends of float64;
    the kernel's sums equal _sum_delayed's numpy path bit for bit, -0.0 included."""
    period = max(1, a * b - min(cut, a * b - 1))
    rng = np.random.default_rng(seed)
    spectra = (rng.standard_normal((members, a, b)) + 1j * rng.standard_normal((members, a, b))
               ) * scale
    which = rng.integers(0, members, terms)
    amps = rng.standard_normal(terms) * (0.0 if zero else 1.0)
    taus = rng.uniform(0.0, 2e-6, terms)
    where = rng.integers(0, rows, terms).tolist()
    weight = rng.uniform(0.0, 2.0, bins)
    out = []
    for kernel in (synthesis_kernel, lambda: None):
        with pytest.MonkeyPatch.context() as mp:
            mp.setattr(codebook, "synthesis_kernel", kernel)
            got = np.full((rows, bins), np.nan + 0j)
            Codebook.sum_delayed(3.1e4, amps, taus, spectra, which, period, weight,
                                 out=got, rows=where)
            out.append(got)
    np.testing.assert_array_equal(out[0].view(np.uint64), out[1].view(np.uint64))


@needs_synthesis
def test_the_synthesis_kernel_refuses_terms_it_cannot_place_and_other_types():
    kernel = synthesis_kernel()
    one = np.ones((1, 1), dtype=np.complex128)
    spectra, out = np.ones((1, 4), dtype=np.complex128), np.zeros((2, 5), dtype=np.complex128)
    ramps = np.ones((1, 2), dtype=np.complex128)
    for member, row in ((1, 0), (-1, 0), (0, 2), (0, -1)):
        with pytest.raises(RuntimeError, match="out of range"):
            kernel(spectra, np.array([member]), np.array([row]), ramps, ramps, one, 4, out)
    with pytest.raises(RuntimeError, match="covering every bin"):  # 2 periods of 2 < 5 bins
        kernel(spectra, np.array([0]), np.array([0]), ramps, ramps, one, 2, out)
    with pytest.raises(TypeError):
        kernel(spectra.astype(np.complex64), np.array([0]), np.array([0]), ramps, ramps, one,
               4, out)


@needs_synthesis
@pytest.mark.parametrize("url", ["paper-scene1", "multi-user", "flat-wall"])
def test_exact_render_is_the_same_with_or_without_the_synthesis_kernel(url):
    """Whole frames, calibration shots, the repetitions CAPTURE RAW returns and one echo:
    the same integers and volts bit for bit."""
    def take(inst, cfg, cols):
        return [*inst.render_sums(cols, cfg, 1),
                *inst.render_sums([0, 1], cfg, 1, calibration=True),
                inst.render_exact(1, cfg, 2), inst.echo(1, cfg)]

    for got, want in zip(*_with_and_without("synthesis_kernel", "exact", url, take),
                         strict=True):
        np.testing.assert_array_equal(got, want)


needs_single_synthesis = pytest.mark.skipif(
    single_synthesis_kernel() is None or not _numpy_fuses_complex_products(np.complex64, 12),
    reason="numba (extra 'fast') not installed, or numpy's complex64 product does not fuse")


@needs_single_synthesis
@settings(max_examples=60, deadline=None)
@given(a=st.integers(1, 9), b=st.integers(1, 9), cut=st.integers(0, 8),
       bins=st.integers(1, 200), rows=st.integers(1, 4), terms=st.integers(0, 12),
       members=st.integers(1, 3), seed=st.integers(0, 2**32 - 1),
       scale=st.sampled_from([1e-30, 1e-3, 1.0, 1e15]), zero=st.booleans())
def test_the_single_synthesis_kernel_is_numpys_complex64_products_and_sums(
        a, b, cut, bins, rows, terms, members, seed, scale, zero):
    """The complex64 twin of the test above: every product and sum rounded to float32
    as numpy's complex64 passes round them (a product computed in double and rounded
    once would differ), bit for bit, -0.0 included."""
    period = max(1, a * b - min(cut, a * b - 1))
    rng = np.random.default_rng(seed)
    spectra = ((rng.standard_normal((members, a, b)) + 1j * rng.standard_normal((members, a, b)))
               * scale).astype(np.complex64)
    which = rng.integers(0, members, terms)
    amps = rng.standard_normal(terms) * (0.0 if zero else 1.0)
    taus = rng.uniform(0.0, 2e-6, terms)
    where = rng.integers(0, rows, terms).tolist()
    weight = rng.uniform(0.0, 2.0, bins)
    out = []
    for kernel in (single_synthesis_kernel, lambda: None):
        with pytest.MonkeyPatch.context() as mp:
            mp.setattr(codebook, "single_synthesis_kernel", kernel)
            got = np.full((rows, bins), np.nan + 0j, dtype=np.complex64)
            Codebook.sum_delayed(3.1e4, amps, taus, spectra, which, period, weight,
                                 out=got, rows=where)
            out.append(got)
    np.testing.assert_array_equal(out[0].view(np.uint32), out[1].view(np.uint32))


@needs_single_synthesis
def test_accumulated_fourier_render_is_the_same_with_or_without_the_single_kernel(monkeypatch):
    """Where accumulated's waveform tables would not fit (paper-massive's case, made
    here by a small cache), its
    echoes come from the single-precision Fourier synthesis: whole frames, calibration
    shots and one echo, the same with the compiled kernel as with numpy's passes."""
    monkeypatch.setattr(echoes, "ECHO_CACHE_BYTES", 1 << 16)

    def take(inst, cfg, cols):
        assert not inst.echo_tabulated(cfg)
        return [*inst.render_sums(cols, cfg, 1),
                *inst.render_sums([0, 1], cfg, 1, calibration=True),
                inst.echo(1, cfg, single=True)]

    for got, want in zip(*_with_and_without("single_synthesis_kernel", "accumulated",
                                            "paper-scene1", take), strict=True):
        np.testing.assert_array_equal(got, want)
