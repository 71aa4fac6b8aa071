"""An archive run: which recordings are new, their tasks on the cluster, their rows into the table.

1. The table says what it holds: a recording whose path, size and
   modification time match rows of every one of its segments is skipped
   without being read.
2. Every other recording is probed on the cluster (content hash, header,
   length).  One whose content the table already holds under another path
   gets one ``duplicate`` row naming the first; a recording that cannot be
   read gets one ``error`` row.
3. Each segment the table does not hold yet is one task; its rows are
   appended to the table as it completes.  A task lost with its worker
   (``KilledWorker``) leaves no row, so the next run does it; one that
   raised is an ``error`` row with the one-line message.

At the end the parts are merged into ``results.parquet`` and
``results.csv``.  A run that is killed keeps every part it wrote; the next
run completes the table, each recording once.
"""

from __future__ import annotations

import glob
import os
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from online_id.archive import recording as rec
from online_id.archive.metadata import MetaRules
from online_id.archive.runner import Outcome, map_tasks
from online_id.archive.store import ResultStore, fingerprint
from online_id.archive.table import DUPLICATE, ERROR, blank_row
from online_id.config import Settings
from online_id.errors import InputDataError

RECORDING_SUFFIXES = (".mf4", ".csv", ".log", ".asc", ".blf")


def expand(paths_or_globs: Sequence[str]) -> list[str]:
    """Files named or matched (a directory: its recordings, recursively), sorted, each once, as absolute paths.

    Raises
    ------
    InputDataError
        A name that is neither a file, a directory nor a pattern matching one (one line).
    """
    out: list[str] = []
    for item in paths_or_globs:
        p = Path(item)
        if p.is_dir():
            found = [str(f) for f in sorted(p.rglob("*")) if f.is_file() and f.suffix.lower() in RECORDING_SUFFIXES]
        elif p.is_file():
            found = [item]
        else:
            found = sorted(f for f in glob.glob(item, recursive=True) if os.path.isfile(f))
            if not found:
                raise InputDataError(f"{item}: no such file, and no file matches it as a pattern")
        out += found
    seen: set[str] = set()
    out = [os.path.abspath(f) for f in out]  # workers elsewhere have another working directory
    return [f for f in out if not (f in seen or seen.add(f))]


@dataclass
class RunSummary:
    """What a run did."""

    recordings: int = 0
    skipped: int = 0  # held by the table
    duplicates: int = 0
    tasks: int = 0
    ok: int = 0  # tasks whose rows have a driveline (status ok)
    failed: int = 0  # error rows written
    lost: int = 0  # tasks without a result (the next run does them)
    rows: int = 0  # rows in the table at the end
    outcomes: list[Outcome] = field(default_factory=list)
    messages: list[str] = field(default_factory=list)


def about(mode: str, s: Settings, segment_s: float | None) -> dict[str, Any]:
    """What a table records about the run that made it (a table with other settings is refused)."""
    keys = ("columns", "units", "inertias", "identification", "model")
    return {"mode": mode, "segment_s": segment_s,
            "settings": fingerprint({k: getattr(s, k) for k in keys})}


def _held(rows: list[dict[str, Any]]) -> tuple[dict[tuple, int], dict[str, tuple[str, set[int], int]]]:
    """(path, size, mtime) -> segments; sha256 -> (first path, segments held, segments) of the table's rows."""
    by_stat: dict[tuple, set[int]] = {}
    by_hash: dict[str, tuple[str, set[int], int]] = {}
    total: dict[tuple, int] = {}
    for r in rows:
        k = (r["path"], r["size_bytes"], r["mtime_ns"])
        by_stat.setdefault(k, set()).add(r["segment"] or 0)
        total[k] = r["segments"] or 1
        if r["sha256"] and r["status"] != DUPLICATE:
            first, segs, n = by_hash.get(r["sha256"], (r["path"], set(), r["segments"] or 1))
            segs.add(r["segment"] or 0)
            by_hash[r["sha256"]] = (first, segs, n)
    complete = {k: total[k] for k, segs in by_stat.items() if len(segs) >= total[k]}
    return complete, by_hash


