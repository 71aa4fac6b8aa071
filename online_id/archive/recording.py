"""The work on one recording, as it runs in a worker: probe it, then identify (and diagnose) it.

Both tasks are module-level functions of one picklable argument, so that
:func:`~online_id.archive.runner.map_tasks` can ship them to any worker.

* :func:`probe` reads what is cheap: the file's size, modification time and
  content hash, the MDF header (start time, test-centre properties), the
  recording's length, and so the bench, start time and segments to cut it
  into.
* :func:`process` identifies one segment as ``online-id identify`` does
  (:func:`~online_id.ingest.benchlog.read_bench` and
  :func:`~online_id.estimation.identification.identify` with its defaults: the
  order grid fitted on the best-excited 40 s of each operating point) and,
  in ``diagnose`` mode, diagnoses the recording as ``online-id diagnose`` does
  (:func:`~online_id.ingest.bench_series.bench_series` and
  :func:`~online_id.diagnose.bench_diagnosis.diagnose_bench`).  Its rows are
  those of :mod:`online_id.archive.table`; an error of the recording is one
  row with its one-line message.
"""

from __future__ import annotations

import datetime as dt
import hashlib
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from online_id.archive.metadata import MetaRules, RecordingMeta, resolve
from online_id.archive.table import ERROR, blank_row, effects_text, identification_rows
from online_id.config import Settings
from online_id.errors import InputDataError, OnlineIdError

IDENTIFY = "identify"
DIAGNOSE = "diagnose"
MODES = (IDENTIFY, DIAGNOSE)
FIT_S = 40.0  # identify's default --fit-seconds
DIAGNOSE_ORDER = 6  # diagnose's default --na / --nb on bench files
DIAGNOSE_MAX_EFFECTS = 3  # diagnose's default --max-effects


def content_hash(path: str | Path, chunk: int = 1 << 20) -> str:
    """SHA-256 of the file's bytes (hex)."""
    h = hashlib.sha256()
    try:
        with open(path, "rb") as f:
            while block := f.read(chunk):
                h.update(block)
    except OSError as err:
        raise InputDataError(f"{path}: cannot read ({err.strerror})") from None
    return h.hexdigest()


@dataclass(frozen=True)
class ProbeJob:
    """What :func:`probe` needs: the file, how to name its bench, and how long a segment may be."""

    path: str
    rules: MetaRules
    settings: Settings
    segment_s: float | None = None  # cut recordings longer than 1.5 times this (None: never)


@dataclass(frozen=True)
class Probe:
    """What :func:`probe` found (``error`` set when the file could not be read)."""

    path: str
    size_bytes: int | None
    mtime_ns: int | None
    sha256: str | None
    meta: RecordingMeta | None
    span_s: tuple[float, float] | None = None  # first and last sample time, when read
    error: str | None = None
    header: dict[str, str] = field(default_factory=dict)

    def base(self, mode: str) -> dict[str, Any]:
        """The recording's columns of its rows."""
        m = self.meta
        return {"path": self.path, "sha256": self.sha256, "size_bytes": self.size_bytes, "mtime_ns": self.mtime_ns,
                "mode": mode, "bench": m.bench if m else None, "bench_source": m.bench_source if m else None,
                "start_time": m.start_time if m else None, "start_source": m.start_source if m else None}


def probe(job: ProbeJob) -> Probe:
    """Stat, hash and read the header of a recording (see module notes); an unreadable file is a Probe with
    its error, not an exception."""
    from online_id.io.mdf import is_mdf

    path = job.path
    try:
        st = os.stat(path)
    except OSError as err:
        return Probe(path, None, None, None, resolve(path, job.rules), error=f"{path}: cannot read ({err.strerror})")
    size, mtime = st.st_size, st.st_mtime_ns
    try:
        digest = content_hash(path)
        start, props, span = None, {}, None
        if is_mdf(path):
            from online_id.io.mdf_header import read_header

            header = read_header(path)
            start, props = header.start_time, header.properties
            if header.duration_s is not None:
                span = (0.0, header.duration_s)
        if job.segment_s and span is None:
            from online_id.ingest.benchlog import read_bench

            data = read_bench(path, job.settings)
            span = (float(data.time_s[0]), float(data.time_s[-1]))
    except OnlineIdError as err:
        return Probe(path, size, mtime, None, resolve(path, job.rules), error=" ".join(str(err).split()))
    return Probe(path, size, mtime, digest, resolve(path, job.rules, start, props), span, header=props)


