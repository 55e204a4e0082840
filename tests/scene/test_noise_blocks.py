"""The noise draws of a batch of columns, computed block by block in the cache, against
the whole-batch formulas they replace, bit for bit (any batch size, block size, length
and repetition count, the block boundaries included)."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from cdma_lidar.scene import instrument
from cdma_lidar.scene.instrument import _BYTE_VARIANCE, _normal_table


def _repetition_sums_whole(rngs, means, sigmas, r):
    """draw_repetition_sums as one pass of each operation over the whole (B, L) batch."""
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
        for acc, rng in zip(total, rngs, strict=True):
            n = (r - 1) * size
            octets = rng.bit_generator.random_raw(-(-n // 8)).view(np.uint8)[:n]
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


@settings(max_examples=40, deadline=None)
@given(columns=st.integers(1, 9), size=st.integers(1, 70), r=st.sampled_from([1, 2, 10, 300]),
       block=st.sampled_from([1, 50, 64, 1 << 16]), seed=st.integers(0, 2**32 - 1),
       level=st.sampled_from(["exact", "accumulated"]))
def test_blocked_noise_equals_the_whole_batch(columns, size, r, block, seed, level):
    data = np.random.default_rng(seed)
    sigmas = (3.0 + 40 * data.random(columns)).tolist()
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(instrument, "_BLOCK_VALUES", block)
        if level == "exact":
            means = [data.normal(0, 5e3, size) for _ in range(columns)]

            def run(fn):
                return fn([np.random.default_rng([seed, c]) for c in range(columns)], means,
                          sigmas, r)

            got = run(instrument.draw_repetition_sums)
            want = run(_repetition_sums_whole)
        else:
            means = [data.normal(0, 5e3, size).astype(np.float32) for _ in range(columns)]
            stds = [np.float32(s) for s in sigmas]

            def run(fn):
                return fn([np.random.default_rng([seed, c]) for c in range(columns)], means,
                          stds)

            got = run(instrument._draw_table_sums)
            want = run(_table_sums_whole)
    assert got.dtype == np.int64 and got.shape == (columns, size)
    np.testing.assert_array_equal(got, want)


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
            mp.setattr(instrument, "_BLOCK_VALUES", block)
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
    """The batch's echo terms (gathered at once) against _echo_terms column by column:
    any columns (repeats, empty ones), powers with channels switched off (0 W) or
    scaled, and the scene's default power."""
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
    got = inst._batch_echo_terms(cfg, items, False)
    for (c, p), terms in zip(items, got, strict=True):
        want = inst._echo_terms(c, cfg, p, False)
        if want is None:
            assert terms is None
            continue
        np.testing.assert_array_equal(terms[0], want[0])
        np.testing.assert_array_equal(terms[1], want[1])
        assert terms[2] == want[2]
