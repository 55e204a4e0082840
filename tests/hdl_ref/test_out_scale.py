"""out_scale (round and saturate) against the model's scaling, every mode at every shift.

Every rounding mode at every ``out_shift`` 0..62 (the model's whole range), with
random raw words of every magnitude up to the build's RAW_W, exact ties at the
shift (q 2^s + 2^(s-1), both signs, q even and odd), both extremes of the raw
range and output widths from 8 to 32 bits, so saturation happens on both rails.
Two mutants (a 16-bit half-LSB constant, a symmetric negative rail) must be caught.
"""

from __future__ import annotations

import numpy as np
import pytest

from cdma_lidar.firmware_model.chain import scale_out as _scale
from cdma_lidar.hdl_ref import cosim
from cdma_lidar.hdl_ref.mutants import MUTANTS, mutated_copy
from cdma_lidar.rounding import ROUNDING_MODES

GENERICS = {"RAW_W": 44, "OUT_W": 32, "TAG_W": 8}
RAW_W = GENERICS["RAW_W"]
BENCH = "cdma_lidar.hdl_ref.tb.test_out_scale"


def _batches() -> list[dict]:
    rng = np.random.default_rng(17)
    lo, hi = -(1 << (RAW_W - 1)), (1 << (RAW_W - 1)) - 1
    batches = []
    for mode, name in enumerate(ROUNDING_MODES):
        for shift in range(63):
            raws = [lo, hi, 0, -1, 1]
            for _ in range(10):
                bits = int(rng.integers(1, RAW_W))
                raws.append(int(rng.integers(-(1 << (bits - 1)), 1 << (bits - 1))))
            if 1 <= shift < RAW_W - 2:
                for q in (2, 3, -2, -3, int(rng.integers(-(1 << (RAW_W - 2 - shift)),
                                                         1 << (RAW_W - 2 - shift)))):
                    raws.append(q * (1 << shift) + (1 << (shift - 1)))
            out_bits = (8, 12, 16, 24, 32)[shift % 5]
            batches.append({"shift": shift, "rounding": mode, "out_bits": out_bits,
                            "raws": raws, "name": name})
    return batches


BATCHES = _batches()


def _expected(batch: dict) -> list[int]:
    raw = np.array(batch["raws"], dtype=np.int64)
    return _scale(raw, batch["shift"], batch["name"], batch["out_bits"]).tolist()


def _run(build_dir, name: str) -> list[list[int]]:
    job = {"batches": [{k: b[k] for k in ("shift", "rounding", "out_bits", "raws")}
                       for b in BATCHES]}
    return cosim.run_job("out_scale", BENCH, build_dir, job, name=name)["batches"]


def _wrong_batches(words: list[list[int]]) -> list[str]:
    return [f"{b['name']} shift {b['shift']}" for b, w in zip(BATCHES, words, strict=True)
            if w != _expected(b)]


def test_batches_cover_ties_rails_and_every_shift():
    assert {(b["rounding"], b["shift"]) for b in BATCHES} == \
        {(m, s) for m in range(3) for s in range(63)}
    rails = [any(v in (-(1 << (b["out_bits"] - 1)), (1 << (b["out_bits"] - 1)) - 1)
                 for v in _expected(b)) for b in BATCHES]
    assert sum(rails) > 60


@pytest.mark.hdl
def test_out_scale_equals_model(hdl_build_root):
    build_dir = cosim.build("out_scale", GENERICS, hdl_build_root / "out_scale")
    assert _wrong_batches(_run(build_dir, "all")) == []


@pytest.mark.hdl
@pytest.mark.parametrize("mutant", [m for m in MUTANTS if m.file == "out_scale.v"],
                         ids=lambda m: m.name)
def test_out_scale_mutant_is_caught(hdl_build_root, mutant):
    rtl = mutated_copy(mutant, hdl_build_root / f"rtl_{mutant.name}")
    build_dir = cosim.build("out_scale", GENERICS, hdl_build_root / f"out_scale_{mutant.name}",
                            rtl_dir=rtl)
    assert _wrong_batches(_run(build_dir, "mutant")), f"{mutant.name} was not caught"
