"""The protocol's modules import each other without a circle (issue 39.5).

Read from the source with ``ast``, imports under ``TYPE_CHECKING`` included: a circle
hidden from the interpreter is still a circle to a reader.
"""

from __future__ import annotations

import ast
from pathlib import Path

import cdma_lidar.protocol as protocol

PACKAGE = "cdma_lidar.protocol"


def _imports() -> dict[str, set[str]]:
    """Module -> the sibling modules it imports."""
    root = Path(protocol.__file__).parent
    mods = {p.stem for p in root.glob("*.py")} - {"__init__"}
    graph: dict[str, set[str]] = {}
    for mod in mods:
        deps: set[str] = set()
        for node in ast.walk(ast.parse((root / f"{mod}.py").read_text())):
            if isinstance(node, ast.ImportFrom) and node.module:
                if node.module == PACKAGE:
                    deps |= {a.name for a in node.names}
                elif node.module.startswith(PACKAGE + "."):
                    deps.add(node.module.split(".")[2])
            elif isinstance(node, ast.Import):
                deps |= {a.name.split(".")[2] for a in node.names
                         if a.name.startswith(PACKAGE + ".")}
        graph[mod] = (deps & mods) - {mod}
    return graph


def _circle(graph: dict[str, set[str]]) -> list[str] | None:
    """One import circle, or None."""
    done: set[str] = set()

    def visit(mod: str, path: list[str]) -> list[str] | None:
        if mod in path:
            return [*path[path.index(mod):], mod]
        if mod in done:
            return None
        for dep in sorted(graph[mod]):
            if (found := visit(dep, [*path, mod])) is not None:
                return found
        done.add(mod)
        return None

    for mod in sorted(graph):
        if (found := visit(mod, [])) is not None:
            return found
    return None


def test_no_module_of_the_protocol_imports_itself_round_a_circle() -> None:
    graph = _imports()
    assert {"endpoint", "streams", "device_sessions", "transmit"} <= set(graph)
    assert _circle(graph) is None, " -> ".join(_circle(graph) or [])


def test_the_circle_finder_finds_one() -> None:
    assert _circle({"a": {"b"}, "b": {"c"}, "c": {"a"}}) == ["a", "b", "c", "a"]
    assert _circle({"a": {"b"}, "b": set()}) is None
