"""The codebook's chip-spectrum tables: built in chunks, shared, indexed without copies."""

from __future__ import annotations

import numpy as np

from cdma_lidar.firmware_model.gold import gold_code
from cdma_lidar.scene import codebook, load_scene
from cdma_lidar.scene.codebook import Codebook, RenderSettings
from cdma_lidar.scene.instrument import Instrument


def _own_transform(cfg: RenderSettings, member: int, uid: int, uid_bits: int) -> np.ndarray:
    """One member's DFT alone, as the codebook defines it (its UID-signed bipolar chips)."""
    bip = 1.0 - 2.0 * gold_code(cfg.poly_u, cfg.poly_v, member).astype(np.float64)
    signs = np.where((uid >> np.arange(uid_bits)) & 1, -1.0, 1.0)
    return np.fft.fft((signs[:, None] * bip[None, :]).reshape(-1))


def test_a_table_built_in_chunks_holds_each_members_own_transform_bit_for_bit():
    """More members than one chunk, in both precisions: every row is the member's own FFT
    (complex64: that FFT rounded), zero past the period, in the table's order."""
    cfg = RenderSettings.from_spec(load_scene("flat-wall").instrument)
    members = tuple(range(3, 3 + 2 * codebook._CHUNK_MEMBERS + 5))
    for single in (False, True):
        got = codebook._transform(cfg.poly_u, cfg.poly_v, members, 5, 3, single)
        assert not got.table.flags.writeable
        for i in members[::7] + members[-1:]:
            want = _own_transform(cfg, i, 5, 3)
            row = got[i].reshape(-1)
            np.testing.assert_array_equal(row[:got.period],
                                          want.astype(np.complex64) if single else want)
            assert not row[got.period:].any()


def test_instruments_of_one_configuration_share_one_table_and_columns_index_it():
    """A second Instrument of the same scene finds the first one's table (no transform
    again); the members a column needs are rows of that table, not a copy of them."""
    scene = load_scene("flat-wall")
    a, b = Instrument(scene, 1), Instrument(scene, 2)
    cfg = RenderSettings.from_spec(a.spec)
    members = cfg.code_index[::3]
    first, period = a.codebook.chip_spectra(cfg, cfg.code_index, cfg.uid, cfg.uid_bits)
    again, _ = b.codebook.chip_spectra(cfg, cfg.code_index, cfg.uid, cfg.uid_bits)
    assert again is first and period == first.period
    table, rows = Codebook.stack(first, members)
    assert table is first.table
    for i, r in zip(members, rows.tolist(), strict=True):
        np.testing.assert_array_equal(table[r], first[i])


def test_the_shared_tables_stay_within_their_bytes(monkeypatch):
    """The least recently used table goes when the next would pass SHARED_SPECTRA_BYTES;
    one larger than the bound is built but not kept."""
    cfg = RenderSettings.from_spec(load_scene("flat-wall").instrument)
    shared = codebook._SharedSpectra()
    one = codebook._transform(cfg.poly_u, cfg.poly_v, (0, 1), 0, 1, False).table.nbytes
    monkeypatch.setattr(codebook, "SHARED_SPECTRA_BYTES", 2 * one)
    x = shared.get(cfg.poly_u, cfg.poly_v, (0, 1), 0, 1, False)
    y = shared.get(cfg.poly_u, cfg.poly_v, (2, 3), 0, 1, False)
    assert shared.get(cfg.poly_u, cfg.poly_v, (0, 1), 0, 1, False) is x  # x is now newest
    shared.get(cfg.poly_u, cfg.poly_v, (4, 5), 0, 1, False)
    assert shared.get(cfg.poly_u, cfg.poly_v, (0, 1), 0, 1, False) is x
    assert shared.get(cfg.poly_u, cfg.poly_v, (2, 3), 0, 1, False) is not y  # y went
    big = shared.get(cfg.poly_u, cfg.poly_v, (0, 1, 2, 3, 4), 0, 1, False)
    assert shared.get(cfg.poly_u, cfg.poly_v, (0, 1, 2, 3, 4), 0, 1, False) is not big
