"""docs/interfaces.md against the code: its module map is generated, and its claims are checked.

``python tests/test_interfaces_doc.py --write`` rewrites the module map (the block between
``<!-- modules:begin -->`` and ``<!-- modules:end -->``: every module of every layer with the
first line of its docstring); the tests below fail when the block, a dotted name, a path,
the receiver output's field list or the error rule disagrees with the code.
"""

from __future__ import annotations

import ast
import builtins
import dataclasses
import importlib
import re
import sys
from pathlib import Path

from cdma_lidar.fileio import atomic_write_text

ROOT = Path(__file__).resolve().parents[1]
DOC = ROOT / "docs" / "interfaces.md"
#: The layers in import order (README): repository folder -> installed package.
LAYERS = ("cdma_lidar", "optics", "firmware_model", "protocol", "hdl_ref", "scene", "virtual",
          "host", "study")
BEGIN, END = "<!-- modules:begin -->", "<!-- modules:end -->"


def _modules() -> list[tuple[str, Path]]:
    """(installed module name, file) of every module of every layer, layer by layer."""
    out = []
    for folder in LAYERS:
        for path in sorted((ROOT / folder).rglob("*.py")):
            rel = path.relative_to(ROOT / folder).with_suffix("")
            if rel.parts[-1] == "__main__" or "tb" in rel.parts:
                continue
            parts = rel.parts[:-1] if rel.parts[-1] == "__init__" else rel.parts
            prefix = ("cdma_lidar",) if folder == "cdma_lidar" else ("cdma_lidar", folder)
            out.append((".".join(prefix + parts), path))
    return out


def module_map() -> str:
    """The generated block: one table row per module, the first line of its docstring."""
    rows = ["| module | what it is |", "|---|---|"]
    for name, path in _modules():
        doc = ast.get_docstring(ast.parse(path.read_text(encoding="utf-8"))) or ""
        first = doc.strip().splitlines()[0] if doc.strip() else "(no docstring)"
        rows.append(f"| `{name}` | {first.replace('|', '/')} |")
    return "\n".join(rows) + "\n"


def _span(text: str) -> tuple[int, int]:
    """Where the generated block's lines lie in ``text`` (after the begin marker's line)."""
    return text.index(BEGIN) + len(BEGIN) + 1, text.index(END)


def _block(text: str) -> str:
    start, end = _span(text)
    return text[start:end]


def test_the_module_map_is_the_codes() -> None:
    assert _block(DOC.read_text(encoding="utf-8")) == module_map(), (
        "docs/interfaces.md's module map is stale: python tests/test_interfaces_doc.py --write")


def test_every_module_has_a_docstring() -> None:
    assert "(no docstring)" not in module_map()


def _resolves(dotted: str) -> bool:
    """Whether ``dotted`` names a module, or an attribute chain on the longest module prefix."""
    parts = dotted.split(".")
    for cut in range(len(parts), 0, -1):
        try:
            obj = importlib.import_module(".".join(parts[:cut]))
        except ModuleNotFoundError:
            continue
        try:
            for attr in parts[cut:]:
                obj = getattr(obj, attr)
        except AttributeError:
            return False
        return True
    return False


def test_every_dotted_name_in_the_prose_exists() -> None:
    prose = DOC.read_text(encoding="utf-8").split(BEGIN)[0]
    names = set(re.findall(r"\bcdma_lidar(?:\.[A-Za-z_]\w*)+", prose))
    assert names, "the check reads no names"
    assert [n for n in sorted(names) if not _resolves(n)] == []


def test_every_repository_path_in_the_prose_exists() -> None:
    prose = DOC.read_text(encoding="utf-8").split(BEGIN)[0]
    paths = {p for p in re.findall(r"`((?:[a-z_]+/)+[\w.]*)`", prose)
             if (ROOT / p.split("/")[0]).is_dir() and not re.search(r"[A-Z<]", p)}
    assert paths, "the check reads no paths"
    assert [p for p in sorted(paths) if not (ROOT / p).exists()] == []


def test_the_receiver_outputs_fields_are_the_classes() -> None:
    from cdma_lidar.firmware_model.output import ReceiverOutput

    text = " ".join(DOC.read_text(encoding="utf-8").split())
    listed = re.search(r"ReceiverOutput \(firmware_model\.output\): (.*?) snr\.", text).group(1)
    named = set(re.findall(r"\b[a-z_]+\b", listed))
    fields = [f.name for f in dataclasses.fields(ReceiverOutput)]
    assert [n for n in fields if n not in named] == [], "fields the doc does not list"


#: Built-in exceptions the package may raise itself (the doc's "Errors" rule lists them):
#: what a Python protocol demands of the code (SystemExit from a main, AttributeError from a
#: module __getattr__, KeyError from a mapping, OSError from a port's read or write,
#: TypeError for an argument of the wrong type, NotImplementedError) and broken internal
#: invariants (RuntimeError, AssertionError).
ALLOWED_BUILTINS = {"SystemExit", "AttributeError", "KeyError", "OSError", "TypeError",
                    "NotImplementedError", "RuntimeError", "AssertionError"}


def _builtin_raises() -> list[tuple[str, int, str]]:
    found = []
    for _, path in _modules():
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
            if isinstance(node, ast.Raise) and node.exc is not None:
                exc = node.exc.func if isinstance(node.exc, ast.Call) else node.exc
                cls = getattr(builtins, exc.id, None) if isinstance(exc, ast.Name) else None
                if isinstance(cls, type) and issubclass(cls, BaseException):
                    found.append((str(path.relative_to(ROOT)), node.lineno, exc.id))
    return found


def test_the_package_raises_only_its_own_errors_and_the_listed_builtins() -> None:
    doc = " ".join(DOC.read_text(encoding="utf-8").split(BEGIN)[0].split())
    for name in ALLOWED_BUILTINS:
        assert f"`{name}`" in doc, f"the doc's error rule does not list {name}"
    found = _builtin_raises()
    assert found, "the check finds no raise of a built-in (it reads nothing)"
    assert [f for f in found if f[2] not in ALLOWED_BUILTINS] == []


if __name__ == "__main__":
    if sys.argv[1:] != ["--write"]:
        sys.exit("usage: python tests/test_interfaces_doc.py --write")
    text = DOC.read_text(encoding="utf-8")
    start, end = _span(text)
    atomic_write_text(DOC, text[:start] + module_map() + text[end:])
