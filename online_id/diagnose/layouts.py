"""Measured layouts: one or two records (e.g. a drive logger and a sensor logger) -> :class:`DiagnoseData`.

No file I/O: :mod:`online_id.offline.diagnose_records` reads the files and the
options, the rig evaluation passes simulated records; both end here.

Notes
-----
Each record is on a uniform grid of its own clock (jitter resampled away by
:func:`online_id.diagnose.align.resample_uniform`).  Any column may be in
either record: the input, the output, each shaft's angle or speed, a
measured shaft torque.  On its own record's grid, at its full rate:

- an angle column is scaled to radians by its unit (``deg``, ``rad``,
  ``rev``, ``countsN``) and differentiated to the shaft's speed [rad/s]
  (:func:`online_id.diagnose.shafts.speed_of`; a wrapped angle is unwrapped);
  a speed column is scaled to rad/s by its unit (``rpm``, ``rad/s``, ``hz``);
  a speed beyond any rig gets a warning naming the likely unit
  (:func:`online_id.units.implausible_speed`);
- the output, when it is an angle column, is scaled like it, and
  differentiated when asked.

The second record's clock is then put on the first's
(:func:`online_id.diagnose.align.decide_clock`: given, estimated, or estimated
only where the clocks plainly differ) and the slower record is interpolated
at the instants of the faster one, both cut to their overlap.  The torsion
across a stage is the twist of two angle-measured shafts ``a``, ``b``:
:math:`\\varphi = (r_b / r_a)\\,\\theta_a - \\theta_b` [rad of ``b``] with
``r`` the shafts' rates (gear ratios), or a measured shaft torque where one
is named.  Everything is then decimated alike through the generic path's
causal data path (:func:`online_id.diagnose.records.build_data`).
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from online_id.diagnose import DiagnoseData
from online_id.diagnose.align import Clock, Resampled, decide_clock, on_grid
from online_id.diagnose.records import RecordSpec, build_data, data_path, decimate_alike
from online_id.diagnose.shafts import ShaftSource, speed_of
from online_id.errors import ConfigError, InputDataError
from online_id.units import implausible_speed

MAX_TWIST_RAD = 0.5 * np.pi
"""A "twist" between two shafts spanning more than a quarter turn is no twist: their ratio is not the gear's."""


@dataclass(frozen=True)
class Column:
    """A column of record ``record`` (0: the first file, 1: the second)."""

    record: int
    name: str


@dataclass(frozen=True)
class ShaftColumn:
    """A shaft measured by an angle or speed column; ``factor`` scales the column to rad or rad/s."""

    shaft: str
    kind: str  # "angle" or "speed"
    column: Column
    factor: float = 1.0
    unit: str = "rad"
    unit_given: bool = True


@dataclass(frozen=True)
class Layout:
    """Which column is what, where, in which unit, and how the clocks relate.

    ``clock``: ``auto``, ``same`` (with ``clock_offset_s``: second = first +
    offset) or ``estimate``; ``align`` names the rotation columns the clocks
    are aligned on (default: the first shaft column of each record).
    ``torsion`` names two angle-measured shafts (default: the first two);
    ``shaft_torque`` a measured shaft torque column, used as the torsion.
    """

    input: Column
    output: Column
    shafts: tuple[ShaftColumn, ...] = ()
    geared: tuple[ShaftSource, ...] = ()
    differentiate_output: bool = False
    clock: str = "auto"
    clock_offset_s: float = 0.0
    align: tuple[Column, Column] | None = None
    torsion: tuple[str, str] | None = None
    shaft_torque: Column | None = None
    sample_rate_hz: float | None = None
    torques: tuple[tuple[str, Column], ...] = ()
    """``(shaft, column)``: a torque acting on that shaft (an input of its channel)."""

    def __post_init__(self) -> None:
        if self.clock not in ("auto", "same", "estimate"):
            raise ConfigError(f"clock must be auto, same or estimate, got {self.clock!r}")
        names = [s.shaft for s in self.shafts]
        dup = {n for n in names if names.count(n) > 1}
        if dup:
            raise ConfigError(f"shaft {sorted(dup)[0]!r} is given twice (--speed-col/--angle-col)")

    def output_factor(self) -> float:
        """The output's scale: that of the angle column it also is, else 1."""
        return next((s.factor for s in self.shafts if s.kind == "angle" and s.column == self.output), 1.0)


def _cumulative(theta: np.ndarray) -> np.ndarray:
    """A wrapped angle [rad] unwrapped (a cumulative one as it is)."""
    return np.unwrap(theta) if np.ptp(theta) <= 2.0 * np.pi + 1e-9 else theta


