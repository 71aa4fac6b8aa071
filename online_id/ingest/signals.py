"""Turn raw input columns into :class:`~online_id.records.BenchData` (SI units)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from online_id.config import ColumnSettings, UnitSettings
from online_id.estimation.preprocess import angle_to_speed, check_uniform
from online_id.errors import InputDataError
from online_id.io.table_csv import LINE_KEY, read_csv_columns
from online_id.records import BenchData
from online_id.units import MAX_PLAUSIBLE_RAD_S, SPEED_UNITS, angle_factor, implausible_speed, unit_hint

MIN_SAMPLES = 200
MAX_SPEED_RPM = 1e5
MAX_TORQUE_NM = 1e6
"""Limits beyond any engine bench: a value past them is a unit or file error (and would overflow the maths)."""


def _check_range(x: np.ndarray, limit: float, column: str, unit: str, lines: np.ndarray | None, source: str,
                 scale: float = 1.0) -> None:
    """``|x * scale| <= limit`` everywhere (NaN fails), else an error naming the first offending line.

    The common case (all in range) is told from the extremes, without a temporary of the column's size
    (an hour at 1 kHz is 29 MB a column).
    """
    lo, hi = float(np.min(x)) * scale, float(np.max(x)) * scale
    if max(abs(lo), abs(hi)) <= limit:  # NaN makes this false: it is found below
        return
    bad = np.flatnonzero(~(np.abs(x * scale) <= limit))
    i = int(bad[0])
    where = f"{source}:{int(lines[i])}" if lines is not None else f"{source}: sample {i}"
    raise InputDataError(f"{where}: column {column!r}: {x[i] * scale:.6g} {unit} is beyond any bench "
                         f"(|value| <= {limit:g} {unit}); check the units in the config")


def _own(x: np.ndarray) -> np.ndarray:
    """``x`` as a float array that may be changed in place (a copy only where it is read-only or not float)."""
    x = np.asarray(x, dtype=float)
    return x if x.flags.writeable else x.copy()


def bench_data_from_columns(
    columns: dict[str, np.ndarray],
    names: ColumnSettings,
    units: UnitSettings,
    source: str,
) -> BenchData:
    """Convert columns (keyed by the names in ``names``) into SI bench data.

    The columns are converted in place (they are the caller's to give away: a reader's fresh arrays), so
    that a long recording is not held twice.
    """
    time_s = _own(columns[names.time])
    if units.time == "ms":
        time_s *= 1e-3
    n = time_s.shape[0]
    if n < MIN_SAMPLES:
        raise InputDataError(f"{source}: only {n} samples; at least {MIN_SAMPLES} are needed to identify anything")
    lines = columns.get(LINE_KEY)
    steps = np.diff(time_s)
    bad = np.flatnonzero(~(steps > 0))
    if bad.size:
        i = int(bad[0]) + 1
        where = f"{source}:{int(lines[i])}" if lines is not None else f"{source}: sample {i}"
        raise InputDataError(
            f"{where}: column {names.time!r}: time does not increase ({time_s[i - 1]!r} then {time_s[i]!r})"
        )
    try:
        check_uniform(time_s)
    except InputDataError as err:
        raise InputDataError(f"{source}: column {names.time!r}: {err}") from None
    speeds = []
    for role in ("dyno_speed", "engine_speed"):
        raw = _own(columns[getattr(names, role)])
        if units.speed in SPEED_UNITS:
            raw *= SPEED_UNITS[units.speed]
            speeds.append(raw)
        else:  # cumulative angles (deg, rad, rev, countsN)
            raw *= angle_factor(units.speed, "units.speed")
            speeds.append(angle_to_speed(raw, time_s, unit="rad"))
    torque = _own(columns[names.dyno_torque])
    if units.torque_sign != "braking":
        np.negative(torque, out=torque)
    for role, x in zip(("dyno_speed", "engine_speed"), speeds):
        try:
            _check_range(x, MAX_SPEED_RPM, getattr(names, role), "rpm", lines, source, scale=30.0 / np.pi)
        except InputDataError as err:
            w = float(np.nanmedian(np.abs(x)))
            hint = unit_hint(w, units.speed, _kind(units.speed)) if w > MAX_PLAUSIBLE_RAD_S else ""
            raise InputDataError(f"{err}" + (f" ({hint})" if hint else "")) from None
    _check_range(torque, MAX_TORQUE_NM, names.dyno_torque, "Nm", lines, source)
    return BenchData(time_s, speeds[0], speeds[1], torque, source)


def _kind(unit: str) -> str:
    return "speed" if unit in SPEED_UNITS else "angle"


def speed_warnings(data: BenchData, names: ColumnSettings, units: UnitSettings) -> list[str]:
    """One line per speed column that turns faster than any rig in the unit it was read in (likely a unit
    error: degrees read as radians), naming the likely unit (:func:`online_id.units.implausible_speed`)."""
    out = []
    for role, x in (("dyno_speed", data.dyno_speed_rad_s), ("engine_speed", data.engine_speed_rad_s)):
        text = implausible_speed(x, getattr(names, role), units.speed, _kind(units.speed))
        if text:
            out.append(f"{data.source}: {text}")
    return out


def read_bench_csv(path: str | Path, names: ColumnSettings | None = None, units: UnitSettings | None = None) -> BenchData:
    """Read a bench CSV file into SI units, with errors naming file, line and column."""
    return read_bench_csv_with(path, names, units)[0]


def read_bench_csv_with(path: str | Path, names: ColumnSettings | None = None, units: UnitSettings | None = None,
                        extra: tuple[str, ...] = ()) -> tuple[BenchData, dict[str, np.ndarray]]:
    """:func:`read_bench_csv` and the columns ``extra`` as they are (one pass over the file)."""
    names = names or ColumnSettings()
    units = units or UnitSettings()
    roles = [names.time, names.dyno_speed, names.engine_speed, names.dyno_torque]
    cols = read_csv_columns(path, roles + [c for c in extra if c not in roles])
    return bench_data_from_columns(cols, names, units, str(path)), {c: cols[c] for c in extra}


def read_bench_mdf(path: str | Path, names: ColumnSettings | None = None, units: UnitSettings | None = None,
                   notify=None) -> BenchData:
    """Read a signal ``.mf4`` recording into SI units (channels named like CSV columns; see :mod:`online_id.io.mdf`).

    The time is the channels' master time (seconds); a channel's own unit,
    when it has one, overrides ``units.speed`` (``rpm``, ``1/min``, ``rad/s``;
    ``deg`` or ``rad`` for cumulative angles) and is scaled to Nm for torque
    (``Nm``, ``kNm``).  ``notify`` gets one line per thing done (resampling,
    units taken from the file).
    """
    import dataclasses

    from online_id.io.mdf import read_mdf_columns, speed_unit, torque_factor

    names = names or ColumnSettings()
    units = units or UnitSettings()
    roles = ("dyno_speed", "engine_speed", "dyno_torque")
    got = read_mdf_columns(path, {role: getattr(names, role) for role in roles})
    notes = list(got.notes)
    speed = {role: speed_unit(got.units[role]) for role in roles[:2]}
    for role in roles[:2]:
        if got.units[role].strip() and speed[role] is None:
            raise InputDataError(f"{path}: channel {getattr(names, role)!r} has unit {got.units[role]!r}; expected "
                                 f"a speed (rpm, 1/min, rad/s) or a cumulative angle (deg, rad)")
    kinds = {u for u in speed.values() if u is not None}
    if len(kinds) > 1 and kinds & {"deg", "rad"}:
        raise InputDataError(f"{path}: channels {names.dyno_speed!r} and {names.engine_speed!r} mix a speed and an "
                             f"angle ({', '.join(sorted(kinds))}); expected two speeds or two angles")
    columns = {names.time: got.time_s}
    unit = units.speed
    for role in roles[:2]:
        x = got.columns[role]
        if speed[role] == "rad/s" and "rpm" in kinds:
            x = x * (30.0 / np.pi)  # one unit for both speeds: rpm
        columns[getattr(names, role)] = x
    if kinds:
        unit = "rpm" if "rpm" in kinds else kinds.pop()
        if unit != units.speed:
            notes.append(f"{path}: speeds in {unit} as the channels' units say (config units.speed "
                         f"{units.speed!r} not used)")
    factor = torque_factor(got.units["dyno_torque"])
    if got.units["dyno_torque"].strip() and factor is None:
        raise InputDataError(f"{path}: channel {names.dyno_torque!r} has unit {got.units['dyno_torque']!r}; "
                             f"expected a torque (Nm, kNm)")
    columns[names.dyno_torque] = got.columns["dyno_torque"] * (factor or 1.0)
    data = bench_data_from_columns(columns, names, dataclasses.replace(units, time="s", speed=unit), str(path))
    for text in notes:
        if notify is not None:
            notify(text)
    return data
