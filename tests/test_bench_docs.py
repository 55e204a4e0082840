"""Benchmark figures in docs/*.md are generated blocks (``python -m bench NAME --write-doc DOC``).

No benchmark runs here: the blocks' headers, names and row labels are checked against
the bench modules' source, and the block functions of ``bench/docblock.py`` on their own.
``python -m bench NAME --check-doc DOC`` compares a block with a fresh run.
"""

from __future__ import annotations

import importlib.util
import re
from pathlib import Path

import pytest

import bench.__main__ as bench_main
from bench import docblock
from bench.__main__ import bench_names, main
from cdma_lidar.errors import ConfigError
from cdma_lidar.firmware_model.correlators import correlator_methods

ROOT = Path(__file__).resolve().parents[1]
DOCS = sorted((ROOT / "docs").glob("*.md"))
_MARKER_RE = re.compile(r"<!-- bench ([\w-]+):(begin|end) -->")


def _doc_blocks() -> list[tuple[str, str, str]]:
    """(doc path relative to the root, bench name, block content) of every docs/*.md block."""
    return [(str(doc.relative_to(ROOT)), name, body) for doc in DOCS
            for name, body in docblock.blocks(doc.read_text()).items()]


def _placeholder(name: str, doc: str) -> str:
    return f"not generated yet: run `python -m bench {name} --write-doc {doc}`\n"


def _labels(output: str) -> list[str]:
    """Row labels of a bench's printed table rows: the text before the first number column.

    Rows may be indented or not. Split where the label holds a number (``1 workers:``
    gives ``workers``; numbers are data) and at parentheses and colons (where a bench's
    f-string puts a field: ``loop (scaled from 2048 members):`` gives ``loop``,
    ``scaled from`` and ``members``).
    """
    labels = []
    for line in output.splitlines():
        m = re.match(r"\s*(\S.*?)\s{2,}[-+]?\d", line)
        if m:
            parts = re.split(r"\s{2,}|\d+(?:\.\d+)?|[():]", m.group(1))
            labels += [p.strip() for p in parts if re.search("[A-Za-z]", p)]
    return labels


def test_some_doc_has_a_bench_block():
    assert any(name == "scene" for _, name, _ in _doc_blocks())


@pytest.mark.parametrize("doc", DOCS, ids=lambda p: p.name)
def test_markers_pair_up(doc):
    text = doc.read_text()
    found = _MARKER_RE.findall(text)
    names = {name for name, _ in found}
    for name in names:
        assert found.count((name, "begin")) == 1 and found.count((name, "end")) == 1, name
    assert set(docblock.blocks(text)) == names  # each begin is followed by its end


@pytest.mark.parametrize(("doc", "name", "body"), _doc_blocks(),
                         ids=lambda v: v if isinstance(v, str) and len(v) < 40 else "")
def test_block_is_generated_by_an_existing_bench(doc, name, body):
    assert name in bench_names()
    if body == _placeholder(name, doc):
        pytest.skip(f"{doc}: bench {name} block not generated yet")
    head = body.splitlines()[0]
    m = docblock.HEADER_RE.fullmatch(head)
    assert m, f"{doc}: bench {name} block must start with the generated header, not {head!r}"
    assert (m["name"], m["doc"]) == (name, doc)
    assert body == docblock.make_block(head, docblock.fenced_output(body))


def _output_and_source(doc: str, name: str, body: str) -> tuple[str, str]:
    """The block's bench output and the bench's source text (skips an ungenerated block)."""
    output = docblock.fenced_output(body)
    if not output:
        pytest.skip(f"{doc}: bench {name} block not generated yet")
    return output, Path(importlib.util.find_spec(f"bench.bench_{name}").origin).read_text()


def _printed_by(text: str, source: str) -> bool:
    """Whether ``text`` (a row label or a word of a block) is something the bench prints:
    literally in its source, or every word of it a word of the source or a registered
    kernel's name (benches print the registry's names), where a configuration code such
    as ``Gall`` (``G`` and the field ``all``) is read as its capital and the rest."""
    if text in source:
        return True
    vocabulary = set(re.findall(r"[A-Za-z]+", source)) | set(correlator_methods())
    return all(w in vocabulary or (w[0].isupper() and w[1:] in vocabulary)
               for w in re.findall(r"[A-Za-z]+", text))


@pytest.mark.parametrize(("doc", "name", "body"), _doc_blocks(),
                         ids=lambda v: v if isinstance(v, str) and len(v) < 40 else "")
def test_block_rows_are_rows_the_bench_prints(doc, name, body):
    """Each table row's label is in the bench's source: a renamed row needs a rerun."""
    output, source = _output_and_source(doc, name, body)
    labels = _labels(output)
    assert labels
    missing = [label for label in labels if not _printed_by(label, source)]
    assert not missing, f"{doc}: rows the bench no longer prints; rerun its --write-doc"


@pytest.mark.parametrize(("doc", "name", "body"), _doc_blocks(),
                         ids=lambda v: v if isinstance(v, str) and len(v) < 40 else "")
def test_block_words_are_words_of_the_bench(doc, name, body):
    """Every word (4 letters or more) of the block's output is in the bench's source."""
    output, source = _output_and_source(doc, name, body)
    words = set(re.findall(r"[A-Za-z]{4,}", output))
    missing = sorted(w for w in words if not _printed_by(w, source))
    assert not missing, f"{doc}: words the bench no longer prints; rerun its --write-doc"


def test_printed_by_reads_kernel_names_and_configuration_codes():
    source = 'print(f"kernel {name}  G{gate}")  # gate "all"'
    assert _printed_by("kernel matmul", source) and _printed_by("Gall", source)
    assert not _printed_by("kernel renamed", source)
    assert not _printed_by("Gnone", source)


