"""Fixtures for the RTL co-simulation: one Icarus build per parameter set, per session.

The builds live in a pytest temporary folder (one sub-folder per parameter
set, named by ``RxParams.tag()``), so every session compiles from the sources
in the checkout. Tests that use a build are skipped, with the reason, only when
Icarus Verilog is not installed (``make test`` and CI install it).
"""

from __future__ import annotations

from pathlib import Path

import pytest

from cdma_lidar.hdl_ref import cosim

SKIP_REASON = ("Icarus Verilog (iverilog, vvp) is not installed: apt-get install iverilog "
               "(make test installs it)")


@pytest.fixture(scope="session")
def hdl_build_root(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """Session folder holding one build folder per parameter set; skips without Icarus."""
    if not cosim.iverilog_available():
        pytest.skip(SKIP_REASON)
    return tmp_path_factory.mktemp("hdl_builds")


@pytest.fixture(scope="session")
def rx_builder(hdl_build_root: Path):
    """Function ``params -> build folder`` that compiles each RxParams once per session."""
    built: dict[cosim.RxParams, Path] = {}

    def get(params: cosim.RxParams) -> Path:
        if params not in built:
            built[params] = cosim.build(cosim.RX_TOP, params.generics(),
                                        hdl_build_root / params.tag())
        return built[params]

    return get


@pytest.fixture(scope="session")
def gold_builder(hdl_build_root: Path):
    """Function ``params -> build folder`` for ``gold_gen``, compiled once per parameter set."""
    built: dict[cosim.GoldParams, Path] = {}

    def get(params: cosim.GoldParams) -> Path:
        if params not in built:
            built[params] = cosim.build(cosim.GOLD_TOP, params.generics(),
                                        hdl_build_root / params.tag())
        return built[params]

    return get


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    """Tests marked slow here (the paper-sized co-simulation, most mutants) run only on request.

    ``pytest -m slow tests/hdl_ref`` (or any -m expression naming slow) runs them;
    a plain ``pytest`` skips them with this reason.
    """
    if "slow" in (config.option.markexpr or ""):
        return
    skip = pytest.mark.skip(reason="slow co-simulation: run with pytest -m slow tests/hdl_ref")
    for item in items:
        if "slow" in item.keywords and "hdl_ref" in str(item.path):
            item.add_marker(skip)
