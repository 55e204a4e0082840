"""The kernel cost model: auto's rule on given estimates, the calibration cache, the estimates.

Deterministic: the rule is checked on hand-made estimate tables and on the built-in
coefficients, never on timings; the calibration itself is run once, for its form.
"""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from cdma_lidar.errors import ConfigError
from cdma_lidar.firmware_model.correlators import GatePlan, choose_correlator, costs, estimates
from cdma_lidar.firmware_model.correlators.costs import (
    COSTS_ENV,
    DEFAULT_COEFFICIENTS,
    MEMORY_FLOOR,
    MEMORY_HEADROOM,
    TRADE_SPEEDUP,
    Coefficients,
    Estimate,
    choose,
)

GIB = float(1 << 30)


def test_the_fastest_kernel_wins_when_memory_is_comparable():
    est = {"a": Estimate(2.0, 1 * GIB), "b": Estimate(1.0, 1.9 * GIB), "c": Estimate(3.0, GIB)}
    assert choose(est) == "b"


def test_a_memory_hog_is_passed_over_for_the_fastest_lean_enough_kernel():
    est = {"hog": Estimate(0.1, 5 * GIB), "lean": Estimate(1.0, 1 * GIB),
           "mid": Estimate(0.5, 2 * GIB)}
    assert choose(est) == "mid"  # 2 GiB <= 2 x 1 GiB; the 5 GiB one is out
    del est["mid"]
    assert choose(est) == "lean"


def test_small_absolute_memory_differences_do_not_count():
    est = {"a": Estimate(1.0, 1e6), "b": Estimate(0.5, 1e6 + MEMORY_FLOOR)}
    assert choose(est) == "b"  # 60x the leanest, but only 64 MiB above it
    est["b"] = Estimate(0.5, 1e6 + MEMORY_FLOOR + 1)
    assert choose(est) == "a"


def test_memory_is_traded_for_time_only_when_both_are_worth_it():
    lean = Estimate(40.0, 0.2 * GIB)
    est = {"lean": lean, "direct": Estimate(1.0, 0.2 * GIB + MEMORY_HEADROOM)}
    assert choose(est) == "direct"  # 40x faster for at most 1 GiB more: worth it
    est["direct"] = Estimate(1.0, 0.2 * GIB + MEMORY_HEADROOM + 1)
    assert choose(est) == "lean"  # over the headroom: never
    est["direct"] = Estimate(40.0 / TRADE_SPEEDUP * 1.01, 0.8 * GIB)
    assert choose(est) == "lean"  # under 4x faster: 4x the memory is not worth it
    est["direct"] = Estimate(40.0 / TRADE_SPEEDUP, 0.8 * GIB)
    assert choose(est) == "direct"


def test_memory_the_rest_of_the_chain_holds_counts_for_every_kernel():
    est = {"lean": Estimate(2.0, 100e6), "fast": Estimate(1.0, 500e6)}
    assert choose(est) == "lean"  # 5x the leanest kernel
    assert choose(est, shared=300e6) == "fast"  # 800 MB against 400 MB for the whole call
    assert choose(est, shared=100e6) == "lean"  # 600 against 200


def test_the_receiver_tells_auto_what_the_chain_holds():
    from cdma_lidar.firmware_model.receiver import FastReceiver, ReceiverConfig

    codes = np.random.default_rng(1).integers(0, 2, (40, 2047), dtype=np.uint8)
    one = FastReceiver(ReceiverConfig(uid_bits=1), codes).plan.shared_bytes
    many = FastReceiver(ReceiverConfig(uid_bits=8, averages=2), codes).plan.shared_bytes
    frame = FastReceiver(ReceiverConfig(uid_bits=1), codes, columns=160).plan.shared_bytes
    assert 0 < one < many and frame > 100 * one


def test_ties_go_to_the_first_and_infinite_costs_never_win():
    est = {"first": Estimate(1.0, GIB), "second": Estimate(1.0, GIB),
           "never": Estimate(math.inf, 0.0)}
    assert choose(est) == "first"
    assert choose({"never": Estimate(math.inf, 0.0)}) == ""


def _plan(n, k, s, count, lag_lo=0, columns=1, y_bound=None):
    rng = np.random.default_rng(n + k)
    bip = (1 - 2 * rng.integers(0, 2, (k, n))).astype(np.int8)
    return GatePlan(bip, s, lag_lo, count, y_bound=y_bound, columns=columns)


