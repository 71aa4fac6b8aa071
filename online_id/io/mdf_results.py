"""Results as ASAM MDF 4 channels (``--out-mf4``), so that asammdf and measurement tools show them beside the
recorded signals.

A results file holds channel groups (one per kind of result: estimates,
quality, state, alerts ...), each on its own time stamps, with units,
comments, value-to-text conversions for states and kinds, and text channels
for messages.  Times are on the recording's time base: the file's start time
is the recording's (the header of an MDF 4 input, the first frame of a log
with Unix times), and the time stamps are seconds from it.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from datetime import datetime, timezone
from pathlib import Path

import numpy as np

from online_id.errors import InputDataError
from online_id.io.mdf import _open, _quiet, is_mdf
from online_id.io.outfile import atomic_output

EPOCH_S = 1e8  # time stamps above this are Unix times


@dataclass(frozen=True)
class Channel:
    """One channel: values (numbers, or ``str`` for a text channel), unit, comment, value-to-text table."""

    name: str
    values: Sequence | np.ndarray
    unit: str = ""
    comment: str = ""
    texts: Mapping[int, str] | None = None


@dataclass(frozen=True)
class ChannelGroup:
    """Channels on one set of time stamps [s from the file's start time]."""

    name: str
    time_s: np.ndarray
    channels: Sequence[Channel] = field(default_factory=tuple)
    comment: str = ""


@dataclass(frozen=True)
class TimeBase:
    """The recording's time base: its start (UTC) and the stream time [s] that start corresponds to."""

    start: datetime | None
    t0_s: float

    def rel(self, t_s) -> np.ndarray:
        """Stream times -> seconds from :attr:`start`."""
        return np.asarray(t_s, dtype=float) - self.t0_s


def recording_time_base(path: str | Path, t_first_s: float | None = None) -> TimeBase:
    """The time base of a recording: an MDF 4 file's header start; else Unix stream times from the first one."""
    path = Path(path)
    if is_mdf(path) and path.exists():
        with _quiet():
            mdf = _open(path)
            try:
                start = mdf.header.start_time
            finally:
                mdf.close()
        if start.tzinfo is None:
            start = start.replace(tzinfo=timezone.utc)
        absolute = t_first_s is not None and t_first_s > EPOCH_S
        return TimeBase(start, start.timestamp() if absolute else 0.0)
    if t_first_s is not None and t_first_s > EPOCH_S:
        return TimeBase(datetime.fromtimestamp(t_first_s, timezone.utc), float(t_first_s))
    return TimeBase(None, 0.0)


def _signal(ch: Channel, t: np.ndarray):
    from asammdf import Signal

    if ch.values is not None and len(ch.values) and isinstance(ch.values[0], str):
        values = np.array([v.encode("utf-8") for v in ch.values], dtype=bytes)
    elif ch.texts is not None:
        values = np.asarray(ch.values, dtype=np.int64)
    else:
        values = np.asarray(ch.values, dtype=float)
    if values.size == 0:
        values = np.zeros(0, dtype=np.int64 if ch.texts is not None else float)
    conversion = None
    if ch.texts:
        conversion = {f"val_{k}": int(v) for k, v in enumerate(ch.texts)}
        conversion |= {f"text_{k}": text.encode() for k, text in enumerate(ch.texts.values())}
        conversion["default"] = b""
    extra = {"encoding": "utf-8"} if values.dtype.kind == "S" else {}
    return Signal(values, t, name=ch.name, unit=ch.unit, comment=ch.comment, conversion=conversion, **extra)


def write_results_mdf(path: str | Path, groups: Sequence[ChannelGroup], base: TimeBase,
                      comment: str = "online-id results") -> None:
    """Write ``groups`` as an MDF 4.10 file (atomically); a failure is one :class:`InputDataError` line."""
    from asammdf import MDF

    path = Path(path)
    with atomic_output(path) as tmp, _quiet():
        mdf = MDF(version="4.10")
        try:
            if base.start is not None:
                mdf.header.start_time = base.start
            for g in groups:
                t = np.asarray(g.time_s, dtype=float)
                for ch in g.channels:
                    if len(ch.values) != t.size:
                        raise InputDataError(f"{path}: channel {ch.name} has {len(ch.values)} values for "
                                             f"{t.size} time stamps")
                mdf.append([_signal(ch, t) for ch in g.channels], acq_name=g.name, comment=g.comment or g.name)
            mdf.save(tmp, overwrite=True)
        except OSError as err:
            raise InputDataError(f"{path}: cannot write: {err.strerror or err}") from err
        finally:
            mdf.close()
