"""The table of a Cinema database (Spec D ``data.csv``): columns, their types, the image columns.

Rules of the specification: UTF-8 CSV with a header of unique names; a column's type is that of
its first non-empty value (integer, float, else string); an empty value is missing; ``NaN`` is
allowed in float columns; whitespace is kept; columns named ``FILE`` or starting with ``FILE``
hold file paths relative to the database folder (they usually come last; some ParaView versions
write ``FILE_png`` first).
"""

import csv
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import numpy as np

from visnerf.data.errors import DatasetError

ColumnType = Literal["integer", "float", "string"]


@dataclass(frozen=True)
class CinemaTable:
    """``data.csv`` read and typed; rows are numbered from 1 as a spreadsheet shows them under the header."""

    path: Path
    columns: tuple[str, ...]
    types: tuple[ColumnType, ...]
    rows: tuple[tuple[str, ...], ...]

    @property
    def n_rows(self) -> int:
        return len(self.rows)

    def index(self, name: str) -> int:
        return self.columns.index(name)

    def find(self, *names: str) -> str | None:
        """The first column whose name matches one of ``names``, ignoring case (producers differ)."""
        lowered = {c.lower(): c for c in self.columns}
        for name in names:
            if name.lower() in lowered:
                return lowered[name.lower()]
        return None

    def file_columns(self) -> tuple[str, ...]:
        return tuple(c for c in self.columns if c.upper().startswith("FILE"))

    def strings(self, name: str) -> list[str]:
        j = self.index(name)
        return [row[j] for row in self.rows]

    def numbers(self, name: str, allow_nan: bool = False) -> np.ndarray:
        """The column as float64 [n]; a missing or non-numeric value is refused with its row and column."""
        j = self.index(name)
        out = np.empty(self.n_rows, dtype=np.float64)
        for i, row in enumerate(self.rows):
            text = row[j]
            if text == "":
                raise DatasetError(f"{self.path}: row {i + 1}, column {name!r}: the value is missing")
            value = _number(text)
            if value is None:
                raise DatasetError(f"{self.path}: row {i + 1}, column {name!r}: {text!r} is not a number "
                                   f"(the column's first value makes it {self.types[j]})")
            if not math.isfinite(value) and not allow_nan:
                raise DatasetError(f"{self.path}: row {i + 1}, column {name!r}: the value must be finite, got {text!r}")
            out[i] = value
        return out


def _number(text: str) -> float | None:
    """``text`` as a number (Python's float syntax, which takes ``NaN`` and ``inf``), else None."""
    try:
        return float(text)
    except ValueError:
        return None


def _column_type(values: list[str]) -> ColumnType:
    """The type of a column's first non-empty value."""
    first = next((v for v in values if v != ""), "")
    if first == "":
        return "string"
    try:
        int(first)
        return "integer"
    except ValueError:
        return "float" if _number(first) is not None else "string"


def read_table(path: Path) -> CinemaTable:
    """Read ``data.csv``; DatasetError naming the line for a bad header or a row of the wrong width."""
    try:
        text = path.read_text(encoding="utf-8-sig")
    except FileNotFoundError:
        raise DatasetError(f"Cinema database table {path} does not exist") from None
    except UnicodeDecodeError as exc:
        raise DatasetError(f"{path} is not UTF-8 text: {exc}") from None
    lines = list(csv.reader(text.splitlines()))
    lines = [line for line in lines if line]  # blank lines carry nothing
    if not lines:
        raise DatasetError(f"{path} is empty: a Cinema table needs a header and at least one row")
    header = tuple(lines[0])
    if any(name == "" for name in header):
        raise DatasetError(f"{path}: the header has an empty column name ({list(header)})")
    repeated = sorted({n for n in header if header.count(n) > 1})
    if repeated:
        raise DatasetError(f"{path}: the header repeats the column name(s) {repeated}")
    rows = []
    for i, line in enumerate(lines[1:], start=1):
        if len(line) != len(header):
            raise DatasetError(f"{path}: row {i} has {len(line)} values for the header's {len(header)} columns")
        rows.append(tuple(line))
    if not rows:
        raise DatasetError(f"{path} has a header but no rows")
    types = tuple(_column_type([row[j] for row in rows]) for j in range(len(header)))
    return CinemaTable(path, header, types, tuple(rows))