def test_labels_of_printed_rows():
    out = ("paper-scene1: heading 12\n  render, cold   12.5   3.1\n  a  b   7\n  x\n"
           "   16 workers:   8.1 s\n  degree 13 (N = 8191)   1.00\n")
    assert _labels(out) == ["render, cold", "a", "b", "workers", "degree", "N ="]
    rows = ("paper-scene1      unpaced  0.0001    0.28\n"
            "  baseline per-member gold_code loop (scaled from 2048 members):    27.2 ms\n")
    assert _labels(rows) == ["paper-scene", "unpaced", "baseline per-member gold_code loop",
                             "scaled from", "members"]


TEXT = "intro\n<!-- bench x:begin -->\nold 1.0\n<!-- bench x:end -->\nafter\n"


def test_replace_block_keeps_the_rest_and_round_trips():
    body = docblock.make_block("head", "row 2.5\n")
    new = docblock.replace_block(TEXT, "x", body)
    assert new.startswith("intro\n<!-- bench x:begin -->\nhead\n")
    assert new.endswith("```\n<!-- bench x:end -->\nafter\n")
    assert docblock.blocks(new) == {"x": body}
    assert docblock.replace_block(new, "x", body) == new
    assert docblock.replace_block(new, "x", "old 1.0\n") == TEXT


@pytest.mark.parametrize("text", [
    "no markers\n",
    "<!-- bench x:begin -->\nonly the begin\n",
    "only the end\n<!-- bench x:end -->\n",
    "<!-- bench x:end -->\nreversed\n<!-- bench x:begin -->\n",
    TEXT + TEXT,
    TEXT.replace("bench x", "bench y"),
])
def test_replace_block_refuses_missing_or_doubled_markers(text):
    with pytest.raises(ConfigError, match="bench x"):
        docblock.replace_block(text, "x", "new\n", "doc.md")


def test_header_is_what_the_test_expects():
    head = docblock.header("scene", "docs/scene.md", 0.0, "abc1234-dirty", 2, ("--full",))
    assert head == ("Generated by `python -m bench scene --write-doc docs/scene.md --full` "
                    "on 1970-01-01 00:00 UTC, commit abc1234-dirty, 2 CPUs.")
    m = docblock.HEADER_RE.fullmatch(head)
    assert m and (m["name"], m["doc"], m["options"]) == ("scene", "docs/scene.md", " --full")


def test_skeleton_replaces_numbers_only():
    a = "  scan / chain   2.62   1.61 (52.4 ms)\n"
    b = "  scan / chain   3.1   -0.5 (1e-3 ms)\n"
    assert docblock.skeleton(a) == docblock.skeleton(b) == ["scan / chain # # (# ms)"]
    assert docblock.skeleton("  scan / chain   2.62\n") != docblock.skeleton(a)


def test_check_names_rows_that_changed():
    text = docblock.replace_block(TEXT, "x", docblock.make_block("h", "a 1\nb 2\n"))
    assert docblock.check(text, "x", "a 5\nb 7\n") == []
    assert docblock.check(text, "x", "a 5\nc 7\n") == ["- b #", "+ c #"]


def test_capture_returns_stdout_and_passes_it_on(capsys):
    import io
    seen = io.StringIO()
    assert docblock.capture(lambda: print("row 1.5"), seen) == "row 1.5\n"
    assert seen.getvalue() == "row 1.5\n"
    assert capsys.readouterr().out == ""


def test_write_doc_without_markers_exits_2(tmp_path, capsys):
    doc = tmp_path / "doc.md"
    doc.write_text("no block here\n")
    assert main(["codes", "--write-doc", str(doc)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "<!-- bench codes:begin -->" in err
    assert doc.read_text() == "no block here\n"


def test_write_doc_needs_one_known_area(tmp_path, capsys):
    doc = tmp_path / "doc.md"
    doc.write_text(TEXT)
    assert main(["nosuch", "--write-doc", str(doc)]) == 2
    assert main(["codes", "scene", "--write-doc", str(doc)]) == 2
    assert doc.read_text() == TEXT


def test_write_doc_replaces_the_block_with_the_output(tmp_path, monkeypatch, capsys):
    """The write path on its own: the bench run is replaced by one printed row."""
    doc = tmp_path / "doc.md"
    doc.write_text(TEXT.replace("bench x", "bench codes"))
    monkeypatch.setattr(bench_main, "run", lambda areas: print(f"row {areas} 1.5"))
    assert main(["codes", "--write-doc", str(doc)]) == 0
    body = docblock.blocks(doc.read_text())["codes"]
    m = docblock.HEADER_RE.fullmatch(body.splitlines()[0])
    assert m and (m["name"], m["doc"]) == ("codes", str(doc))
    assert docblock.fenced_output(body) == "row ['codes'] 1.5\n"
    assert doc.read_text().startswith("intro\n") and doc.read_text().endswith("after\n")
    assert capsys.readouterr().out == "row ['codes'] 1.5\n"
    assert main(["codes", "--check-doc", str(doc)]) == 0
    monkeypatch.setattr(bench_main, "run", lambda areas: print("other row 1.5"))
    assert main(["codes", "--check-doc", str(doc)]) == 1


def test_a_kernels_row_label_parses_back_into_its_case():
    from bench.bench_kernels import Case, parse_case, quick_grid

    for case in [*quick_grid(), Case(9, 9, 2, 0, r=100, uid_bits=4, adc_bits=14, columns=160)]:
        assert parse_case(case.label()) == case
    assert parse_case("d9 S9 K2 Gall R100 n4 b14") is None
