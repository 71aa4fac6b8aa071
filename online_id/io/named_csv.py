"""CSV tables whose columns are named on the command line or in a header line.

:func:`read_table` reads the wanted columns of a CSV with a header (through
:func:`online_id.io.table_csv.read_csv_columns`) or of a headerless CSV whose
columns are named by the caller (``--no-header --columns a,b,c``).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from online_id.errors import InputDataError
from online_id.io.table_csv import LINE_KEY, _sniff_delimiter, first_line, read_csv_columns, read_csv_header


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
    """Columns ``wanted`` of ``path``; ``names`` given means the file has no header line."""
    path = Path(path)
    if names is None:
        table = read_csv_columns(path, wanted)
        table.pop(LINE_KEY, None)
        return table
    missing = [w for w in wanted if w not in names]
    if missing:
        raise InputDataError(f"{path}: --columns names no column {missing[0]!r} (named: {', '.join(names)})")
    delim = _sniff_delimiter(_first_line(path))
    try:
        data = np.loadtxt(path, delimiter=None if delim == " " else delim, comments="#", ndmin=2)
    except ValueError as err:
        raise InputDataError(f"{path}: {err}") from None
    if data.shape[1] != len(names):
        raise InputDataError(f"{path}: {data.shape[1]} columns but --columns names {len(names)} "
                             f"({', '.join(names)})")
    return {w: data[:, names.index(w)].astype(float) for w in wanted}
