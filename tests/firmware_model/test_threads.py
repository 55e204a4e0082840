"""Receive-chain threads: the count follows the machine, a setting and an environment
variable override it, column threads times BLAS threads never exceed it, and the
integers do not depend on it."""

from __future__ import annotations

import threading
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from threadpoolctl import threadpool_info

from cdma_lidar.errors import ConfigError
from cdma_lidar.firmware_model.correlators import base
from cdma_lidar.firmware_model.receiver import FastReceiver, ReceiverConfig, reference


def _blas_threads() -> int:
    """Threads of the BLAS numpy's products run on (the chain's products: numpy's wheel
    ships it in numpy.libs; elsewhere every BLAS counts). scipy loads a BLAS of its own
    on the first import of scipy.linalg, after the chain's limiter was made: that one is
    not the chain's, and counting it failed these checks whenever an earlier test in the
    process had imported scipy.linalg."""
    libs = [i for i in threadpool_info() if i["user_api"] == "blas"]
    own = [i for i in libs if Path(i["filepath"]).parent.name.startswith("numpy")]
    return max(i["num_threads"] for i in own or libs)


def test_default_follows_the_machine_unless_the_variable_is_set(monkeypatch):
    monkeypatch.delenv(base.THREADS_ENV, raising=False)
    monkeypatch.delenv("OMP_NUM_THREADS", raising=False)
    assert base.default_threads() == base.machine_threads() >= 1
    monkeypatch.setenv("OMP_NUM_THREADS", "1")  # a Dask worker's share
    assert base.default_threads() == 1
    monkeypatch.setenv("OMP_NUM_THREADS", "3,1")  # OpenMP's nested form: the outer level
    assert base.default_threads() == 3
    monkeypatch.setenv("OMP_NUM_THREADS", "lots")  # not ours to refuse: the machine's
    assert base.default_threads() == base.machine_threads()
    monkeypatch.setenv(base.THREADS_ENV, "3")  # ours first
    assert base.default_threads() == 3
    for bad in ("0", "two", "-1", "1.5"):
        monkeypatch.setenv(base.THREADS_ENV, bad)
        with pytest.raises(ConfigError, match=base.THREADS_ENV):
            base.default_threads()


@pytest.mark.parametrize("bad", [0, -2, True, 1.5, "4"])
def test_a_bad_thread_setting_names_the_field(bad):
    codes = np.ones((1, 7), dtype=np.uint8)
    with pytest.raises(ConfigError, match="threads"):
        FastReceiver(ReceiverConfig(samples_per_chip=1, gate_len=3), codes, threads=bad)


@pytest.mark.parametrize(("threads", "columns"), [(4, 8), (4, 3), (3, 1), (1, 5), (2, 2)])
def test_column_threads_times_blas_threads_stay_within_the_setting(threads, columns):
    seen: list[tuple[int, int, str, int]] = []
    lock = threading.Lock()

    def task(c0: int, c1: int) -> None:
        inner: list[tuple[int, int]] = []
        base.parallel_columns(lambda a, b: inner.append((a, b)), 10, 1 << 20, threads)
        assert inner == [(0, 10)]  # nested: inline, one call
        assert base.column_threads(10, 1 << 20, threads) == 1  # what auto is told
        with lock:
            seen.append((c0, c1, threading.current_thread().name, _blas_threads()))

    base.parallel_columns(task, columns, 1 << 20, threads)
    parts = min(threads, columns)
    assert base.column_threads(columns, 1 << 20, threads) == parts
    assert base.column_threads(columns, (1 << 18) - 1, threads) == 1  # too small to split
    assert sorted((c0, c1) for c0, c1, _, _ in seen)[0][0] == 0
    assert sum(c1 - c0 for c0, c1, _, _ in seen) == columns and len(seen) == parts
    if parts > 1:  # in the pool's threads
        assert all(name.startswith("cdma-rx") for _, _, name, _ in seen)
    assert all(b * parts <= threads and b == max(1, threads // parts) for *_, b in seen)


def test_small_work_runs_in_the_calling_thread():
    names = []
    base.parallel_columns(lambda a, b: names.append(threading.current_thread().name), 8,
                          1000, 4)
    assert names == [threading.current_thread().name]


@settings(max_examples=10, deadline=None)
@given(st.integers(1, 5), st.integers(1, 9), st.integers(0, 2**32 - 1))
def test_the_integers_do_not_depend_on_the_thread_count(threads, columns, seed):
    rng = np.random.default_rng(seed)
    codes = rng.integers(0, 2, (3, 127))
    cfg = ReceiverConfig(samples_per_chip=4, averages=64, uid_bits=2, uid=1, gate_start=480,
                         gate_len=40, peaks=2, out_shift=2, rounding="half_up")
    frame = rng.integers(-2048, 2048, (columns, cfg.column_samples(127))).astype(np.int16)
    one = FastReceiver(cfg, codes, threads=1).frame(frame)
    many = FastReceiver(cfg, codes, threads=threads).frame(frame)  # 2^18 and more: split
    assert all(a.same_as(b) for a, b in zip(one, many, strict=True))
    assert many[-1].same_as(reference(cfg, codes, frame[-1]))


def test_the_environment_variable_sets_a_receivers_threads(monkeypatch):
    monkeypatch.setenv(base.THREADS_ENV, "2")
    seen = []
    real = base.parallel_columns

    def spy(task, columns, size, threads=None):
        seen.append(base.resolve_threads(threads))
        return real(task, columns, size, threads)

    monkeypatch.setattr("cdma_lidar.firmware_model.chain.parallel_columns", spy)
    rng = np.random.default_rng(3)
    codes = rng.integers(0, 2, (2, 31))
    cfg = ReceiverConfig(samples_per_chip=2, averages=2, gate_len=9)
    x = rng.integers(-2048, 2048, (2, cfg.column_samples(31)))
    FastReceiver(cfg, codes).frame(x)
    FastReceiver(cfg, codes, threads=5).frame(x)
    assert seen == [2, 5]


def test_small_work_runs_blas_on_one_thread():
    # a threaded BLAS call of a millisecond stalls whenever another process holds a core
    seen = []
    base.parallel_columns(lambda a, b: seen.append(_blas_threads()), 1, (1 << 18) - 1, 4)
    base.parallel_columns(lambda a, b: seen.append(_blas_threads()), 1, 1 << 18, 4)
    assert seen == [1, 4]
