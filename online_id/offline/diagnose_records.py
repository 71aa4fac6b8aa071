"""Generic records for ``online-id diagnose``: one or two CSV files, shafts, units, clocks.

The file side of :mod:`online_id.diagnose.layouts`: reads the columns the options name
(header line or ``--no-header --columns``) from whichever file holds them,
puts each file on a uniform grid of its own clock (jitter reported), and hands
the records and their layout to :func:`online_id.diagnose.layouts.assemble` (units,
speeds from angles at full rate, clocks, torsion).  Warnings (a speed beyond
any rig, a large clock drift, no torsion) go to stderr as they are found and
into the JSON's ``recording.warnings``.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

from online_id.diagnose import DiagnoseData
from online_id.diagnose.align import Resampled, resample_uniform
from online_id.diagnose.shafts import parse_shafts
from online_id.errors import ConfigError, InputDataError
from online_id.io.named_csv import column_names, read_table
from online_id.io.table_csv import LINE_KEY
from online_id.diagnose.layouts import Column, Layout, ShaftColumn, assemble
from online_id.units import angle_factor, speed_factor

DEFAULT_ANGLE_UNIT = "rad"


def _names(args: argparse.Namespace, option: str) -> list[str] | None:
    text = getattr(args, option.replace("-", "_"))
    if not args.no_header:
        if text:
            raise ConfigError(f"--{option} needs --no-header")
        return None
    if not text:
        raise ConfigError(f"--no-header needs --{option} A,B,C naming the columns")
    names = [n.strip() for n in text.split(",")]
    if len(set(names)) != len(names) or not all(names):
        raise ConfigError(f"--{option} {text!r}: column names must be distinct and non-empty")
    return names


class _Files:
    """The files' headers, and which file holds a column a option names."""

    def __init__(self, paths: list[Path], headers: list[list[str]], named: list[str]):
        self.paths, self.headers, self.named = paths, headers, named

    def find(self, name: str, option: str) -> Column:
        """``NAME`` (looked up in every file) or ``NAME@1`` / ``NAME@2`` (in that file)."""
        base, at, which = name.rpartition("@")
        if at and which in ("1", "2") and base:
            k = int(which) - 1
            if k >= len(self.paths):
                raise ConfigError(f"{option} {name}: there is no file {which} (give --second-file)")
            if base not in self.headers[k]:
                raise InputDataError(f"{self.paths[k]}: no column {base!r} ({option}); {self.named[k]}: "
                                     f"{', '.join(self.headers[k])}")
            return Column(k, base)
        hits = [k for k, h in enumerate(self.headers) if name in h]
        if len(hits) > 1:
            raise ConfigError(f"{option} {name!r}: the column is in both {self.paths[0]} and {self.paths[1]}; "
                              f"say which: {name}@1 or {name}@2")
        if not hits:
            raise InputDataError("; ".join(f"{p}: no column {name!r} ({option}); {self.named[k]}: {', '.join(h)}"
                                           for k, (p, h) in enumerate(zip(self.paths, self.headers))))
        return Column(hits[0], name)


def _split_col(item: str, option: str) -> tuple[str, str, str | None]:
    """``NAME[:SHAFT[:UNIT]]`` -> name, shaft (default the column), unit (None: the default)."""
    parts = item.split(":")
    if len(parts) > 3 or not parts[0]:
        raise ConfigError(f"{option} {item!r}: expected NAME[:SHAFT[:UNIT]]")
    name = parts[0]
    shaft = parts[1] if len(parts) > 1 and parts[1] else name.rpartition("@")[0] or name
    unit = parts[2] if len(parts) > 2 and parts[2] else None
    return name, shaft, unit


def _shafts(args: argparse.Namespace, files: _Files) -> tuple[list[ShaftColumn], list]:
    """The measured shafts with their columns and units, and the geared ones."""
    default_angle = args.angle_unit or DEFAULT_ANGLE_UNIT
    if args.angle_unit:
        angle_factor(args.angle_unit, "--angle-unit")
    speed_factor(args.speed_unit, "--speed-unit")
    out = []
    for kind, items in (("speed", args.speed_col), ("angle", args.angle_col)):
        option = f"--{kind}-col"
        for item in items:
            name, shaft, unit = _split_col(item, option)
            col = files.find(name, option)
            if kind == "angle":
                u = unit or default_angle
                factor = angle_factor(u, f"{option} {item}")
                given = unit is not None or args.angle_unit is not None
            else:
                u = unit or args.speed_unit
                factor, given = speed_factor(u, f"{option} {item}"), True
            out.append(ShaftColumn(shaft, kind, col, factor, u, given))
    # the geared shafts (and the checks of names) as the shafts module parses them
    geared = [s for s in parse_shafts([], [], args.gear_ratio)]
    return out, geared


def _read(path: Path, names: list[str] | None, cols: list[str], time_col: str | None,
          fs: float | None) -> Resampled:
    table = read_table(path, list(dict.fromkeys(cols + ([time_col] if time_col else []))), names)
    lines = table.pop(LINE_KEY, None)
    if time_col:
        return resample_uniform(table.pop(time_col), table, str(path), time_col, lines)
    if fs is None or fs <= 0:
        raise ConfigError(f"{path}: give --time-col NAME or --fs HZ (> 0)")
    n = len(next(iter(table.values()))) if table else 0
    return Resampled(np.arange(n) / fs, table, float(fs), 0.0, 0.0, False)