def _record_signals(rec: Resampled, index: int, layout: Layout, source: str, warnings: list[str],
                    names: dict[str, str]) -> dict[str, np.ndarray]:
    """The signals record ``index`` holds, keyed by role, derived at its full rate."""
    out: dict[str, np.ndarray] = {}
    fs = rec.fs_hz
    for s in layout.shafts:
        if s.column.record != index:
            continue
        x = rec.columns[s.column.name] * s.factor
        w = speed_of(s.kind, x, fs)
        out[f"w:{s.shaft}"] = w
        if s.kind == "angle":
            out[f"theta:{s.shaft}"] = _cumulative(x)
        text = implausible_speed(w, s.column.name, s.unit, s.kind)
        if text:
            warnings.append(f"{source}: {text}")
    if layout.input.record == index:
        out[names["input"]] = rec.columns[layout.input.name]
    if layout.output.record == index:
        y = rec.columns[layout.output.name] * layout.output_factor()
        out[names["output"]] = np.gradient(y) * fs if layout.differentiate_output else y
    if layout.shaft_torque is not None and layout.shaft_torque.record == index:
        out["shaft_torque"] = rec.columns[layout.shaft_torque.name]
    for shaft, col in layout.torques:
        if col.record == index:
            out[f"tq:{shaft}"] = rec.columns[col.name]
    return out


def _align_signal(rec: Resampled, index: int, layout: Layout, signals: dict) -> tuple[np.ndarray | None, str]:
    """The rotation signal record ``index`` offers for clock alignment, and its name."""
    if layout.align is not None:
        col = layout.align[index]
        shaft = next((s for s in layout.shafts if s.column == col), None)
        if shaft is not None:
            return signals[f"w:{shaft.shaft}"], col.name
        x = rec.columns[col.name]
        d = np.diff(x)  # a column that is no shaft: monotonic means a cumulative angle
        kind = "angle" if np.all(d >= 0) or np.all(d <= 0) else "speed"
        return speed_of(kind, x, rec.fs_hz), col.name
    shaft = next((s for s in layout.shafts if s.column.record == index), None)
    return (None, "") if shaft is None else (signals[f"w:{shaft.shaft}"], shaft.column.name)


def _names(layout: Layout, sources: list[str]) -> dict[str, str]:
    """Report names of input and output (the column names; told apart by file when equal)."""
    i, o = layout.input, layout.output
    iname, oname = i.name, o.name
    if iname == oname and i.record != o.record:
        iname, oname = f"{iname}@{i.record + 1}", f"{oname}@{o.record + 1}"
    if layout.differentiate_output:
        oname = f"d{oname}/dt"
    for n in (iname, oname):
        if n.startswith(("w:", "theta:", "tq:")) or n == "shaft_torque":
            raise ConfigError(f"{sources[0]}: column name {n!r} is reserved; rename the column")
    return {"input": iname, "output": oname}


def assemble(records: list[Resampled], layout: Layout, sources: list[str],
             notes: dict | None = None) -> DiagnoseData:
    """The diagnosis data of one or two records laid out as ``layout`` says (see module notes).

    ``sources`` names the records (file paths) for messages.  Returns data
    whose ``notes`` carry the clock (``clock``), the layout (``layout``: where
    each signal came from, in which unit) and the warnings (``warnings``).
    """
    if not 1 <= len(records) <= 2:
        raise ConfigError(f"one or two records, got {len(records)}")
    source = " + ".join(sources)
    notes = dict(notes or {})
    warnings: list[str] = []
    names = _names(layout, sources)
    signals = [_record_signals(r, i, layout, sources[i], warnings, names) for i, r in enumerate(records)]
    if len(records) == 1:
        merged, fs = signals[0], records[0].fs_hz
        base, t0 = 0, float(records[0].time_s[0])
    else:
        (x1, on1), (x2, on2) = (_align_signal(r, i, layout, signals[i]) for i, r in enumerate(records))
        r1, r2 = records
        clock = decide_clock(r1.time_s, x1, r2.time_s, x2, r1.fs_hz, mode=layout.clock,
                             offset_s=layout.clock_offset_s, source=source, on=f"{on1} / {on2}")
        warnings += list(clock.warnings)
        base = 1 if r2.fs_hz > 1.001 * r1.fs_hz else 0  # the slower record is interpolated, never decimated
        recs = [replace(r, columns=s) for r, s in zip(records, signals)]
        if base == 0:
            t, cut, moved = on_grid(recs[0], recs[1], clock.fit.to_clock2(recs[0].time_s), source)
        else:
            t, cut, moved = on_grid(recs[1], recs[0], clock.fit.to_clock1(recs[1].time_s), source)
        merged, fs, t0 = {**cut, **moved}, records[base].fs_hz, float(t[0])
        notes["clock"] = clock.as_dict(f"{on1} / {on2}" if clock.mode == "estimated" else "")
    speeds = tuple(ShaftSource(s.shaft, "speed", f"w:{s.shaft}") for s in layout.shafts)
    spec = RecordSpec(names["input"], names["output"], speeds + tuple(layout.geared),
                      sample_rate_hz=layout.sample_rate_hz, output_centred=layout.differentiate_output)
    rec = Resampled(np.arange(len(merged[names["input"]])) / fs, merged, fs, 0.0, 0.0, False)
    notes["layout"] = _layout_note(layout, sources, base, fs, t0, merged)
    if layout.differentiate_output:  # the sensor a delay is reported on: the column, not its derivative
        notes["output_sensor"] = names["output"][1:-3]
    data = build_data(rec, None, spec, source, notes)
    torsion, how = _torsion(merged, layout, data, source, warnings)
    joints = _joints(merged, layout, data) if layout.shaft_torque is None else {}
    torques = {k: v for k, v in merged.items() if k.startswith("tq:")}
    if torsion is not None or joints or torques:
        path = data_path(fs, layout.sample_rate_hz)
        t = decimate_alike({**joints, **torques, **({} if torsion is None else {"torsion": torsion})}, path)
        n = next(iter(t.values())).size
        if n != len(data):
            raise InputDataError(f"{source}: the torsion has {n} samples after the data path, the record {len(data)}")
        acting = {k[3:]: t.pop(k) for k in list(t) if k.startswith("tq:")}
        data = replace(data, torsion=t.pop("torsion", None), joints=t, torques=acting)
    data.notes["layout"]["torsion"] = how
    if data.joints:
        data.notes["layout"]["joints"] = sorted(data.joints)
    data.notes["warnings"] = warnings
    return data


