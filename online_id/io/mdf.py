"""ASAM MDF 4 (``.mf4``) measurement files through asammdf: signal recordings in, and out.

Test-bed automation and calibration tools record MDF 4 in two shapes:

* **signal recordings**: one channel per quantity (``DynoSpeed`` in rpm,
  ``DynoTorque`` in Nm), in channel groups that may run at different rates;
* **bus logging** (ASAM MDF bus logging): the raw CAN frames, in a
  ``CAN_DataFrame`` channel group; python-can's ``MF4Reader``/``MF4Writer``
  read and write those, so :mod:`online_id.io.canlog` treats them as a CAN
  log like ``.blf``.

:func:`is_bus_log` tells the two apart.  :func:`read_mdf_columns` maps the
channels of a signal recording like CSV columns (a channel is named as in the
config's ``columns``, optionally ``NAME@GROUP`` with the channel group's index
or acquisition name when the name is in several groups), converts their units
into the ones the offline methods read, and puts channels recorded at
different rates, or jittered, onto one uniform grid by linear interpolation
(asammdf's ``Signal.interp``), saying what was done.

Every failure (no such file, not an MDF file, a file cut short, a missing
channel) is an :class:`~online_id.errors.InputDataError` of one line naming
the file and, where it applies, the channel.
"""

from __future__ import annotations

import contextlib
import gc
import logging
import sys
import warnings
from collections.abc import Callable, Iterator, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from online_id.errors import InputDataError
from online_id.io.outfile import atomic_output

SUFFIX = ".mf4"

SPEED_UNITS = {"rpm": "rpm", "1/min": "rpm", "min-1": "rpm", "min^-1": "rpm", "u/min": "rpm", "rev/min": "rpm",
               "rad/s": "rad/s", "deg": "deg", "°": "deg", "rad": "rad"}
"""Unit strings of speed (or cumulative angle) channels, lower case -> the unit name of the config."""
TORQUE_SCALE = {"nm": 1.0, "n.m": 1.0, "n*m": 1.0, "n m": 1.0, "n·m": 1.0, "knm": 1000.0}
"""Unit strings of torque channels, lower case -> factor to Nm."""


def is_mdf(path: str | Path) -> bool:
    """True when the suffix is ``.mf4``."""
    return Path(path).suffix.lower() == SUFFIX


@contextlib.contextmanager
def _quiet() -> Iterator[None]:
    """Silence asammdf's warnings, log records and the noise of its half-built objects on a bad file."""
    hook = sys.unraisablehook
    # asammdf's MDF4.__del__ fails on a file it could not open; an interrupt (SIGINT, SIGTERM) passes on
    sys.unraisablehook = lambda info: hook(info) if isinstance(info.exc_value, KeyboardInterrupt) else None
    level = logging.getLogger("asammdf").level
    logging.getLogger("asammdf").setLevel(logging.CRITICAL)
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            yield
    finally:
        gc.collect()
        sys.unraisablehook = hook
        logging.getLogger("asammdf").setLevel(level)


def read_error(path: Path, err: BaseException, what: str = "MDF 4 file") -> InputDataError:
    """A one-line error for an MDF file asammdf could not read (cut short, corrupt, not MDF)."""
    text = " ".join(str(err).split()) or type(err).__name__
    if isinstance(err, ValueError | EOFError) and ("seek" in text or "buffer" in text or "unpack" in text):
        text = f"it is cut short or corrupt ({text})"
    return InputDataError(f"{path}: cannot read the {what}: {text}")


def opened(factory: Callable[[], Any], path: Path, what: str = "MDF 4 file") -> Any:
    """``factory()`` (asammdf's ``MDF(path)``, python-can's ``MF4Reader(path)``), or the one-line error of
    :func:`read_error`; call it inside :func:`_quiet`.

    The error is raised outside the ``except`` block, so that it carries neither asammdf's exception
    as its context nor, through that exception's traceback, the half-built ``MDF4`` object: that object
    is collected here, while :func:`_quiet` silences its failing ``__del__``, not at the interpreter's exit
    (where it printed a traceback after the one-line error).
    """
    error = None
    try:
        return factory()
    except Exception as err:  # asammdf raises MdfException, ValueError, struct.error, ... on a bad file
        error = read_error(path, err, what)
    gc.collect()
    raise error


