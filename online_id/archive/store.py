"""The results table on disk: a directory of Parquet files that a run appends to and a re-run resumes.

Layout of ``RESULTS/``::

    archive.json        what made the table: mode (identify or diagnose) and the settings' fingerprint
    results.parquet     the table as of the last finished run (sorted, one row per recording and point)
    results.csv         the same as CSV (written with it)
    parts/*.parquet     rows appended since: a file every few seconds while a run goes on
    .lock               held while a run writes (a second run on the same table is refused)

Each part is written under a temporary name and renamed, so a run that is
killed leaves whole parts and loses at most the rows of the last few seconds;
all rows of one task (every operating point of a recording) go into the same
part.  Reading the table merges ``results.parquet`` and the parts and keeps
the first row of each key (content hash, segment, operating point): a run
killed between writing ``results.parquet`` and removing the merged parts
still reads each recording once.  At the end of a run the parts are merged
into ``results.parquet`` and ``results.csv``.

pyarrow is imported here only (the ``archive`` extra).
"""

from __future__ import annotations

import hashlib
import json
import os
import time
from collections.abc import Iterable
from pathlib import Path
from typing import Any

from online_id.archive.table import COLUMNS, NAMES, sort_rows
from online_id.errors import ConfigError, InputDataError
from online_id.io.outfile import atomic_output, check_output

TABLE = "results.parquet"
CSV = "results.csv"
META = "archive.json"
PARTS = "parts"


def require_pyarrow() -> None:
    """Raise a one-line :class:`ConfigError` naming the extra when pyarrow is missing."""
    try:
        import pyarrow  # noqa: F401
    except ImportError as err:
        raise ConfigError(f"the results table needs pyarrow, which is not installed ({err.msg}): "
                          "pip install 'online-id[archive]'") from None


def schema():
    """The table's pyarrow schema (from :data:`~online_id.archive.table.COLUMNS`)."""
    import pyarrow as pa

    types = {"string": pa.string(), "int64": pa.int64(), "float64": pa.float64(),
             "timestamp": pa.timestamp("us", tz="UTC")}
    return pa.schema([pa.field(c.name, types[c.type]) for c in COLUMNS])


def row_key(row: dict[str, Any]) -> tuple:
    """What makes a row unique: the content (or, unread or a duplicate, the file), the segment and the
    operating point."""
    ident = row.get("sha256")
    if not ident or row.get("status") == "duplicate":
        ident = f"{row.get('path')}|{row.get('size_bytes')}|{row.get('mtime_ns')}"
    return (ident, row.get("segment"), row.get("op_index"))


def fingerprint(doc: dict[str, Any]) -> str:
    """A short hash of a JSON-able description of the settings."""
    return hashlib.sha256(json.dumps(doc, sort_keys=True, default=repr).encode()).hexdigest()[:16]


def read_rows(path: str | Path) -> list[dict[str, Any]]:
    """Every row of a results directory (or of one ``.parquet`` or ``.csv`` table), merged and in order.

    Raises
    ------
    InputDataError
        No such table, or a file that is not one (one line, names the file).
    """
    require_pyarrow()
    path = Path(path)
    if path.is_dir():
        files = [path / TABLE] if (path / TABLE).is_file() else []
        # a hidden part is the temporary file of a write that was killed before it finished
        files += sorted(f for f in (path / PARTS).glob("*.parquet") if not f.name.startswith(".")) \
            if (path / PARTS).is_dir() else []
        if not files:
            raise InputDataError(f"{path}: no results table here (expected {TABLE} or {PARTS}/*.parquet, "
                                 "as `online-id archive identify --out` writes)")
    elif path.is_file():
        files = [path]
    else:
        raise InputDataError(f"{path}: no such results table")
    rows: list[dict[str, Any]] = []
    seen: set[tuple] = set()
    for f in files:
        for r in _read_file(f):
            k = row_key(r)
            if k not in seen:
                seen.add(k)
                rows.append(r)
    return sort_rows(rows)


def _read_file(f: Path) -> list[dict[str, Any]]:
    import pyarrow as pa
    import pyarrow.csv as pacsv
    import pyarrow.parquet as pq

    try:
        if f.suffix.lower() == ".csv":
            opts = pacsv.ConvertOptions(column_types=schema(), strings_can_be_null=True)
            table = pacsv.read_csv(f, convert_options=opts)
        else:
            table = pq.read_table(f)
    except (OSError, pa.ArrowException) as err:
        raise InputDataError(f"{f}: cannot read the results table: {' '.join(str(err).split())}") from None
    missing = [n for n in NAMES if n not in table.column_names]
    if missing:
        raise InputDataError(f"{f}: not an archive results table (no column {missing[0]!r})")
    return table.select(list(NAMES)).to_pylist()