def run(paths: Sequence[str], out: str | Path, mode: str, settings: Settings, client: Any, *,
        rules: MetaRules | None = None, segment_s: float | None = None, quiet: bool = False,
        say: Callable[[str], None] | None = None, flush_s: float = 5.0,
        on_task: Callable[[Outcome], None] | None = None) -> RunSummary:
    """Identify (``mode`` "identify") or also diagnose ("diagnose") the recordings ``paths`` into the
    table ``out`` on ``client``'s cluster (see module notes).

    ``flush_s``: how often the rows that came in are written to the table (0: at once).  ``on_task`` is
    called after each task's rows are queued for the table.
    """
    if mode not in rec.MODES:
        raise ValueError(f"mode: expected one of {rec.MODES}, got {mode!r}")
    say = say or (lambda text: None)
    rules = rules or MetaRules()
    if mode == rec.DIAGNOSE:
        segment_s = None  # a diagnosis reads the whole recording
    files = expand(paths)
    summary = RunSummary(recordings=len(files))
    with ResultStore(out, about(mode, settings, segment_s), flush_s=flush_s) as store:
        complete, by_hash = _held(store.rows())
        todo = []
        for f in files:
            try:
                st = os.stat(f)
            except OSError:
                todo.append(f)
                continue
            if (f, st.st_size, st.st_mtime_ns) in complete:
                summary.skipped += 1
            else:
                todo.append(f)
        if summary.skipped:
            say(f"{summary.skipped} of {len(files)} recordings are in the table already")
        probes = map_tasks(client, rec.probe, [rec.ProbeJob(f, rules, settings, segment_s) for f in todo],
                           label="archive: reading", quiet=quiet)
        jobs: list[rec.Job] = []
        this_run: dict[str, str] = {}  # content hash -> the first path of this run with it
        for o in probes:
            f = todo[o.index]
            if not o.ok:
                if o.lost:
                    summary.lost += 1
                    summary.messages.append(f"{f}: not read ({o.error}); the next run tries again")
                    continue
                p = rec.Probe(f, None, None, None, None)
                store.add([rec.error_row(p, mode, o.error or "failed")])
                summary.failed += 1
                continue
            p: rec.Probe = o.value
            if p.error is not None:
                store.add([rec.error_row(p, mode, p.error)])
                summary.failed += 1
                summary.messages.append(p.error)
                continue
            windows = rec.segments(p.span_s, segment_s)
            first, held_segs, _n = by_hash.get(p.sha256, (this_run.get(p.sha256), set(range(len(windows))), 0))
            this_run.setdefault(p.sha256, f)
            if first is not None and first != f and len(held_segs) >= len(windows):
                store.add([blank_row(**p.base(mode), segment=0, segments=1, status=DUPLICATE,
                                     error=f"same content as {first}")])
                summary.duplicates += 1
                continue
            for k, w in enumerate(windows):
                if k not in held_segs or first != f:
                    jobs.append(rec.Job(p, mode, settings, k, len(windows), w))
        summary.tasks = len(jobs)
        if jobs:
            say(f"{len(jobs)} tasks ({mode}) for {len({j.probe.path for j in jobs})} recordings")

        def done(o: Outcome) -> None:
            job = jobs[o.index]
            if o.lost:
                summary.lost += 1
                summary.messages.append(f"{job.probe.path}: lost ({o.error}); the next run does it")
                return
            if o.error is not None:
                rows = [blank_row(**job.probe.base(mode), segment=job.segment, segments=job.segments,
                                  status=ERROR, error=o.error)]
            else:
                rows = o.value
            store.add(rows)
            if any(r["status"] == ERROR for r in rows):
                summary.failed += 1
                summary.messages.append(f"{job.probe.path}: {rows[0]['error']}")
            elif rows and rows[0]["status"] == "ok":
                summary.ok += 1
            if on_task is not None:
                on_task(o)

        summary.outcomes = map_tasks(client, rec.process, jobs, label=f"archive {mode}", on_done=done, quiet=quiet)
        summary.rows = len(store.compact())
    return summary
