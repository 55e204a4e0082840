"""The noise draws of a batch of columns, computed block by block in the cache, against
the whole-batch formulas they replace, bit for bit (any batch size, block size, length
and repetition count, the block boundaries included)."""

from __future__ import annotations

import math

import numpy as np
import pytest
from fma_probes import blas_fuses
from hypothesis import given, settings
from hypothesis import strategies as st

from cdma_lidar.scene import codebook, echoes
from cdma_lidar.scene import sums as sums_module
from cdma_lidar.scene.noise_kernel import repetition_kernel, row_kernel
from cdma_lidar.scene.streams import from_seed_words, seed_words
from cdma_lidar.scene.sums import _BYTE_VARIANCE, _normal_table


def _repetition_sums_whole(rngs, means, sigmas, r):
    """draw_repetition_sums as one pass of each operation over the whole (B, L) batch (its
    bytes drawn as it draws them: rows of at most _BYTES_PER_DRAW bytes per draw, each draw
    a whole number of generator words)."""
    size = means[0].size
    draw = np.empty((len(rngs), size))
    for row, rng in zip(draw, rngs, strict=True):
        rng.standard_normal(out=row)
    draw *= np.sqrt(r * np.square(np.asarray(sigmas, dtype=np.float64))
                    + (r - 1) * _BYTE_VARIANCE)[:, None]
    for row, mean in zip(draw, means, strict=True):
        row += mean
    if r > 1:
        total = np.zeros(draw.shape, dtype=np.uint16 if (r - 1) * 255 < 1 << 16 else np.uint32)
        rows = max(1, sums_module._BYTES_PER_DRAW // size)
        for acc, rng in zip(total, rngs, strict=True):
            octets = np.concatenate([
                rng.bit_generator.random_raw(-(-n // 8)).view(np.uint8)[:n]
                for n in (min(rows, r - 1 - r0) * size for r0 in range(0, r - 1, rows))])
            acc += np.add.reduce(octets.reshape(-1, size), axis=0, dtype=total.dtype)
        uniforms = total.astype(np.float64)
        uniforms += 0.5 * (r - 1)
        uniforms *= 1.0 / 256
        draw -= uniforms
    return np.floor(draw, out=np.empty(draw.shape, dtype=np.int64), casting="unsafe")


def _table_sums_whole(rngs, means, stds):
    """_draw_table_sums as one pass of each operation over the whole (B, L) batch."""
    size = means[0].size
    quarter = -(-size // 4)
    words = np.empty((len(rngs), quarter), dtype=np.uint64)
    for row, rng in zip(words, rngs, strict=True):
        row[:] = rng.bit_generator.random_raw(quarter)
    draw = _normal_table().take(words.view(np.uint16)[:, :size])
    draw *= np.asarray(stds, dtype=np.float32)[:, None]
    for row, mean in zip(draw, means, strict=True):
        row += mean
    return np.floor(draw, out=np.empty(draw.shape, dtype=np.int64), casting="unsafe")


needs_numba = pytest.mark.skipif(row_kernel() is None, reason="numba (extra 'fast') not installed")


def test_every_compiled_kernel_is_there_where_numba_is():
    """With numba installed, no kernel quietly falls back to numpy (a numba whose
    internals moved would: compile_kernel logs it and returns None)."""
    pytest.importorskip("numba")
    from cdma_lidar.scene.echo_kernel import synthesis_kernel, terms_kernel

    assert all(k() is not None for k in (row_kernel, repetition_kernel, terms_kernel,
                                         synthesis_kernel))


def test_a_numba_without_the_needed_internals_falls_back_with_a_warning(caplog):
    pytest.importorskip("numba")
    from cdma_lidar.scene.noise_kernel import compile_kernel

    def signature(t, readonly):
        raise ImportError("no module named numba.np.random._moved")

    with caplog.at_level("WARNING", logger="cdma_lidar.scene.noise_kernel"):
        assert compile_kernel(lambda: None, signature, "numpy runs instead") is None
    assert "numpy runs instead" in caplog.text and "_moved" in caplog.text


@settings(max_examples=90, deadline=None)
@given(columns=st.integers(1, 9), size=st.integers(1, 70), r=st.sampled_from([1, 2, 10, 300]),
       block=st.sampled_from([1, 50, 64, 1 << 16]), draw=st.sampled_from([1, 100, 1 << 24]),
       seed=st.integers(0, 2**32 - 1),
       level=st.sampled_from(["exact", "exact, numpy", "accumulated", "accumulated, numpy"]))
def test_blocked_noise_equals_the_whole_batch(columns, size, r, block, draw, seed, level):
    """Every path against the whole-batch formulas of numpy's generators seeded by key:
    exact's compiled row kernel (its own PCG64 and ziggurat) and its numpy blocks (bytes
    in one draw per column or in several, uint16 or uint32 byte sums at R = 300),
    accumulated's compiled row kernel (where numba is installed) and its numpy blocks."""
    data = np.random.default_rng(seed)
    sigmas = (3.0 + 40 * data.random(columns)).tolist()
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(sums_module, "BLOCK_VALUES", block)
        mp.setattr(sums_module, "_BYTES_PER_DRAW", draw)
        if level.endswith(", numpy"):
            mp.setattr(sums_module, "row_kernel", lambda: None)
            mp.setattr(sums_module, "repetition_kernel", lambda: None)
        keys = [[seed, c] for c in range(columns)]
        if level.startswith("exact"):
            means = [data.normal(0, 5e3, size) for _ in range(columns)]
            got = sums_module._draw_exact_sums(seed_words(keys), means, sigmas, r)
            want = _repetition_sums_whole([np.random.default_rng(k) for k in keys], means,
                                          sigmas, r)
        else:
            means = [data.normal(0, 5e3, size).astype(np.float32) for _ in range(columns)]
            stds = [np.float32(s) for s in sigmas]

            got = sums_module._draw_table_sums(seed_words(keys), means, stds)
            want = _table_sums_whole([np.random.default_rng(k) for k in keys], means, stds)
    assert got.dtype == sums_module.SUM_TYPE and got.shape == (columns, size)
    np.testing.assert_array_equal(got, want)


_WORD = st.one_of(st.sampled_from([0, 1, 2**63, 2**64 - 1]), st.integers(0, 2**64 - 1))


@needs_numba
@settings(max_examples=80, deadline=None)
@given(seed=st.lists(_WORD, min_size=4, max_size=4), size=st.integers(1, 70))
def test_compiled_row_draws_numpys_pcg64_words(seed, size):
    """The kernel's own PCG64 (seeding, 128-bit steps, XSL-RR output) against numpy's
    generator seeded with the same words, any seed (the carries of the extremes
    included), read through a table that maps each 16-bit quarter to itself."""
    seed = np.array(seed, dtype=np.uint64)
    got = np.empty(size, dtype=np.int32)
    row_kernel()(seed, np.arange(1 << 16, dtype=np.float32), np.float32(1),
                 np.zeros(size, dtype=np.float32), got)
    (rng,) = from_seed_words(seed[None])
    want = rng.bit_generator.random_raw(-(-size // 4)).view(np.uint16)[:size]
    np.testing.assert_array_equal(got, want)


@needs_numba
@settings(max_examples=60, deadline=None)
@given(size=st.integers(1, 40), scale=st.floats(1.0, 400.0, width=32),
       mean=st.floats(-3e5, 3e5, width=32), seed=st.lists(_WORD, min_size=4, max_size=4))
def test_compiled_row_equals_numpy_float32(size, scale, mean, seed):
    """The compiled kernel on one row against numpy's float32 operations written out
    (product, sum, floor, each rounded to float32) on numpy's words, means far from zero
    on both sides."""
    seed = np.array(seed, dtype=np.uint64)
    means = (mean + np.random.default_rng(size).normal(0, 50, size)).astype(np.float32)
    table = _normal_table()
    got = np.empty(size, dtype=np.int32)
    row_kernel()(seed, table, np.float32(scale), means, got)
    (rng,) = from_seed_words(seed[None])
    words = rng.bit_generator.random_raw(-(-size // 4)).view(np.uint16)[:size]
    want = table[words.astype(np.intp)] * np.float32(scale)
    want += means
    np.testing.assert_array_equal(got, np.floor(want).astype(np.int32))


@needs_numba
def test_compiled_row_refuses_other_precisions_and_seeds():
    kernel, table = row_kernel(), _normal_table()
    seed, out = np.zeros(4, dtype=np.uint64), np.empty(8, dtype=np.int32)
    with pytest.raises(TypeError):  # float64 means would be added in float64
        kernel(seed, table, np.float32(1), np.zeros(8), out)
    with pytest.raises(RuntimeError, match="4 words"):
        kernel(seed[:3], table, np.float32(1), np.zeros(8, dtype=np.float32), out)
    with pytest.raises(RuntimeError, match="mean must match"):
        kernel(seed, table, np.float32(1), np.zeros(7, dtype=np.float32), out)


def _repetition_row(seed, r, scale, means):
    """exact's kernel on one row: (its sums, its Gaussians, its byte words)."""
    size = means.size
    got, draw = np.empty(size, dtype=np.int32), np.empty(size)
    total, words = np.empty(size, dtype=np.uint32), np.empty(-(-(r - 1) * size // 8), np.uint64)
    repetition_kernel()(np.asarray(seed, dtype=np.uint64), r, scale, means, draw, total,
                        words, got)
    return got, draw, words


@needs_numba
@settings(max_examples=60, deadline=None)
@given(size=st.integers(1, 40), r=st.sampled_from([1, 2, 3, 10, 301]),
       scale=st.floats(1.0, 400.0), mean=st.floats(-3e7, 3e7),
       seed=st.lists(_WORD, min_size=4, max_size=4))
def test_compiled_repetition_row_equals_numpy_float64(size, r, scale, mean, seed):
    """exact's compiled kernel on one row against numpy's generator (seeded with the same
    words, any seed) and numpy's float64 operations written out (byte sums, product, sum,
    uniforms, difference, floor): means far from zero on both sides, byte counts that are
    not a multiple of 8, and the generator's words after the Gaussians the same."""
    means = mean + np.random.default_rng(size).normal(0, 50, size)
    got, draw, words = _repetition_row(seed, r, scale, means)
    (rng,) = from_seed_words(np.array([seed], dtype=np.uint64))
    z = rng.standard_normal(size)
    n = (r - 1) * size
    raw = rng.bit_generator.random_raw(-(-n // 8))
    octets = raw.view(np.uint8)[:n].reshape(r - 1, size)
    want = z * scale
    want += means
    want -= (octets.sum(axis=0, dtype=np.int64) + 0.5 * (r - 1)) * (1.0 / 256)
    np.testing.assert_array_equal(draw, z)
    np.testing.assert_array_equal(words, raw)
    np.testing.assert_array_equal(got, np.floor(want).astype(np.int32))


@needs_numba
@pytest.mark.parametrize("size", [1, 8188, 300_000])
def test_compiled_normals_equal_numpys(size):
    """The kernel's own ziggurat against numpy's standard_normal on the same generator:
    the same values bit for bit (300 000 draws reach the wedges and the tail beyond
    3.654, where exp and log1p enter), and the generator's next words the same."""
    seed = seed_words([[7, size]])[0]
    _, draw, words = _repetition_row(seed, 2, 1.0, np.zeros(size))
    (rng,) = from_seed_words(seed[None])
    want = rng.standard_normal(size)
    np.testing.assert_array_equal(draw, want)
    if size == 300_000:
        assert np.count_nonzero(np.abs(want) > 3.6541528853610088) > 10  # the tail
    np.testing.assert_array_equal(words, rng.bit_generator.random_raw(words.size))


@needs_numba
def test_compiled_repetition_row_keeps_numpys_rounding_order():
    """Rows whose floors tell the float64 orders apart (random values almost never do):
    ``(z s + m) - u`` against ``z s + (m - u)`` and ``(z s - u) + m`` (z s rounded to u,
    m = 1 - 2^-53: a tie), and the rounded product against a fused multiply-add (z s = 1
    - d exactly, d > 0 small enough that it rounds to 1, m = -1). z and the byte come
    from the generator; the scale is chosen around them. The kernel gives numpy's order
    on both."""
    from fractions import Fraction

    def near(target, z, below):
        """A scale s within 8 steps of target / z with fl(z s) = target, its exact product
        below the target where ``below`` (None if there is none)."""
        s = target / z
        for k in range(-8, 9):
            t = s
            for _ in range(abs(k)):
                t = np.nextafter(t, math.copysign(math.inf, k))
            if z * t == target and (not below or Fraction(z) * Fraction(t) < target):
                return float(t)
        return None

    got, want, others = [], [], {"m - u first": [], "z s - u first": [], "fused": []}
    for r in (2, 1):  # u from a byte, m = 1 - 2^-53; no bytes, m = -1
        for key in range(100):  # the first z with a scale (most have one)
            seed = seed_words([[key]])[0]
            (probe,) = from_seed_words(seed[None])
            z = probe.standard_normal()
            u = ((probe.bit_generator.random_raw() & 0xFF) + 0.5) / 256 if r == 2 else 0.0
            scale, mean = (near(u, z, False), 1 - 2.0**-53) if r == 2 else (near(1.0, z, True),
                                                                            -1.0)
            if scale is not None:
                break
        got.append(int(_repetition_row(seed, r, scale, np.array([mean]))[0][0]))
        want.append(math.floor((z * scale + mean) - u))
        others["m - u first"].append(math.floor(z * scale + (mean - u)))
        others["z s - u first"].append(math.floor((z * scale - u) + mean))
        others["fused"].append(math.floor(Fraction(z) * Fraction(scale) + Fraction(mean) - u))
    assert all(order != want for order in others.values())  # the rows tell them apart
    assert got == want


@needs_numba
def test_compiled_rows_refuse_other_types_and_shapes():
    kernel = repetition_kernel()
    seed, mean, draw = np.zeros(4, dtype=np.uint64), np.zeros(8), np.zeros(8)
    total, words, out = np.zeros(8, np.uint32), np.zeros(2, np.uint64), np.empty(8, np.int32)
    kernel(seed, 3, 1.0, mean, draw, total, words, out)
    for args in ((seed.astype(np.int64), 3, 1.0, mean, draw, total, words, out),
                 (seed, 3, 1.0, mean.astype(np.float32), draw, total, words, out),
                 (seed, 3, 1.0, mean, draw, total.astype(np.uint16), words, out),
                 (seed, 3, 1.0, mean, draw, total, words, out.astype(np.int64)),
                 (seed, 3, 1.0, mean[::2], draw[:4], total[:4], words, out[:4])):
        with pytest.raises(TypeError):
            kernel(*args)
    for args in ((seed, 3, 1.0, mean[:7], draw, total, words, out),
                 (seed, 3, 1.0, mean, draw, total, words[:1], out),
                 (seed, 0, 1.0, mean, draw, total, words, out)):
        with pytest.raises(RuntimeError, match="match the row"):
            kernel(*args)
    with pytest.raises(RuntimeError, match="4 words"):
        kernel(seed[:3], 3, 1.0, mean, draw, total, words, out)


@needs_numba
@pytest.mark.parametrize(("level", "name"), [("accumulated", "row_kernel"),
                                             ("exact", "repetition_kernel")])
def test_render_is_the_same_with_or_without_numba(level, name):
    """paper-scene1's first 24 columns, a batch out of order with a repeat, and calibration
    shots: the compiled kernel's sums (it ran on every column) equal the numpy path's bit
    for bit."""
    from cdma_lidar.scene import load_scene
    from cdma_lidar.scene.instrument import Instrument, RenderSettings

    inst = Instrument(load_scene(f"paper-scene1?fidelity={level}"), 3)
    cfg = RenderSettings.from_spec(inst.spec)
    home = {"terms_kernel": echoes, "synthesis_kernel": codebook}.get(name, sums_module)
    compiled, calls = getattr(home, name)(), []

    def counted(*args):
        calls.append(args[-1].size)
        compiled(*args)

    out = []
    for kernel in (lambda: counted, lambda: None):
        with pytest.MonkeyPatch.context() as mp:
            mp.setattr(home, name, kernel)
            got = [inst.render_sums(cols, cfg, 4) for cols in (list(range(24)), [9, 2, 9, 0])]
            got.append(inst.render_sums([0, 5], cfg, 4, calibration=True))
        out.append(got)
    assert calls == [cfg.frame_samples] * 30
    for (sums, drawn), (want, want_drawn) in zip(*out, strict=True):
        assert drawn.all()
        np.testing.assert_array_equal(drawn, want_drawn)
        np.testing.assert_array_equal(sums, want)


@pytest.mark.parametrize("level", ["exact", "accumulated"])
def test_render_sums_do_not_depend_on_the_block_size(level):
    """paper-scene1's first 24 columns (lit and empty) and calibration shots, their echoes
    made and scaled two or three columns at a time against all in one block: the same
    sums, bit for bit."""
    from cdma_lidar.scene import load_scene
    from cdma_lidar.scene.instrument import Instrument, RenderSettings

    inst = Instrument(load_scene(f"paper-scene1?fidelity={level}"), 5)
    cfg = RenderSettings.from_spec(inst.spec)
    cols = list(range(24))
    out = {}
    for block in (1 << 30, 2 * cfg.frame_samples + 1, 3 * cfg.frame_samples):
        with pytest.MonkeyPatch.context() as mp:
            mp.setattr(sums_module, "BLOCK_VALUES", block)
            mp.setattr(echoes, "BLOCK_VALUES", block)
            inst.forget()
            sums, drawn = inst.render_sums(cols, cfg, 2)
            cal, ok = inst.render_sums([0, 1, 2], cfg, 2, calibration=True)
        assert drawn.all() and ok.all()
        out[block] = (sums, cal)
    ref = out.pop(1 << 30)
    assert np.any(inst.truth.hits.lit[:, cols].any(axis=0))
    for sums, cal in out.values():
        np.testing.assert_array_equal(sums, ref[0])
        np.testing.assert_array_equal(cal, ref[1])


_WALL = None  # paper-scene1 on 12 columns, built on first use


@settings(max_examples=30, deadline=None)
@given(data=st.data())
def test_batched_echo_terms_equal_the_columns_own(data):
    """The batch's echo terms and noise levels (gathered at once) against _echo_terms and
    noise_rms_v_at column by column, bit for bit: any columns (repeats, empty ones),
    powers with channels switched off (0 W) or scaled, the scene's default power, scan
    or calibration noise."""
    global _WALL
    from cdma_lidar.scene import load_scene
    from cdma_lidar.scene.instrument import Instrument, RenderSettings

    if _WALL is None:
        _WALL = Instrument(load_scene("paper-scene1?instrument.columns=12"), 0)
    inst = _WALL
    assert 0 < sum(inst.lit_channels(c).size for c in range(inst.columns)) < 12 * 40
    cfg = RenderSettings.from_spec(inst.spec)
    cols = data.draw(st.lists(st.integers(0, inst.columns - 1), min_size=1, max_size=8))
    items = []
    for c in cols:
        kind = data.draw(st.sampled_from(["default", "scaled", "some off", "all off"]))
        p = inst.default_power_w[:, c].copy()
        if kind == "scaled":
            p *= data.draw(st.floats(0.1, 3.0))
        elif kind == "some off":
            p[data.draw(st.lists(st.integers(0, inst.channels - 1), max_size=20))] = 0.0
        elif kind == "all off":
            p[:] = 0.0
        items.append((c, None if kind == "default" else p))
    assert inst.noise.fixed_v is None  # the link budget's noise, summed over channels
    calibration = data.draw(st.booleans())
    sigmas = inst.noise.rms_items(cfg, items, calibration)
    for (c, p), sigma in zip(items, sigmas.tolist(), strict=True):
        assert sigma == inst.noise_rms_v_at(c, cfg, p, calibration)
    got = inst.echoes.batch_terms(cfg, items, False)
    for (c, p), terms in zip(items, got, strict=True):
        want = inst.echoes.terms(c, cfg, p, False)
        if want is None:
            assert terms is None
            continue
        np.testing.assert_array_equal(terms[0], want[0])
        np.testing.assert_array_equal(terms[1], want[1])
        assert terms[2] == want[2]
        np.testing.assert_array_equal(terms[3], want[3])


def _tabulated_reference(inst, cfg, column):
    """tabulated_echo as first written: one column, its terms in their own order by saxpy.
    Where the numba kernel renders and this BLAS's saxpy does not fuse its multiply-adds
    (the two round differently, both valid), the column alone through the kernel instead."""
    from scipy.linalg.blas import saxpy

    from cdma_lidar.scene.echo_kernel import terms_kernel

    length = cfg.frame_samples
    if terms_kernel() is not None and not blas_fuses():
        alone = np.zeros((1, length), dtype=np.float32)
        inst.echoes.tabulated_echoes(cfg, [(column, None)], False, alone)
        return alone[0]
    out = np.zeros(length, dtype=np.float32)
    amps, taus, members, _ = inst.echoes.terms(column, cfg, None, False)
    steps = taus * (inst.spec.chip_rate_hz * cfg.samples_per_chip * codebook.TABLE_PHASES)
    whole = np.floor(steps)
    delay, phase = np.divmod(whole.astype(np.int64), codebook.TABLE_PHASES)
    stack, where, _ = inst.codebook.waveform_table(cfg, members)
    for a, t, d, p, i in zip(amps.tolist(), (steps - whole).tolist(), delay.tolist(),
                             phase.tolist(), members, strict=True):
        s = length - d % length
        out = saxpy(stack[where[i], p, s:s + length], out, a=a * (1.0 - t))
        out = saxpy(stack[where[i], p + 1, s:s + length], out, a=a * t)
    return out


def _wall_with_ghosts(ghosts: bool):
    """A wall of six channels on five columns; a ghost on channels 2 and 0 of columns 0
    and 3 (its terms come after the echoes, out of channel order)."""
    import tomllib
    from importlib import resources

    from cdma_lidar.scene.instrument import Instrument
    from cdma_lidar.scene.scenefile import parse_scene

    doc = tomllib.loads(resources.files("cdma_lidar.scene").joinpath(
        "presets", "flat-wall.toml").read_text("utf-8"))
    doc.pop("shortcuts")
    doc["instrument"].update({"wavelengths": {"count": 6}, "columns": 5})
    if ghosts:
        doc["instrument"]["ghosts"] = [{"distance_m": 4.0, "amplitude_v": 4e-3,
                                        "channels": [2, 0], "columns": [0, 3]}]
    return Instrument(parse_scene(doc), 1)


@pytest.mark.parametrize("ghosts", [False, True])
def test_tabulated_echoes_of_a_batch_equal_each_column_alone(ghosts):
    """accumulated's echoes of a batch (each row's terms in passes of up to four, with
    numba) against each column's terms added in their own order by saxpy, bit for bit
    (_wall_with_ghosts)."""
    from cdma_lidar.scene.instrument import RenderSettings

    inst = _wall_with_ghosts(ghosts)
    cfg = RenderSettings.from_spec(inst.spec)
    items = [(c, None) for c in (3, 0, 4, 3, 1)]
    batch = np.zeros((len(items), cfg.frame_samples), dtype=np.float32)
    inst.echoes.tabulated_echoes(cfg, items, False, batch)
    assert np.all(np.abs(batch).max(axis=1) > 0)
    for (c, _), row in zip(items, batch, strict=True):
        np.testing.assert_array_equal(_tabulated_reference(inst, cfg, c), row)
    terms = inst.echoes.terms(0, cfg, None, False)
    assert (terms[3].tolist()[-2:] == [2, 0]) == ghosts  # the ghosts' terms, last


@pytest.mark.parametrize("ghosts", [False, True])
def test_exact_echoes_of_a_batch_equal_each_column_alone(ghosts):
    """exact's echoes of a batch (spectra summed channel by channel without ghosts, term by
    term with them) against echo() column by column, bit for bit (_wall_with_ghosts)."""
    from cdma_lidar.scene.instrument import RenderSettings

    inst = _wall_with_ghosts(ghosts)
    cfg = RenderSettings.from_spec(inst.spec)
    items = [(c, inst.default_power_w[:, c]) for c in (3, 0, 4, 3, 1)]
    batch = inst.echoes.batch(cfg, items, False)[0]
    assert np.all(np.abs(batch).max(axis=1) > 0)
    for (c, p), row in zip(items, batch, strict=True):
        np.testing.assert_array_equal(inst.echo(c, cfg, p), row)


def test_waveform_tables_appended_member_by_member_equal_tables_built_at_once():
    """The stack of waveform tables grows as members are first used: each member's rows
    and peak are where its index says, whatever order the members came in."""
    from cdma_lidar.scene.instrument import RenderSettings

    grown, at_once = _wall_with_ghosts(False), _wall_with_ghosts(False)
    cfg = RenderSettings.from_spec(grown.spec)
    for members in ((5,), (3, 5, 9), (0, 9)):
        stack, where, peak = grown.codebook.waveform_table(cfg, members)
    assert stack.shape[0] == len(where) == 4
    whole, at, top = at_once.codebook.waveform_table(cfg, (9, 0, 5, 3))
    for i in (0, 3, 5, 9):
        np.testing.assert_array_equal(stack[where[i]], whole[at[i]])
        assert peak[i] == top[i]


def test_tabulated_echoes_refuse_a_batch_they_cannot_add_into_in_place():
    """BLAS adds into the batch's flat view: a strided batch (its flat form a copy, the
    sums lost) is refused, not silently left unchanged."""
    from cdma_lidar.scene.instrument import RenderSettings

    inst = _wall_with_ghosts(False)
    cfg = RenderSettings.from_spec(inst.spec)
    batch = np.zeros((2, 2 * cfg.frame_samples), dtype=np.float32)[:, ::2]
    with pytest.raises(ValueError, match="C-contiguous"):
        inst.echoes.tabulated_echoes(cfg, [(0, None), (1, None)], False, batch)
