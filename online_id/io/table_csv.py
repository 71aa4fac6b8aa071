"""Read and write numeric CSV tables with errors that name file, line and column."""

from __future__ import annotations

import csv
import math
from pathlib import Path
from typing import Iterable, Mapping

import numpy as np

from online_id.errors import InputDataError
from online_id.io.outfile import atomic_output

LINE_KEY = "__line__"
"""Key of the extra column that :func:`read_csv_columns` returns: file line numbers."""


def _sniff_delimiter(header: str) -> str:
    for delim in (",", ";", "\t"):
        if delim in header:
            return delim
    return " "


def read_csv_columns(path: str | Path, columns: Iterable[str]) -> dict[str, np.ndarray]:
    """Read the named numeric columns of a CSV file with a header line.

    Lines starting with ``#`` and blank lines are skipped.  The result also
    holds, under :data:`LINE_KEY`, the file line number of every row.  The delimiter is
    taken from the header line (comma, semicolon, tab or spaces).

    Raises
    ------
    InputDataError
        The file cannot be read, a column is missing, a cell is not a finite
        number or a row is short; the message names file, line and column.
    """
    path = Path(path)
    wanted = list(columns)
    try:
        handle = path.open("r", newline="", encoding="utf-8-sig")
    except OSError as err:
        raise InputDataError(f"{path}: cannot open: {err.strerror or err}") from err
    line_no = 0
    try:
        with handle:
            lines = (line for line in handle)
            header_line = None
            header_no = 0
            for header_no, line in enumerate(lines, start=1):
                if line.strip() and not line.lstrip().startswith("#"):
                    header_line = line
                    break
            if header_line is None:
                raise InputDataError(f"{path}: the file is empty (expected a header line with columns {', '.join(wanted)})")
            delim = _sniff_delimiter(header_line)
            if delim == " ":
                header = header_line.split()
            else:
                header = next(csv.reader([header_line], delimiter=delim))
            header = [name.strip() for name in header]
            missing = [name for name in wanted if name not in header]
            if missing:
                raise InputDataError(
                    f"{path}:{header_no}: missing column{'s' if len(missing) > 1 else ''} "
                    f"{', '.join(repr(m) for m in missing)}; the header has {', '.join(repr(h) for h in header)}"
                )
            index = {name: header.index(name) for name in wanted}
            need = max(index.values()) + 1
            values: dict[str, list[float]] = {name: [] for name in wanted}
            line_numbers: list[int] = []
            reader = csv.reader(handle, delimiter=delim) if delim != " " else (ln.split() for ln in handle)
            line_no = header_no
            for row in reader:
                line_no += 1
                if not row or (len(row) == 1 and not row[0].strip()) or row[0].lstrip().startswith("#"):
                    continue
                if len(row) < need:
                    raise InputDataError(f"{path}:{line_no}: row has {len(row)} cells, expected at least {need}")
                for name, col in index.items():
                    cell = row[col].strip()
                    try:
                        value = float(cell)
                    except ValueError:
                        raise InputDataError(
                            f"{path}:{line_no}: column {name!r}: {cell!r} is not a number"
                        ) from None
                    if not math.isfinite(value):
                        raise InputDataError(f"{path}:{line_no}: column {name!r}: value {cell!r} is not finite")
                    values[name].append(value)
                line_numbers.append(line_no)
    except UnicodeDecodeError as err:
        raise InputDataError(f"{path}: not a text CSV file (it holds bytes that are not UTF-8: {err.reason})") from None
    except csv.Error as err:
        raise InputDataError(f"{path}:{line_no + 1}: not a text CSV file ({err})") from None
    out = {name: np.asarray(v, dtype=float) for name, v in values.items()}
    out[LINE_KEY] = np.asarray(line_numbers, dtype=np.int64)
    return out


def write_csv_columns(path: str | Path, columns: Mapping[str, np.ndarray], formats: Mapping[str, str] | None = None) -> None:
    """Write equally long columns as a CSV file with a header line."""
    path = Path(path)
    names = list(columns)
    data = np.column_stack([np.asarray(columns[n], dtype=float) for n in names])
    fmt = [(formats or {}).get(n, "%.6g") for n in names]
    with atomic_output(path) as tmp:  # no half-written file: a temporary name, renamed on success
        try:
            np.savetxt(tmp, data, delimiter=",", header=",".join(names), comments="", fmt=fmt)
        except OSError as err:
            raise InputDataError(f"{path}: cannot write: {err.strerror or err}") from err