def _torsion(merged: dict, layout: Layout, data: DiagnoseData, source: str,
             warnings: list[str]) -> tuple[np.ndarray | None, str]:
    """The torsion at full rate and what it is, or ``None`` and why not."""
    if layout.shaft_torque is not None:
        return merged["shaft_torque"], f"measured shaft torque {layout.shaft_torque.name!r}"
    angled = [s.shaft for s in layout.shafts if s.kind == "angle"]
    pair = layout.torsion
    if pair is None:
        if len(angled) < 2:
            return None, "none (no two angle columns, no shaft torque)"
        pair = (angled[0], angled[1])
    a, b = pair
    for s in (a, b):
        if s not in angled:
            raise ConfigError(f"--torsion {a}:{b}: {s!r} is not a shaft measured by an angle column "
                              f"(angle shafts: {', '.join(angled) or 'none'})")
    rho = data.shaft_rates[b] / data.shaft_rates[a]
    phi = _twist(merged, data, a, b)
    span = float(np.ptp(phi))
    if not span <= MAX_TWIST_RAD:
        warnings.append(f"{source}: no torsion from {a} and {b}: their twist spans {span:.3g} rad, so they do "
                        f"not turn at the rate ratio {rho:.6g}; give the exact ratio (--gear-ratio "
                        f"{b}={a}/R) or another pair (--torsion A:B)")
        return None, f"none ({a} and {b} do not turn at a fixed ratio)"
    return phi, f"twist ({rho:.6g} {a} - {b}) [rad of {b}]"


def _twist(merged: dict, data: DiagnoseData, a: str, b: str) -> np.ndarray:
    """``(r_b / r_a) theta_a - theta_b`` [rad of ``b``] of two angle-measured shafts at full rate."""
    return data.shaft_rates[b] / data.shaft_rates[a] * merged[f"theta:{a}"] - merged[f"theta:{b}"]


def _joints(merged: dict, layout: Layout, data: DiagnoseData) -> dict[str, np.ndarray]:
    """The twist across each joint between two angle-measured shafts next to each other in the order the
    angle columns are given (``--torsion A:B``: that pair only), at full rate; a pair whose twist spans more
    than :data:`MAX_TWIST_RAD` is left out (they do not turn at the rates' ratio)."""
    angled = [s.shaft for s in layout.shafts if s.kind == "angle"]
    pairs = [layout.torsion] if layout.torsion is not None else list(zip(angled[:-1], angled[1:]))
    out = {}
    for a, b in pairs:
        phi = _twist(merged, data, a, b)
        if float(np.ptp(phi)) <= MAX_TWIST_RAD:
            out[f"{a}-{b}"] = phi
    return out


def _layout_note(layout: Layout, sources: list[str], base: int, fs: float, t0: float, merged: dict) -> dict:
    """Where each signal came from and in which unit; ``t0_s``: the first sample on the time base's clock."""
    def where(c: Column) -> str:
        return f"{c.name} ({sources[c.record]})"

    return {"time_base": sources[base], "fs_hz": fs, "t0_s": t0, "input": where(layout.input),
            "output": where(layout.output) + (", differentiated" if layout.differentiate_output else ""),
            "shafts": {s.shaft: {"column": where(s.column), "kind": s.kind,
                                 "unit": s.unit + ("" if s.unit_given else " (assumed: no unit given)"),
                                 "mean_rpm": float(np.mean(merged[f"w:{s.shaft}"])) * 30.0 / np.pi}
                       for s in layout.shafts}}
