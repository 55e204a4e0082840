"""Tidy tables of study results: named columns, one row per point or task; CSV and Markdown.

No pandas: a study's tables are small (one row per point), and a list of dicts reads
and writes CSV with the standard library.
"""

from __future__ import annotations

import csv
import io
import math
import os
from collections.abc import Iterable, Mapping, Sequence
from typing import Any

import numpy as np

from cdma_lidar.errors import ConfigError

__all__ = ["Scalar", "Table", "plain", "read_csv"]

Scalar = int | float | str | bool | None


class Table:
    """A tidy table: named columns of equal length (lists of JSON scalars), in order."""

    def __init__(self, columns: Sequence[str] = (), rows: Iterable[Mapping[str, Any]] = ()):
        self.columns: list[str] = list(columns)
        self.rows: list[dict[str, Any]] = []
        for row in rows:
            self.append(row)

    def append(self, row: Mapping[str, Any]) -> None:
        for k in row:
            if k not in self.columns:
                self.columns.append(k)
        self.rows.append(dict(row))

    def __len__(self) -> int:
        return len(self.rows)

    def column(self, name: str) -> np.ndarray:
        """One column as a numpy array (float64 where numeric; missing cells are NaN)."""
        vals = [r.get(name) for r in self.rows]
        if all(v is None or (isinstance(v, int | float | np.number) and not isinstance(v, bool))
               for v in vals):
            return np.array([np.nan if v is None else v for v in vals], dtype=np.float64)
        return np.array(vals, dtype=object)

    def add_column(self, name: str, values: Iterable[Any]) -> None:
        values = list(values)
        if len(values) != len(self.rows):
            raise ConfigError(f"column {name!r}: {len(values)} values for {len(self.rows)} rows",
                              name)
        if name not in self.columns:
            self.columns.append(name)
        for row, v in zip(self.rows, values, strict=True):
            row[name] = plain(v)

    def where(self, **equal: Any) -> Table:
        """The rows whose columns equal the given values."""
        return Table(self.columns, [r for r in self.rows
                                    if all(r.get(k) == v for k, v in equal.items())])

    def to_csv(self) -> str:
        buf = io.StringIO()
        w = csv.writer(buf, lineterminator="\n")
        w.writerow(self.columns)
        for r in self.rows:
            w.writerow([_csv_cell(r.get(c)) for c in self.columns])
        return buf.getvalue()

    def to_markdown(self, columns: Sequence[str] | None = None, digits: int = 4) -> str:
        """A Markdown table (numbers to ``digits`` significant digits)."""
        cols = list(columns) if columns is not None else self.columns
        lines = ["| " + " | ".join(cols) + " |", "|" + "---|" * len(cols)]
        for r in self.rows:
            lines.append("| " + " | ".join(_fmt(r.get(c), digits) for c in cols) + " |")
        return "\n".join(lines) + "\n"

    def to_text(self, digits: int = 4) -> str:
        """Aligned plain text: a header row, then one line per row (numbers to ``digits``
        significant digits, right-aligned; text left-aligned)."""
        cells = [[_fmt(r.get(c), digits) for c in self.columns] for r in self.rows]
        numeric = [all(isinstance(r.get(c), int | float) or r.get(c) is None
                       for r in self.rows) for c in self.columns]
        widths = [max([len(c), *(len(row[i]) for row in cells)])
                  for i, c in enumerate(self.columns)]

        def line(values: Sequence[str]) -> str:
            return "  ".join(v.rjust(w) if num else v.ljust(w)
                             for v, w, num in zip(values, widths, numeric, strict=True)).rstrip()

        return "\n".join([line(self.columns), *(line(row) for row in cells)])

    def __str__(self) -> str:
        return self.to_text()

    def __repr__(self) -> str:
        return f"Table: {len(self)} rows x {len(self.columns)} columns\n{self.to_text()}"


def plain(v: Any) -> Scalar:
    """numpy scalars -> Python scalars (JSON-able); anything else unchanged."""
    if isinstance(v, np.bool_):
        return bool(v)
    if isinstance(v, np.integer):
        return int(v)
    if isinstance(v, np.floating):
        return float(v)
    return v


def _csv_cell(v: Any) -> str:
    if v is None:
        return ""
    if isinstance(v, float):
        return repr(v) if math.isfinite(v) else ("nan" if math.isnan(v) else str(v))
    return str(v)


def _fmt(v: Any, digits: int) -> str:
    if v is None:
        return ""
    if isinstance(v, float):
        return "nan" if math.isnan(v) else f"{v:.{digits}g}"
    return str(v)


def read_csv(path: str | os.PathLike[str]) -> Table:
    """Read a table written by :meth:`Table.to_csv` (numbers parsed back; '' is None)."""
    with open(path, newline="") as fh:
        reader = csv.reader(fh)
        header = next(reader)
        table = Table(header)
        for row in reader:
            table.rows.append({c: _parse_cell(v) for c, v in zip(header, row, strict=True)})
    return table


def _parse_cell(text: str) -> Scalar:
    if text == "":
        return None
    if text in ("True", "False"):
        return text == "True"
    try:
        return int(text)
    except ValueError:
        pass
    try:
        return float(text)
    except ValueError:
        return text