def _clock_mode(args: argparse.Namespace) -> str:
    if args.clock_offset_s is not None and not args.same_clock:
        raise ConfigError("--clock-offset-s goes with --same-clock (a known offset between loggers on one clock)")
    if args.same_clock and args.align is not None:
        raise ConfigError("--same-clock and --align exclude each other: one states the clock, the other estimates it")
    if args.same_clock:
        return "same"
    return "estimate" if args.align is not None else "auto"


def read_records(args: argparse.Namespace) -> DiagnoseData:
    """The generic CSV path: one or two files as the options say, as diagnosis data."""
    paths = [Path(args.path)] + ([Path(args.second_file)] if args.second_file else [])
    if not args.second_file:
        for flag, given in (("--same-clock", args.same_clock), ("--align", args.align is not None),
                            ("--clock-offset-s", args.clock_offset_s is not None),
                            ("--second-time-col", args.second_time_col), ("--second-columns", args.second_columns)):
            if given:
                raise ConfigError(f"{flag} needs --second-file")
    mode = _clock_mode(args) if args.second_file else "auto"
    for p in paths:
        if not p.exists():
            raise InputDataError(f"{p}: no such file")
    names = [_names(args, "columns")] + ([_names(args, "second-columns")] if args.second_file else [])
    headers = [column_names(p, n) for p, n in zip(paths, names)]
    times = [args.time_col] + ([args.second_time_col or args.time_col] if args.second_file else [])
    if args.second_file and not all(times):
        raise ConfigError("--second-file needs time columns in both files (--time-col, --second-time-col)")
    for p, h, t in zip(paths, headers, times):
        if t and t not in h:
            raise InputDataError(f"{p}: no time column {t!r} (columns: {', '.join(h)})")
    # the time columns are each file's own: not candidates for the other options
    files = _Files(paths, [[c for c in h if c != t] for h, t in zip(headers, times)],
                   ["columns" if n is None else f"named by --{opt}" for n, opt in zip(names, ("columns", "second-columns"))])
    shafts, geared = _shafts(args, files)
    align = None
    if args.align:
        a1, sep, a2 = args.align.partition(":")
        if not (sep and a1 and a2):
            raise ConfigError(f"--align {args.align!r}: expected COL1:COL2")
        align = (files.find(f"{a1}@1", "--align"), files.find(f"{a2}@2", "--align"))
    torsion = None
    if args.torsion:
        a, sep, b = args.torsion.partition(":")
        if not (sep and a and b):
            raise ConfigError(f"--torsion {args.torsion!r}: expected SHAFT1:SHAFT2")
        torsion = (a, b)
    torques = []
    for item in getattr(args, "torque_col", []) or []:
        col, sep, shaft = item.rpartition(":")
        if not (sep and col and shaft):
            raise ConfigError(f"--torque-col {item!r}: expected COLUMN:SHAFT")
        if shaft not in [s.shaft for s in shafts]:
            raise ConfigError(f"--torque-col {item!r}: no shaft {shaft!r} (shafts: "
                              f"{', '.join(s.shaft for s in shafts) or 'none'})")
        torques.append((shaft, files.find(col, "--torque-col")))
    layout = Layout(files.find(args.input_col, "--input-col"), files.find(args.output_col, "--output-col"),
                    tuple(shafts), tuple(geared), args.differentiate_output, mode, args.clock_offset_s or 0.0,
                    align, torsion,
                    files.find(args.shaft_torque_col, "--shaft-torque-col") if args.shaft_torque_col else None,
                    args.sample_rate, tuple(torques))
    used = [layout.input, layout.output, *(s.column for s in shafts), *(align or ()),
            *([layout.shaft_torque] if layout.shaft_torque else []), *(c for _, c in torques)]
    records = [_read(p, n, [c.name for c in used if c.record == k], t, args.fs if k == 0 else None)
               for k, (p, n, t) in enumerate(zip(paths, names, times))]
    notes = {"file": {"path": str(paths[0]), **records[0].as_dict()}}
    if args.second_file:
        notes["second_file"] = {"path": str(paths[1]), **records[1].as_dict()}
    data = assemble(records, layout, [str(p) for p in paths], notes)
    for text in [data.notes["clock"]["text"]] if "clock" in data.notes else []:
        print(f"note: {text}", file=sys.stderr)
    assumed = [s.column.name for s in shafts if s.kind == "angle" and not s.unit_given]
    if assumed:
        print(f"note: angle column{'s' if len(assumed) > 1 else ''} {', '.join(assumed)} taken as radians "
              "(no unit given: --angle-unit UNIT or NAME:SHAFT:UNIT)", file=sys.stderr)
    lay = data.notes["layout"]
    if lay["shafts"]:
        print("note: shafts (mean speed): " + ", ".join(f"{n} {v['mean_rpm']:.6g} rpm from {v['column']} in {v['unit']}"
                                                      for n, v in lay["shafts"].items())
              + f"; torsion: {lay['torsion']}", file=sys.stderr)
    for text in data.notes["warnings"]:
        print(f"warning: {text}", file=sys.stderr)
    return data