def _open(path: Path):
    from asammdf import MDF

    if path.is_dir():
        raise InputDataError(f"{path}: cannot read the MDF 4 file: it is a directory")
    if not path.is_file():
        raise InputDataError(f"{path}: cannot read the MDF 4 file: no such file")
    return opened(lambda: MDF(path), path)


def is_bus_log(path: str | Path) -> bool:
    """True when the ``.mf4`` file holds CAN bus logging (a ``CAN_DataFrame`` channel group).

    Raises
    ------
    InputDataError
        Missing, unreadable or not an MDF file (one line, names the file).
    """
    path = Path(path)
    with _quiet():
        mdf = _open(path)
        try:
            return any(ch.name == "CAN_DataFrame" for group in mdf.groups for ch in group.channels)
        finally:
            mdf.close()


@dataclass
class MdfColumns:
    """Channels of a signal recording on one time grid (see :func:`read_mdf_columns`)."""

    time_s: np.ndarray
    columns: dict[str, np.ndarray]  # name as asked -> values in ``units``
    units: dict[str, str]  # name as asked -> unit of the values (rpm, rad/s, deg, rad or Nm)
    notes: list[str] = field(default_factory=list)  # what was done (resampling, units taken from the file)


def _find(mdf, path: Path, spec: str) -> tuple[str, int, int]:
    """``NAME`` or ``NAME@GROUP`` -> (name, group index, channel index)."""
    name, _, group = spec.rpartition("@") if "@" in spec else (spec, "", "")
    where = mdf.whereis(name)
    if group:
        acq = {i: str(g.channel_group.acq_name or "") for i, g in enumerate(mdf.groups)}
        where = tuple(w for w in where if str(w[0]) == group or acq[w[0]] == group)
    groups = sorted({g for g, _ in where})
    if not where:
        names = sorted({ch.name for g in mdf.groups for ch in g.channels if ch.name != "time"})
        shown = ", ".join(repr(n) for n in names[:20]) + (", ..." if len(names) > 20 else "")
        raise InputDataError(f"{path}: no channel {spec!r}; the file has {shown} (config key columns)")
    if len(groups) > 1:
        acq = ", ".join(f"{g} {str(mdf.groups[g].channel_group.acq_name or '')!r}" for g in groups)
        raise InputDataError(f"{path}: channel {name!r} is in {len(groups)} channel groups ({acq}); name one "
                             f"as '{name}@GROUP' with the group's index or acquisition name (config key columns)")
    return name, where[0][0], where[0][1]


def _rate_hz(t: np.ndarray) -> float:
    return 1.0 / float(np.median(np.diff(t))) if t.size > 1 else float("nan")


def _uniform(t: np.ndarray) -> bool:
    if t.size < 3:
        return True
    dt = np.diff(t)
    mean = (t[-1] - t[0]) / (t.size - 1)
    return bool(mean > 0 and np.max(np.abs(dt - mean)) <= 0.01 * mean)