def test_the_issue_cases_do_not_go_to_the_fft():
    # degree 18, S = 64, K = 1 and 4, 64-lag gate: the FFT was chosen and 13x slower
    for k in (1, 4):
        plan = _plan(2**18 - 1, k, 64, 66)
        assert choose_correlator(plan, DEFAULT_COEFFICIENTS) != "fft"
    # whole period of a degree-13 code: the FFT; the paper frame's class: the matrix product
    assert choose_correlator(_plan(8191, 40, 4, 4 * 8191 + 2), DEFAULT_COEFFICIENTS) == "fft"
    assert choose_correlator(_plan(2047, 40, 4, 66, columns=160),
                             DEFAULT_COEFFICIENTS) == "matmul"


def test_estimates_grow_with_the_work():
    co = DEFAULT_COEFFICIENTS
    small, wide = _plan(2047, 40, 4, 66), _plan(2047, 40, 4, 66, y_bound=1 << 45)
    assert small.matmul_limbs() == 1 and wide.matmul_limbs() > 1
    for name in ("matmul", "fft", "direct"):
        a, b = estimates(small, co)[name], estimates(wide, co)[name]
        assert b.seconds > a.seconds, name  # limbs cost
        more = estimates(_plan(2047, 80, 4, 66), co)[name]
        assert more.seconds > a.seconds and more.peak_bytes >= a.peak_bytes, name


def test_coefficients_must_be_positive_numbers():
    with pytest.raises(ConfigError, match="mac"):
        Coefficients(mac=0.0, byte=1.0, fft=1.0, call=1.0)
    with pytest.raises(ConfigError, match="call"):
        Coefficients(mac=1.0, byte=1.0, fft=1.0, call=math.nan)
    with pytest.raises(ConfigError, match="ram"):
        Coefficients(mac=1.0, byte=1.0, fft=1.0, call=1.0, ram=0.5)  # main memory < cache


def test_streaming_from_main_memory_costs_the_ram_ratio():
    """Codes far beyond the cache, read once per lag, cost ``ram`` times more per byte."""
    plan = _plan(32767, 400, 1, 3)
    cheap, dear = (Coefficients(mac=1e-11, byte=1e-11, fft=1e-10, call=5e-7, ram=r)
                   for r in (1.0, 8.0))
    assert estimates(plan, dear)["direct"].seconds > 4 * estimates(plan, cheap)["direct"].seconds


def test_a_cache_of_the_first_format_is_ignored(tmp_path, monkeypatch, caplog):
    path = tmp_path / "k.json"
    monkeypatch.setenv(COSTS_ENV, str(path))
    path.write_text(json.dumps({"format": 1, "coefficients": {
        "mac": 1e-9, "byte": 1e-9, "fft": 1e-9, "call": 1e-6}}))
    costs.set_coefficients(None)
    assert costs.coefficients() == DEFAULT_COEFFICIENTS
    assert "format 1" in caplog.text


def test_the_cache_is_written_read_and_a_bad_one_ignored(tmp_path, monkeypatch, caplog):
    path = tmp_path / "sub" / "kernel-costs.json"
    monkeypatch.setenv(COSTS_ENV, str(path))
    costs.set_coefficients(None)
    assert costs.cache_path() == path
    assert costs.coefficients() == DEFAULT_COEFFICIENTS  # no file yet
    mine = Coefficients(mac=1e-9, byte=2e-9, fft=3e-9, call=4e-6)
    assert costs.save(mine) == path
    assert json.loads(path.read_text())["coefficients"]["fft"] == 3e-9
    assert costs.coefficients() == mine
    path.write_text("{not json")
    costs.set_coefficients(None)
    assert costs.coefficients() == DEFAULT_COEFFICIENTS
    assert "ignoring kernel cost calibration" in caplog.text


def test_default_location_follows_xdg(monkeypatch, tmp_path):
    monkeypatch.delenv(COSTS_ENV, raising=False)
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path))
    assert costs.cache_path() == tmp_path / "cdma-lidar" / "kernel-costs.json"


def test_calibration_measures_every_primitive(tmp_path, monkeypatch, capsys):
    monkeypatch.setenv(COSTS_ENV, str(tmp_path / "k.json"))
    assert costs.main(["--calibrate", "--show"]) == 0
    out = capsys.readouterr().out
    assert "wrote" in out and "Coefficients(" in out
    co = costs.coefficients()
    assert co != DEFAULT_COEFFICIENTS and all(v > 0 for v in vars(co).values())
