"""The house rules: one namespace, and imports that follow the instrument's data path.

* Every product module imports only the layers below its own (docs/interfaces.md draws
  them). Imports are read with ``ast``, function-local ones included, so a lazy import
  cannot hide a dependency.
* A function-local import is allowed only for an optional (or heavy, deferred)
  third-party dependency, and says so in a comment on its line or the line above.
  ``importlib.import_module("name")`` counts as an import of ``name``.
* The exceptions, :data:`LAZY_REEXPORTS`: ``cdma_lidar/__init__.py`` loads the Python
  quick start (:mod:`cdma_lidar.api`, top layer) on first use of one of its names (PEP
  562), so ``import cdma_lidar`` stays light and ``cdma_lidar.open(URL)`` works; and
  ``cdma_lidar/scene/__init__.py`` loads ``load_scene``, ``PRESETS`` and ``Scene`` the same
  way, so the scene's light modules (its CLI) load without numpy. The
  CLI loads a command's module by the name in its ``COMMANDS`` table (top layer: it
  may import every layer).
* Nothing imports the repository's folder names as top-level packages (``protocol``,
  ``scene``, ...): from the repository root those would resolve to the folders and hide
  a missing ``cdma_lidar.`` prefix.
* ``pyproject.toml`` lists every package folder, and a wheel built from a clean copy
  of the tracked files puts only ``cdma_lidar`` at the top of site-packages.
"""

from __future__ import annotations

import ast
import shutil
import subprocess
import sys
import tomllib
import zipfile
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
PYPROJECT = tomllib.loads((ROOT / "pyproject.toml").read_text("utf-8"))
PACKAGE_DIR: dict[str, str] = PYPROJECT["tool"]["setuptools"]["package-dir"]

#: What each layer may import (itself included). Top to bottom the instrument's data
#: path: core -> optics -> firmware model and protocol (siblings) -> RTL reference and
#: scene -> virtual device -> host -> studies -> CLI.
ALLOWED: dict[str, set[str]] = {
    "core": {"core"},
    "optics": {"core", "optics"},
    "firmware_model": {"core", "firmware_model"},
    "protocol": {"core", "protocol"},
    "hdl_ref": {"core", "firmware_model", "hdl_ref"},
    "scene": {"core", "optics", "firmware_model", "scene"},
    "virtual": {"core", "optics", "firmware_model", "protocol", "hdl_ref", "scene", "virtual"},
    "host": {"core", "optics", "firmware_model", "protocol", "host"},
    "study": {"core", "optics", "firmware_model", "protocol", "hdl_ref", "scene", "virtual",
              "host", "study"},
    "cli": {"core", "optics", "firmware_model", "protocol", "hdl_ref", "scene", "virtual",
            "host", "study", "cli"},
}

#: Modules of the cdma_lidar/ folder that sit at the top, composing the others.
TOP_MODULES = {"cdma_lidar.cli", "cdma_lidar.demo", "cdma_lidar.api"}

#: (module, name it loads lazily): the only imports allowed against the table.
LAZY_REEXPORTS = {("cdma_lidar", "cdma_lidar.api"),
                  ("cdma_lidar.scene", "cdma_lidar.scene.loader"),
                  ("cdma_lidar.scene", "cdma_lidar.scene.model")}

#: The repository's folder names, which must never be imported as top-level packages.
FOLDER_NAMES = {Path(d).name for d in PACKAGE_DIR.values()} - {"cdma_lidar"}


def layer_of(module: str) -> str:
    """The layer of a dotted ``cdma_lidar`` module name."""
    if module in TOP_MODULES or any(module.startswith(m + ".") for m in TOP_MODULES):
        return "cli"
    parts = module.split(".")
    if len(parts) >= 2 and parts[1] in ALLOWED and parts[1] != "core":
        return parts[1]
    return "core"


def product_modules() -> list[tuple[str, Path]]:
    """(dotted name, file) of every module the distribution installs."""
    out = []
    for package, folder in PACKAGE_DIR.items():
        for path in sorted((ROOT / folder).rglob("*.py")):
            rel = path.relative_to(ROOT / folder).with_suffix("")
            parts = [p for p in rel.parts if p != "__init__"]
            out.append((".".join([package, *parts]), path))
    return out