def read_mdf_columns(path: str | Path, names: Mapping[str, str]) -> MdfColumns:
    """The channels ``names`` (role -> channel name) of a signal ``.mf4`` on one uniform grid.

    Channels that share one uniform time base are returned as recorded.
    Otherwise every channel is interpolated linearly onto a uniform grid at
    the rate of the fastest one, over the span all of them cover, and a note
    says so.

    Raises
    ------
    InputDataError
        Unreadable file, missing or ambiguous channel, a channel without
        numeric samples, channels that do not overlap in time (names the
        file and the channel).
    """
    from asammdf.blocks.options import FloatInterpolation, IntegerInterpolation

    path = Path(path)
    with _quiet():
        mdf = _open(path)
        try:
            signals = {}
            for role, spec in names.items():
                name, group, index = _find(mdf, path, spec)
                try:
                    sig = mdf.get(name, group, index)
                except Exception as err:  # asammdf: a data block cut short, a bad conversion
                    raise read_error(path, err, f"channel {spec!r} of the MDF 4 file") from None
                if sig.samples.dtype.kind not in "iuf" or sig.samples.ndim != 1:
                    raise InputDataError(f"{path}: channel {spec!r} holds {sig.samples.dtype} samples, "
                                         f"expected numbers (config key columns)")
                if sig.timestamps.size < 2:
                    raise InputDataError(f"{path}: channel {spec!r} has {sig.timestamps.size} samples")
                signals[role] = sig
        finally:
            mdf.close()
        times = [s.timestamps for s in signals.values()]
        notes = []
        same = all(t.shape == times[0].shape and np.array_equal(t, times[0]) for t in times)
        if same and _uniform(times[0]):
            grid = np.asarray(times[0], dtype=float)
            columns = {role: np.asarray(s.samples, dtype=float) for role, s in signals.items()}
        else:
            rates = {role: _rate_hz(s.timestamps) for role, s in signals.items()}
            fastest = max(rates.values())
            t0 = max(float(t[0]) for t in times)
            t1 = min(float(t[-1]) for t in times)
            if not t1 > t0:
                raise InputDataError(f"{path}: the channels {', '.join(map(repr, names.values()))} do not "
                                     f"overlap in time; nothing to resample")
            grid = t0 + np.arange(int(np.floor((t1 - t0) * fastest + 1e-6)) + 1) / fastest
            columns = {role: np.asarray(s.interp(grid, IntegerInterpolation.LINEAR_INTERPOLATION,
                                                 FloatInterpolation.LINEAR_INTERPOLATION).samples, dtype=float)
                       for role, s in signals.items()}
            recorded = ", ".join(f"{names[r]} {rates[r]:.6g} Hz" + ("" if _uniform(signals[r].timestamps)
                                                                    else " (not uniform)") for r in signals)
            notes.append(f"{path}: channels recorded at {recorded}: resampled onto one uniform "
                         f"{fastest:.6g} Hz grid by linear interpolation, t = {t0:.3f}-{t1:.3f} s "
                         f"(the span all channels cover, {grid.size} samples)")
    units = {role: str(s.unit or "") for role, s in signals.items()}
    return MdfColumns(grid, columns, units, notes)


def speed_unit(unit: str) -> str | None:
    """The config's name for a speed channel's unit string (``1/min`` -> ``rpm``), None for no unit."""
    return SPEED_UNITS.get(unit.strip().lower()) if unit.strip() else None


def torque_factor(unit: str) -> float | None:
    """Factor from a torque channel's unit to Nm, None for no unit."""
    return TORQUE_SCALE.get(unit.strip().lower()) if unit.strip() else None


def write_mdf_signals(path: str | Path, time_s: np.ndarray, channels: Mapping[str, tuple[np.ndarray, str]],
                      acq_name: str = "bench") -> None:
    """Write channels ``name -> (values, unit)`` on one time base as an MDF 4.10 signal recording.

    Raises
    ------
    InputDataError
        The file cannot be written (names the file).
    """
    from asammdf import MDF, Signal

    path = Path(path)
    t = np.asarray(time_s, dtype=float)
    with atomic_output(path) as tmp, _quiet():
        mdf = MDF(version="4.10")
        try:
            mdf.append([Signal(np.asarray(v, dtype=float), t, name=name, unit=unit)
                        for name, (v, unit) in channels.items()], acq_name=acq_name, comment="online-id")
            mdf.save(tmp, overwrite=True)
        except OSError as err:
            raise InputDataError(f"{path}: cannot write: {err.strerror or err}") from err
        finally:
            mdf.close()
