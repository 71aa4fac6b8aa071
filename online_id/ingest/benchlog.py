"""A recorded CAN log as bench data: what ``identify``, ``diagnose`` and ``convert`` read.

A bench engineer's recording is a candump ``.log``, ``.asc`` or ``.blf`` of
the bus, not a CSV.  This decodes it with the same DBC codec and sample
assembler as the service (the config's ``dbc``, ``mapping`` and ``input``
sections), so the samples are those the service would have estimated from.

The offline methods need one uniform grid.  A log with gaps (a role silent
for longer than ``input.timeout_s``, a restarted recording) gives several
stretches; the longest one is used and :class:`LogBench` says what was left
out.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np

from online_id.service.assembly import AssembledSample, AssemblyCounters, SampleAssembler
from online_id.config import Settings
from online_id.progress import Progress
from online_id.errors import InputDataError
from online_id.io.logformats import SUFFIXES
from online_id.io.mdf import is_bus_log, is_mdf
from online_id.records import ROLES, BenchData, FrameFault
from online_id.ingest.signals import MIN_SAMPLES, read_bench_csv, read_bench_mdf


@dataclass
class LogBench:
    """The longest gap-free stretch of a CAN log, and what the rest held."""

    data: BenchData
    stretches: int  # gap-free stretches in the log
    samples_total: int  # samples in all stretches
    frames: int  # frames read
    counters: AssemblyCounters  # unusable frames by kind, as the service counts them
    truncated: str | None = None  # the warning when the log ends early

    @property
    def unknown_frames(self) -> int:
        """Frames of IDs the mapping does not use (ignored)."""
        return self.counters.faults[FrameFault.UNKNOWN_ID]

    def note(self) -> str | None:
        """One line for the user when not all of the log is used, else None."""
        if self.stretches <= 1:
            return self.truncated
        t = self.data.time_s
        text = (f"{self.data.source}: {self.stretches} gap-free stretches; using the longest, "
                f"t = {t[0]:.3f}-{t[-1]:.3f} s ({len(t)} of {self.samples_total} samples)")
        return text if self.truncated is None else f"{self.truncated}\n{text}"


def is_can_log(path: str | Path) -> bool:
    """True when the file is a CAN log python-can reads: by the suffix, and for ``.mf4`` by its content."""
    if is_mdf(path):
        return is_bus_log(path)
    return Path(path).suffix.lower() in SUFFIXES


def read_bench_log(path: str | Path, s: Settings, progress: Progress | None = None) -> LogBench:
    """Decode and assemble a CAN log (see module notes).

    ``progress`` (a :class:`~online_id.progress.Progress`) is given the
    frames read every 2000 frames, as ``replay`` does.

    Raises
    ------
    InputDataError
        Unreadable log (names the file and line), or no stretch of at least
        ``MIN_SAMPLES`` samples (names the file, and the input frames found).
    """
    # the CAN side (python-can, cantools) only when a log is read: a bench CSV does not load it
    from online_id.io.canlog import count_frames, read_log
    from online_id.io.dbc import CommandSample
    from online_id.service.runtime import input_decoder

    path = Path(path)
    decoder = input_decoder(s)
    assembler = SampleAssembler(s.input.sample_rate_hz, s.input.timeout_s, s.input.slow_roles)
    counters = assembler.counters
    stretches: list[list[AssembledSample]] = []
    frames = 0
    cut: list[str] = []
    total = count_frames(path) if progress is not None and progress.enabled else None
    for t_s, ident, data, is_ext, is_err in read_log(path, cut.append):
        if progress is not None and frames % 2000 == 0:
            progress.count(frames, total, f"t = {t_s:.1f} s")
        frames += 1
        res = FrameFault.MALFORMED if is_err else decoder.decode(ident, data, t_s, is_ext)
        if isinstance(res, FrameFault):
            counters.count(res)
            continue
        if isinstance(res, CommandSample):
            continue
        for sample in res:
            for a in assembler.push(sample):
                if a.discontinuity or not stretches:
                    stretches.append([])
                stretches[-1].append(a)
    total = sum(len(x) for x in stretches)
    best = max(stretches, key=len) if stretches else []
    if len(best) < MIN_SAMPLES:
        roles = ", ".join(f"{r} ({decoder.mapping.role(r).message})" for r in ROLES)
        unknown = counters.faults[FrameFault.UNKNOWN_ID]
        raise InputDataError(
            f"{path}: only {len(best)} samples in its longest gap-free stretch ({frames} frames read, "
            f"{unknown} of other IDs, {counters.bad_frames} unusable); at least {MIN_SAMPLES} are needed, "
            f"with every role present: {roles} at {s.input.sample_rate_hz:g} Hz ({decoder.source}, "
            f"config keys dbc, mapping, input)")
    data = BenchData(np.array([a.t_s for a in best]), np.array([a.dyno_speed for a in best]),
                     np.array([a.engine_speed for a in best]), np.array([a.dyno_torque for a in best]),
                     str(path))
    return LogBench(data, len(stretches), total, frames, counters, cut[0] if cut else None)


def read_bench(path: str | Path, s: Settings, notify: Callable[[str], None] | None = None) -> BenchData:
    """A bench CSV or a CAN log (by the suffix) as bench data; ``notify`` gets the log's note."""
    if not is_can_log(path):
        if is_mdf(path):
            return read_bench_mdf(path, s.columns, s.units, notify)
        return read_bench_csv(path, s.columns, s.units)
    log = read_bench_log(path, s)
    note = log.note()
    if note and notify is not None:
        notify(note)
    return log.data
