"""The header of an ASAM MDF 4 recording: when it started and what the test centre wrote about it.

A test-bed automation system fills the MDF 4 header block (HD): the
measurement's absolute start time, and in its comment (``HDcomment`` XML) a
description and ``common_properties`` such as the test bed, the project, the
operator or the engine.  :func:`read_header` returns them for the archive;
:func:`write_recording` writes a signal recording with them (the archive
simulator's files).

Errors are one-line :class:`~online_id.errors.InputDataError` naming the file.
"""

from __future__ import annotations

import datetime as dt
import xml.etree.ElementTree as ET
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from online_id.errors import InputDataError
from online_id.io.mdf import _open, _quiet, read_error
from online_id.io.outfile import atomic_output


@dataclass(frozen=True)
class RecordingHeader:
    """What an MDF 4 header says about a recording."""

    start_time: dt.datetime | None  # timezone-aware (UTC) measurement start; None when the file has none
    properties: dict[str, str] = field(default_factory=dict)  # HDcomment common_properties, name -> text
    description: str = ""  # the HDcomment's text
    duration_s: float | None = None  # span of the first channel group's master time


def _properties(comment: str) -> tuple[dict[str, str], str]:
    """``common_properties`` (flat ``<e name=...>`` entries, nested lists skipped) and the text of an HDcomment."""
    if not comment or not comment.lstrip().startswith("<"):
        return {}, comment or ""
    try:
        root = ET.fromstring(comment)
    except ET.ParseError:
        return {}, ""
    props = {}
    common = root.find("common_properties")
    if common is not None:
        for e in common.findall("e"):
            name = e.get("name")
            if name:
                props[name] = (e.text or "").strip()
    text = root.findtext("TX") or ""
    return props, text.strip()


def read_header(path: str | Path) -> RecordingHeader:
    """The start time, the header's properties and description, and the recording's length.

    Raises
    ------
    InputDataError
        Missing, unreadable or not an MDF file (one line, names the file).
    """
    path = Path(path)
    with _quiet():
        mdf = _open(path)
        try:
            header = mdf.header
            start = header.start_time
            if start is not None and start.tzinfo is None:
                start = start.replace(tzinfo=dt.timezone.utc)
            start = start.astimezone(dt.timezone.utc) if start is not None else None
            if start is not None and start.timestamp() <= 0:  # an unset header holds the epoch
                start = None
            props, text = _properties(header.comment if isinstance(header.comment, str) else "")
            duration = None
            if mdf.groups:
                try:
                    t = mdf.get_master(0)
                except Exception as err:  # asammdf: a data block cut short
                    raise read_error(path, err) from None
                duration = float(t[-1] - t[0]) if len(t) > 1 else 0.0
        finally:
            mdf.close()
    return RecordingHeader(start, props, text, duration)


def write_recording(path: str | Path, time_s: np.ndarray, channels: Mapping[str, tuple[np.ndarray, str]], *,
                    start_time: dt.datetime, properties: Mapping[str, str] | None = None,
                    description: str = "", acq_name: str = "bench") -> None:
    """Write channels ``name -> (values, unit)`` on one time base as an MDF 4.10 signal recording whose
    header holds ``start_time`` (timezone-aware), ``description`` and ``properties`` (common_properties).

    Raises
    ------
    InputDataError
        The file cannot be written, or ``start_time`` has no timezone (names the file).
    """
    from asammdf import MDF, Signal

    path = Path(path)
    if start_time.tzinfo is None:
        raise InputDataError(f"{path}: the start time {start_time} has no timezone")
    t = np.asarray(time_s, dtype=float)
    with atomic_output(path) as tmp, _quiet():
        mdf = MDF(version="4.10")
        try:
            mdf.append([Signal(np.asarray(v, dtype=float), t, name=name, unit=unit)
                        for name, (v, unit) in channels.items()], acq_name=acq_name, comment="online-id")
            header = mdf.header
            header.start_time = start_time
            header.description = description
            for key, value in (properties or {}).items():
                # asammdf keeps every common property here (its author, project, ... setters too)
                header._common_properties[str(key)] = str(value)
            mdf.save(tmp, overwrite=True)
        except OSError as err:
            raise InputDataError(f"{path}: cannot write: {err.strerror or err}") from err
        finally:
            mdf.close()
