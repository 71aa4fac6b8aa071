"""Read and write numeric CSV tables with errors that name file, line and column."""

from __future__ import annotations

import csv
import itertools
import math
import warnings
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


def read_csv_columns(path: str | Path, columns: Iterable[str], names: list[str] | None = None) -> dict[str, np.ndarray]:
    """Read the named numeric columns of a CSV file with a header line (or, with ``names``, without one).

    Lines starting with ``#`` and blank lines are skipped.  The result also
    holds, under :data:`LINE_KEY`, the file line number of every row.  The delimiter is
    taken from the header line (comma, semicolon, tab or spaces).  ``names``
    names the columns of a file that has no header line (its first data line
    gives the delimiter).

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
            if names is None:
                for header_no, line in enumerate(lines, start=1):
                    if line.strip() and not line.lstrip().startswith("#"):
                        header_line = line
                        break
                if header_line is None:
                    raise InputDataError(f"{path}: the file is empty (expected a header line with columns {', '.join(wanted)})")
                delim = _sniff_delimiter(header_line)
                header = _header_names(header_line)
            else:
                data_line = first_line(path)
                if data_line is None:
                    raise InputDataError(f"{path}: the file is empty")
                delim = _sniff_delimiter(data_line)
                header = list(names)
            missing = [name for name in wanted if name not in header]
            if missing:
                raise InputDataError(
                    f"{path}:{header_no}: missing column{'s' if len(missing) > 1 else ''} "
                    f"{', '.join(repr(m) for m in missing)}; the header has {', '.join(repr(h) for h in header)}"
                )
            index = {name: header.index(name) for name in wanted}
            capacity = _count_lines(path)  # an upper bound on the rows: arrays allocated once
            out = {name: np.empty(capacity) for name in wanted}
            line_numbers = np.empty(capacity, dtype=np.int32 if capacity < 2**31 else np.int64)
            rows = 0
            line_no = header_no
            while True:
                chunk = list(itertools.islice(handle, _CHUNK_LINES))
                if not chunk:
                    break
                block = _parse_fast(chunk, delim, index)
                if block is not None:
                    k = block.shape[0]
                    for c, name in enumerate(wanted):
                        out[name][rows:rows + k] = block[:, c]
                    line_numbers[rows:rows + k] = np.arange(line_no + 1, line_no + 1 + k)
                else:
                    values, numbers = _parse_rows(path, chunk, delim, index, line_no)
                    k = len(numbers)
                    for name in wanted:
                        out[name][rows:rows + k] = values[name]
                    line_numbers[rows:rows + k] = numbers
                rows += k
                line_no += len(chunk)
    except UnicodeDecodeError as err:
        raise InputDataError(f"{path}: not a text CSV file (it holds bytes that are not UTF-8: {err.reason})") from None
    except csv.Error as err:
        raise InputDataError(f"{path}:{line_no + 1}: not a text CSV file ({err})") from None
    result = {name: out[name][:rows] for name in wanted}
    result[LINE_KEY] = line_numbers[:rows]
    return result


_CHUNK_LINES = 65536


def first_line(path: str | Path) -> str | None:
    """The first line of a text file that is not blank or a ``#`` comment (None if there is none)."""
    path = Path(path)
    try:
        with path.open("r", newline="", encoding="utf-8-sig") as handle:
            for line in handle:
                if line.strip() and not line.lstrip().startswith("#"):
                    return line
    except OSError as err:
        raise InputDataError(f"{path}: cannot open: {err.strerror or err}") from err
    except UnicodeDecodeError as err:
        raise InputDataError(f"{path}: not a text CSV file (it holds bytes that are not UTF-8: {err.reason})") from None
    return None


def read_csv_header(path: str | Path) -> list[str]:
    """The column names of a CSV file's header line (the first line that is not blank or a ``#`` comment;
    quoted names as the csv module reads them), or [] for a file without one."""
    line = first_line(path)
    return [] if line is None else _header_names(line)


def _header_names(line: str) -> list[str]:
    """The column names of a header line (its delimiter sniffed; quoted names as the csv module reads them)."""
    delim = _sniff_delimiter(line)
    cells = line.split() if delim == " " else next(csv.reader([line], delimiter=delim))
    return [name.strip() for name in cells]


def _count_lines(path: Path) -> int:
    """Number of line breaks in the file, plus one."""
    count = 1
    with path.open("rb") as raw:
        while block := raw.read(1 << 22):
            count += block.count(b"\n")
    return count


def _parse_fast(chunk: list[str], delim: str, index: dict[str, int]) -> np.ndarray | None:
    """The wanted columns of ``chunk`` parsed by NumPy, or None when the chunk needs the careful parser.

    Only a chunk of plain rows (no blank or comment line) whose wanted cells
    all parse as finite numbers is taken; anything else (a bad cell, a short
    row, a quoted or unusual number) goes to :func:`_parse_rows`, which gives
    the same values or the error naming line and column.
    """
    for line in chunk:
        text = line.lstrip()
        if not text or text.startswith("#"):
            return None
    cols = list(index.values())
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            block = np.loadtxt(chunk, delimiter=None if delim == " " else delim, usecols=cols,
                               ndmin=2, dtype=float, comments=None, quotechar=None)
    except ValueError:
        return None
    if block.shape != (len(chunk), len(cols)) or not np.all(np.isfinite(block)):
        return None
    return block


def _parse_rows(path: Path, chunk: list[str], delim: str, index: dict[str, int],
                line_no: int) -> tuple[dict[str, list[float]], list[int]]:
    """Parse ``chunk`` (lines after ``line_no``) row by row; errors name file, line and column."""
    need = max(index.values()) + 1
    values: dict[str, list[float]] = {name: [] for name in index}
    line_numbers: list[int] = []
    reader = csv.reader(chunk, delimiter=delim) if delim != " " else (ln.split() for ln in chunk)
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
    return values, line_numbers


def write_csv_columns(path: str | Path, columns: Mapping[str, np.ndarray], formats: Mapping[str, str] | None = None) -> None:
    """Write equally long columns as a CSV file with a header line.

    Columns without a format get ``%.12g``: twelve significant digits keep a microsecond time stamp
    to 1e5 s (``%.6g`` wrote 5000.001 s as 5000).
    """
    path = Path(path)
    names = list(columns)
    data = np.column_stack([np.asarray(columns[n], dtype=float) for n in names])
    fmt = [(formats or {}).get(n, "%.12g") for n in names]
    with atomic_output(path) as tmp:  # no half-written file: a temporary name, renamed on success
        try:
            np.savetxt(tmp, data, delimiter=",", header=",".join(names), comments="", fmt=fmt)
        except OSError as err:
            raise InputDataError(f"{path}: cannot write: {err.strerror or err}") from err
