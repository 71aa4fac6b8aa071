"""CSV tables whose columns are named on the command line or in a header line.

:func:`read_table` reads the wanted columns of a CSV with a header or of a
headerless CSV whose columns are named by the caller (``--no-header --columns
a,b,c``), both through :func:`online_id.io.table_csv.read_csv_columns` (errors
name file, line and column).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from online_id.errors import InputDataError
from online_id.io.table_csv import _sniff_delimiter, first_line, read_csv_columns, read_csv_header


def _first_line(path: Path) -> str:
    line = first_line(path)
    if line is None:
        raise InputDataError(f"{path}: the file is empty")
    return line


def column_names(path: str | Path, names: list[str] | None = None) -> list[str]:
    """The column names: ``names`` for a headerless file, else the header line's
    (:func:`~online_id.io.table_csv.read_csv_header`)."""
    path = Path(path)
    if names is not None:
        return list(names)
    header = read_csv_header(path)
    if not header:
        raise InputDataError(f"{path}: the file is empty")
    return header


def read_table(path: str | Path, wanted: list[str], names: list[str] | None = None) -> dict[str, np.ndarray]:
    """Columns ``wanted`` of ``path``; ``names`` given means the file has no header line.

    The result also holds, under :data:`~online_id.io.table_csv.LINE_KEY`, the
    file line of every row (for errors that name the line).
    """
    path = Path(path)
    if names is None:
        return read_csv_columns(path, wanted)
    missing = [w for w in wanted if w not in names]
    if missing:
        raise InputDataError(f"{path}: --columns names no column {missing[0]!r} (named: {', '.join(names)})")
    line = _first_line(path)
    delim = _sniff_delimiter(line)
    cells = len(line.split()) if delim == " " else len(line.split(delim))
    if cells != len(names):
        raise InputDataError(f"{path}: {cells} columns but --columns names {len(names)} ({', '.join(names)})")
    return read_csv_columns(path, wanted, names)