def _imports(path: Path, module: str) -> list[tuple[str, int, bool]]:
    """(imported module, line, function-local) for every import in ``path``."""
    tree = ast.parse(path.read_text("utf-8"), filename=str(path))
    local_nodes: set[int] = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef | ast.Lambda):
            local_nodes.update(id(n) for n in ast.walk(node)
                               if isinstance(n, ast.Import | ast.ImportFrom))
    found = []
    is_package = path.name == "__init__.py"
    for node in ast.walk(tree):
        if (isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute)
                and node.func.attr == "import_module" and node.args
                and isinstance(node.args[0], ast.Constant)
                and isinstance(node.args[0].value, str)):
            local = any(isinstance(n, ast.FunctionDef | ast.AsyncFunctionDef | ast.Lambda)
                        and node in ast.walk(n) for n in ast.walk(tree))
            found.append((node.args[0].value, node.lineno, local))
            continue
        if isinstance(node, ast.Import):
            names = [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            if node.level:  # relative: resolve against this module's package
                base = module.split(".")
                base = base if is_package else base[:-1]
                base = base[: len(base) - (node.level - 1)]
                names = [".".join(base + ([node.module] if node.module else []))]
            else:
                names = [node.module or ""]
        else:
            continue
        found.extend((n, node.lineno, id(node) in local_nodes) for n in names)
    return found


MODULES = product_modules()


def test_every_package_folder_is_listed_in_pyproject() -> None:
    listed = set(PYPROJECT["tool"]["setuptools"]["packages"])
    on_disk = set()
    for package, folder in PACKAGE_DIR.items():
        for init in (ROOT / folder).rglob("__init__.py"):
            rel = init.parent.relative_to(ROOT / folder)
            on_disk.add(".".join([package, *rel.parts]))
    assert on_disk - listed == set(), "package folders missing from pyproject.toml"
    missing_dirs = {p for p in listed if not (ROOT / _folder_of(p)).is_dir()}
    assert missing_dirs == set(), "pyproject.toml lists packages with no folder"


def _folder_of(package: str) -> Path:
    best = max((p for p in PACKAGE_DIR if package == p or package.startswith(p + ".")), key=len)
    rest = package[len(best) + 1:].split(".") if package != best else []
    return Path(PACKAGE_DIR[best], *rest)


def test_the_layer_table_knows_every_product_package() -> None:
    for package in PACKAGE_DIR:
        assert layer_of(package + ".x") in ALLOWED, package
    assert {layer_of(m) for m, _ in MODULES} == set(ALLOWED)


@pytest.mark.parametrize(("module", "path"), MODULES, ids=[m for m, _ in MODULES])
def test_imports_follow_the_layers(module: str, path: Path) -> None:
    mine = layer_of(module)
    bad = []
    for name, line, _local in _imports(path, module):
        top = name.split(".")[0]
        if (module, name) in LAZY_REEXPORTS:
            continue
        if top in FOLDER_NAMES:
            bad.append(f"line {line}: imports {name!r}; write cdma_lidar.{name}")
        elif top == "cdma_lidar" and layer_of(name) not in ALLOWED[mine]:
            bad.append(f"line {line}: {mine} imports {name} ({layer_of(name)})")
    assert not bad, f"{path.relative_to(ROOT)}:\n" + "\n".join(bad)


@pytest.mark.parametrize(("module", "path"), MODULES, ids=[m for m, _ in MODULES])
def test_function_local_imports_are_optional_dependencies_that_say_so(
        module: str, path: Path) -> None:
    lines = path.read_text("utf-8").splitlines()
    bad = []
    for name, line, local in _imports(path, module):
        if not local:
            continue
        said = "#" in lines[line - 1] or lines[line - 2].strip().startswith("#")
        if (module, name) in LAZY_REEXPORTS:
            continue
        if name.split(".")[0] in {"cdma_lidar", *FOLDER_NAMES}:
            bad.append(f"line {line}: function-local import of our own {name}")
        elif not said:
            bad.append(f"line {line}: lazy import of {name} without a comment saying why")
    assert not bad, f"{path.relative_to(ROOT)}:\n" + "\n".join(bad)


def test_the_layering_test_catches_a_bad_import(tmp_path: Path) -> None:
    """The checks above can fail: a protocol module importing the scene is caught."""
    bad = tmp_path / "bad.py"
    bad.write_text("def f():\n    from cdma_lidar.scene import load_scene\n    import protocol\n"
                   "    importlib.import_module('cdma_lidar.host')\n")
    found = _imports(bad, "cdma_lidar.protocol.bad")
    assert ("cdma_lidar.scene", 2, True) in found and ("protocol", 3, True) in found
    assert ("cdma_lidar.host", 4, True) in found
    assert layer_of("cdma_lidar.scene") not in ALLOWED[layer_of("cdma_lidar.protocol.bad")]
    assert layer_of("cdma_lidar.demo") == "cli" and layer_of("cdma_lidar.errors") == "core"


def _tracked_copy(dest: Path) -> Path:
    """A copy of the files git tracks (what a fresh clone has), without build leftovers."""
    files = subprocess.run(["git", "ls-files", "-z"], cwd=ROOT, capture_output=True,
                           check=True).stdout.decode().split("\0")
    for name in filter(None, files):
        src = ROOT / name
        if src.is_file():
            (dest / name).parent.mkdir(parents=True, exist_ok=True)
            shutil.copy2(src, dest / name)
    return dest


@pytest.mark.skipif(shutil.which("git") is None, reason="needs git to list the tracked files")
def test_wheel_puts_only_cdma_lidar_at_the_top(tmp_path: Path) -> None:
    src = _tracked_copy(tmp_path / "src")
    out = tmp_path / "wheel"
    proc = subprocess.run([sys.executable, "-m", "pip", "wheel", "--no-deps", "-q",
                           "-w", str(out), str(src)], capture_output=True, text=True)
    assert proc.returncode == 0, proc.stderr[-2000:]
    (wheel,) = out.glob("cdma_lidar-*.whl")
    names = zipfile.ZipFile(wheel).namelist()
    tops = {n.split("/")[0] for n in names}
    dist_info = {t for t in tops if t.endswith(".dist-info")}
    assert tops - dist_info == {"cdma_lidar"}
    for data in ("cdma_lidar/scene/presets/paper-scene1.toml",
                 "cdma_lidar/hdl_ref/rtl/rx_chain.v",
                 "cdma_lidar/firmware_model/receiver.py",
                 "cdma_lidar/virtual/urlhandler/protocol_virtual.py"):
        assert data in names


def test_import_cdma_lidar_loads_only_itself_until_the_api_is_used() -> None:
    """The lazy re-export: the core loads nothing of ours but its version constant (nor
    numpy) at import time."""
    code = ("import sys, cdma_lidar\n"
            "before = sorted(m for m in sys.modules if m.startswith(('cdma_lidar', 'numpy')))\n"
            "import cdma_lidar.api\n"
            "assert cdma_lidar.open is cdma_lidar.api.open\n"
            "assert cdma_lidar.scan is cdma_lidar.api.scan\n"
            "assert set(cdma_lidar.API_NAMES) == set(cdma_lidar.api.__all__)\n"
            "print(before)\n")
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.strip() == "['cdma_lidar', 'cdma_lidar.version']"


#: Rooms small enough to read in one sitting (issue "One instrument"): lines per module, per
#: class.
MAX_MODULE_LINES, MAX_CLASS_LINES = 800, 400


def _too_big(source: str, name: str) -> list[str]:
    found = [f"{name}: {source.count(chr(10))} lines"] if source.count("\n") > MAX_MODULE_LINES \
        else []
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.ClassDef) and node.end_lineno - node.lineno >= MAX_CLASS_LINES:
            found.append(f"{name}.{node.name}: {node.end_lineno - node.lineno + 1} lines")
    return found


def test_no_module_or_class_is_too_big_to_read() -> None:
    big = [f for m, p in product_modules() for f in _too_big(p.read_text(encoding="utf-8"), m)]
    assert big == []


def test_the_size_check_sees_a_big_class() -> None:
    body = "\n".join(f"    x{i} = {i}" for i in range(MAX_CLASS_LINES))
    assert _too_big(f"class Big:\n{body}\n", "m") == [f"m.Big: {MAX_CLASS_LINES + 1} lines"]