def write_table(rows: list[dict[str, Any]], parquet: Path, csv: Path | None = None) -> None:
    """``rows`` as a Parquet file (and a CSV), each written atomically."""
    import pyarrow as pa
    import pyarrow.csv as pacsv
    import pyarrow.parquet as pq

    table = pa.Table.from_pylist(rows, schema=schema())
    with atomic_output(parquet) as tmp:
        pq.write_table(table, tmp)
    if csv is not None:
        with atomic_output(csv) as tmp:
            pacsv.write_csv(table, tmp)


class ResultStore:
    """A results directory opened for a run (see module notes); use as a context manager.

    Parameters
    ----------
    directory
        ``RESULTS``.
    about
        What made the table (mode, settings): a directory made with other
        settings is refused, so one table holds results of one method.
    flush_s, flush_rows
        Write a part when this long has passed since the last one, or this
        many rows wait.
    """

    def __init__(self, directory: str | Path, about: dict[str, Any], *, flush_s: float = 5.0,
                 flush_rows: int = 500) -> None:
        require_pyarrow()
        self.directory = Path(directory)
        self.about = about
        self.flush_s = flush_s
        self.flush_rows = flush_rows
        self._pending: list[dict[str, Any]] = []
        self._last_flush = time.monotonic()
        self._n_part = 0
        self._lock_fd: int | None = None
        self.rows_written = 0

    def __enter__(self) -> ResultStore:
        import fcntl

        check_output(self.directory, "results", directory=True)
        try:
            (self.directory / PARTS).mkdir(parents=True, exist_ok=True)
        except OSError as err:
            raise InputDataError(f"{self.directory}: cannot create the results directory ({err.strerror})") from None
        fd = os.open(self.directory / ".lock", os.O_RDWR | os.O_CREAT, 0o644)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            os.close(fd)
            raise InputDataError(f"{self.directory}: another online-id archive run is writing this table; "
                                 "wait for it or give another --out") from None
        self._lock_fd = fd
        for stale in (self.directory / PARTS).glob(".*.partial.parquet"):  # a killed run's unfinished part
            stale.unlink(missing_ok=True)
        meta = self.directory / META
        want = {"table": "online-id archive", **self.about}
        if meta.exists():
            try:
                have = json.loads(meta.read_text())
            except (OSError, ValueError) as err:
                self._unlock()
                raise InputDataError(f"{meta}: unreadable ({err})") from None
            diff = [k for k in want if have.get(k) != want[k]]
            if diff:
                self._unlock()
                raise ConfigError(f"{self.directory}: this table was made with {diff[0]} {have.get(diff[0])!r}, "
                                  f"not {want[diff[0]]!r}: give another --out (or the same settings) so that one "
                                  "table holds one method's results")
        else:
            with atomic_output(meta) as tmp:
                tmp.write_text(json.dumps(want, indent=1) + "\n")
        return self

    def __exit__(self, *exc: object) -> None:
        try:
            self.flush()
        finally:
            self._unlock()

    def _unlock(self) -> None:
        if self._lock_fd is not None:
            os.close(self._lock_fd)  # closing releases the flock
            self._lock_fd = None

    def rows(self) -> list[dict[str, Any]]:
        """What the table holds now (merged, in order; empty for a new table)."""
        d = self.directory
        if not (d / TABLE).is_file() and not any((d / PARTS).glob("*.parquet")):
            return []
        return read_rows(d)

    def add(self, rows: Iterable[dict[str, Any]]) -> None:
        """Queue the rows of one task; a part is written when due (see class notes)."""
        self._pending.extend(rows)
        if len(self._pending) >= self.flush_rows or time.monotonic() - self._last_flush >= self.flush_s:
            self.flush()

    def flush(self) -> None:
        """Write the queued rows as a new part (nothing when none wait)."""
        self._last_flush = time.monotonic()
        if not self._pending:
            return
        name = f"part-{time.strftime('%Y%m%dT%H%M%S', time.gmtime())}-{os.getpid()}-{self._n_part:05d}.parquet"
        self._n_part += 1
        write_table(self._pending, self.directory / PARTS / name)
        self.rows_written += len(self._pending)
        self._pending = []

    def compact(self) -> list[dict[str, Any]]:
        """Merge everything into ``results.parquet`` and ``results.csv``, remove the merged parts; the rows."""
        self.flush()
        parts = sorted((self.directory / PARTS).glob("*.parquet"))
        rows = self.rows()
        write_table(rows, self.directory / TABLE, self.directory / CSV)
        for p in parts:
            p.unlink(missing_ok=True)
        return rows
