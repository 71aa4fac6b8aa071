"""Which bench a recording is from and when it started: from a mapping file, the MDF header, or the path.

Where each answer comes from is kept beside it (``bench_source``,
``start_source``), in this order of precedence:

1. a **mapping file** (``--bench-map FILE``): a CSV with the columns
   ``pattern,bench`` and optionally ``start_time`` (ISO 8601); ``pattern`` is a
   shell glob matched against the recording's path (``*/tb07/*``,
   ``*_B03_*.mf4``), the first matching line wins;
2. the **MDF 4 header**: the common property ``bench`` (or ``test_bed``,
   ``testbed``, ``test_bench``) and the measurement's start time;
3. the **path**: the regular expression ``--bench-pattern`` (its group
   ``bench``; default: ``bench07``, ``bench_B3``, ``testbed-4`` anywhere in the
   path), and a date and time in the file name (``20250304T073000``,
   ``2025-03-04_07-30-00``, taken as UTC);
4. otherwise the bench is the name of the file's directory and the start
   time is unknown (such rows are kept, but a trend needs dates).
"""

from __future__ import annotations

import csv
import datetime as dt
import fnmatch
import re
from dataclasses import dataclass
from pathlib import Path

from online_id.errors import ConfigError, InputDataError

BENCH_KEYS = ("bench", "test_bed", "testbed", "test_bench")
DEFAULT_BENCH_PATTERN = r"(?i)(?:bench|test[_-]?bed)[_\- ]?(?P<bench>[A-Za-z0-9]+)"
_STAMP = re.compile(r"(?<!\d)(\d{4})-?(\d{2})-?(\d{2})[T_\- ]?(\d{2})[-:]?(\d{2})[-:]?(\d{2})(?!\d)")


def parse_time(text: str, where: str) -> dt.datetime:
    """An ISO 8601 date or date-time as an aware UTC datetime (no zone: UTC); one-line error naming ``where``."""
    try:
        t = dt.datetime.fromisoformat(text.strip().replace("Z", "+00:00"))
    except ValueError:
        raise InputDataError(f"{where}: expected an ISO 8601 date or time (2025-03-04T07:30:00), got {text!r}") from None
    return (t if t.tzinfo else t.replace(tzinfo=dt.timezone.utc)).astimezone(dt.timezone.utc)


@dataclass(frozen=True)
class BenchMap:
    """Lines of a mapping file: (glob pattern, bench, start time or None, line number)."""

    source: str
    entries: tuple[tuple[str, str, dt.datetime | None, int], ...]

    @classmethod
    def load(cls, path: str | Path) -> BenchMap:
        """Read a mapping CSV (see module notes); errors name the file and line."""
        path = Path(path)
        try:
            text = path.read_text(encoding="utf-8-sig")
        except OSError as err:
            raise InputDataError(f"{path}: cannot read the bench mapping ({err.strerror})") from None
        rows = list(csv.reader(text.splitlines()))
        if not rows:
            raise InputDataError(f"{path}: the bench mapping is empty; expected a header line pattern,bench[,start_time]")
        head = [h.strip().lower() for h in rows[0]]
        if "pattern" not in head or "bench" not in head:
            raise InputDataError(f"{path}, line 1: expected the columns pattern,bench[,start_time], got {rows[0]!r}")
        unknown = [h for h in head if h not in ("pattern", "bench", "start_time")]
        if unknown:
            raise InputDataError(f"{path}, line 1: unknown column {unknown[0]!r} (expected pattern, bench, start_time)")
        entries = []
        for n, row in enumerate(rows[1:], start=2):
            if not any(c.strip() for c in row):
                continue
            if len(row) != len(head):
                raise InputDataError(f"{path}, line {n}: expected {len(head)} fields, got {len(row)}")
            rec = {h: c.strip() for h, c in zip(head, row)}
            if not rec["pattern"] or not rec["bench"]:
                raise InputDataError(f"{path}, line {n}: empty pattern or bench")
            start = parse_time(rec["start_time"], f"{path}, line {n}, column start_time") if rec.get("start_time") else None
            entries.append((rec["pattern"], rec["bench"], start, n))
        return cls(str(path), tuple(entries))

    def match(self, path: str) -> tuple[str, dt.datetime | None] | None:
        """(bench, start time) of the first line whose pattern matches ``path`` (as given, or absolute)."""
        full = str(Path(path).resolve())
        for pattern, bench, start, _n in self.entries:
            if fnmatch.fnmatch(path, pattern) or fnmatch.fnmatch(full, pattern):
                return bench, start
        return None


@dataclass(frozen=True)
class MetaRules:
    """How to find the bench and start time of a recording (see module notes)."""

    mapping: BenchMap | None = None
    bench_pattern: str = DEFAULT_BENCH_PATTERN

    def __post_init__(self) -> None:
        try:
            rx = re.compile(self.bench_pattern)
        except re.error as err:
            raise ConfigError(f"--bench-pattern {self.bench_pattern!r}: not a regular expression ({err})") from None
        if "bench" not in rx.groupindex:
            raise ConfigError(f"--bench-pattern {self.bench_pattern!r}: needs a named group (?P<bench>...)")


@dataclass(frozen=True)
class RecordingMeta:
    """A recording's bench and start time, each with where it came from."""

    bench: str
    bench_source: str  # "mapping", "mdf header", "path", "directory"
    start_time: dt.datetime | None
    start_source: str  # "mapping", "mdf header", "file name", "unknown"


def resolve(path: str, rules: MetaRules, header_start: dt.datetime | None = None,
            header_props: dict[str, str] | None = None) -> RecordingMeta:
    """The bench and start time of the recording at ``path`` (see module notes for the precedence)."""
    mapped = rules.mapping.match(path) if rules.mapping is not None else None
    props = {k.lower(): v for k, v in (header_props or {}).items()}
    header_bench = next((props[k] for k in BENCH_KEYS if props.get(k)), None)
    m = re.search(rules.bench_pattern, path)
    if mapped is not None:
        bench, bench_source = mapped[0], "mapping"
    elif header_bench:
        bench, bench_source = header_bench, "mdf header"
    elif m is not None and m.group("bench"):
        bench, bench_source = m.group("bench"), "path"
    else:
        bench, bench_source = Path(path).resolve().parent.name or "?", "directory"
    if mapped is not None and mapped[1] is not None:
        start, start_source = mapped[1], "mapping"
    elif header_start is not None:
        start, start_source = header_start, "mdf header"
    else:
        start, start_source = _name_time(Path(path).name), "file name"
        if start is None:
            start_source = "unknown"
    return RecordingMeta(bench, bench_source, start, start_source)


def _name_time(name: str) -> dt.datetime | None:
    """The first date-time stamp in a file name (UTC), or None."""
    m = _STAMP.search(name)
    if m is None:
        return None
    try:
        return dt.datetime(*(int(x) for x in m.groups()), tzinfo=dt.timezone.utc)
    except ValueError:  # 2025-13-45: not a date
        return None