def segments(span_s: tuple[float, float] | None, segment_s: float | None) -> list[tuple[float, float] | None]:
    """Time windows to identify separately: the whole recording (``[None]``) unless it is longer than 1.5
    ``segment_s``; then ``round(length / segment_s)`` equal windows (a plateau across a cut is cut too)."""
    if span_s is None or not segment_s:
        return [None]
    t0, t1 = span_s
    n = int(round((t1 - t0) / segment_s))
    if (t1 - t0) <= 1.5 * segment_s or n < 2:
        return [None]
    edges = np.linspace(t0, t1, n + 1)
    return [(float(a), float(b)) for a, b in zip(edges[:-1], edges[1:])]


@dataclass(frozen=True)
class Job:
    """One task of :func:`process`: a recording's segment and what to do with it."""

    probe: Probe
    mode: str
    settings: Settings
    segment: int = 0
    segments: int = 1
    window: tuple[float, float] | None = None


def _window(data, window: tuple[float, float] | None):
    if window is None:
        return data
    i0, i1 = np.searchsorted(data.time_s, window, side="left")
    if i1 >= len(data) - 1:
        i1 = len(data)
    return data.slice(int(i0), int(i1))


def process(job: Job) -> list[dict[str, Any]]:
    """The table rows of one segment (see module notes)."""
    from online_id.ingest.benchlog import read_bench
    from online_id.estimation.identification import identify

    s = job.settings
    base = {**job.probe.base(job.mode), "segment": job.segment, "segments": job.segments,
            "segment_t0_s": job.window[0] if job.window else None,
            "segment_t1_s": job.window[1] if job.window else None}
    try:
        data = _window(read_bench(job.probe.path, s), job.window)
        result = identify(data, s.identification, s.inertias, fit_s=FIT_S, refine_s=None)
    except OnlineIdError as err:
        return [blank_row(**base, status=ERROR, error=" ".join(str(err).split()))]
    load = [float(np.mean(data.dyno_torque_nm[p.plateau.start:p.plateau.stop])) for p in result.points]
    rows = identification_rows(base, result, load)
    if job.mode == DIAGNOSE:
        effects, line = diagnose_recording(job.probe.path, s)
        for r in rows:
            r["effects"], r["diagnosis"] = effects, line
    return rows


def diagnose_recording(path: str, s: Settings) -> tuple[str | None, str]:
    """(effects, result line) of ``online-id diagnose PATH`` with its defaults; an error is the result line."""
    from online_id.ingest.bench_series import bench_series
    from online_id.diagnose.bench_diagnosis import diagnose_bench

    try:
        series = bench_series(Path(path), s)
        doc = diagnose_bench(series, na=DIAGNOSE_ORDER, nb=DIAGNOSE_ORDER, max_effects=DIAGNOSE_MAX_EFFECTS).as_dict()
    except OnlineIdError as err:
        return None, "error: " + " ".join(str(err).split())
    return effects_text(doc["effects"]), str(doc["result"])


def error_row(probe: Probe, mode: str, error: str) -> dict[str, Any]:
    """The one row of a recording that gave no result."""
    return blank_row(**probe.base(mode), segment=0, segments=1, status=ERROR, error=error)


def utc(t: dt.datetime | None) -> str:
    """A start time for people (``2025-03-04 07:30 UTC``; ``-`` when unknown)."""
    return "-" if t is None else t.astimezone(dt.timezone.utc).strftime("%Y-%m-%d %H:%M UTC")
