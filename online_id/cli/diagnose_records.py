"""Generic records for ``online-id diagnose``: one or two CSV files, shafts, clocks, resampling.

The file side of :mod:`online_id.diagnose.align` and
:mod:`online_id.diagnose.shafts`: reads the columns the options name (header
line or ``--no-header --columns``), puts each file on a uniform grid (jitter
reported), aligns a second file's clock on the first (offset and drift from a
rotation signal both files hold), and returns the merged columns with notes
for the report.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from online_id.diagnose import DiagnoseData
from online_id.diagnose.align import Resampled, resample_uniform
from online_id.diagnose.records import RecordSpec, build_data
from online_id.diagnose.shafts import parse_shafts
from online_id.errors import ConfigError, InputDataError
from online_id.io.named_csv import column_names, read_table

SPEED_UNITS = {"rad/s": 1.0, "rpm": 2.0 * np.pi / 60.0, "hz": 2.0 * np.pi}


def add_arguments(g: argparse._ArgumentGroup) -> None:
    """The generic path's shaft, second-file and headerless options."""
    g.add_argument("--speed-col", action="append", default=[], metavar="NAME[:SHAFT]",
                   help="a shaft speed column (repeatable); SHAFT names the shaft (default: the column)")
    g.add_argument("--speed-unit", choices=sorted(SPEED_UNITS), default="rad/s",
                   help="unit of the --speed-col columns (default rad/s)")
    g.add_argument("--angle-col", action="append", default=[], metavar="NAME[:SHAFT]",
                   help="a cumulative shaft angle column [rad] (repeatable; wrapped angles are unwrapped)")
    g.add_argument("--gear-ratio", action="append", default=[], metavar="SHAFT=REF/R",
                   help="SHAFT turns once per R turns of REF (REF*R: R times per turn); defines unmeasured "
                   "shafts and the order grid (repeatable)")
    g.add_argument("--second-file", metavar="FILE",
                   help="a second CSV (e.g. the sensor side) on its own clock, aligned on its time column")
    g.add_argument("--second-time-col", metavar="NAME", help="time column of the second file (default --time-col)")
    g.add_argument("--align", metavar="COL1:COL2",
                   help="rotation columns (speed or angle) of the two files used to align the clocks "
                   "(default: the first shaft column of each file)")
    g.add_argument("--no-header", action="store_true", help="the CSV files have no header line; see --columns")
    g.add_argument("--columns", metavar="A,B,C", help="names of the columns of a headerless PATH")
    g.add_argument("--second-columns", metavar="A,B,C", help="names of the columns of a headerless --second-file")


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


def _file(path: Path, names: list[str] | None, wanted: list[str], time_col: str | None,
          fs: float | None) -> tuple[Resampled, list[str]]:
    if not path.exists():
        raise InputDataError(f"{path}: no such file")
    header = column_names(path, names)
    cols = [c for c in dict.fromkeys(wanted) if c in header]
    if time_col and time_col not in header:
        raise InputDataError(f"{path}: no time column {time_col!r} (columns: {', '.join(header)})")
    table = read_table(path, cols + ([time_col] if time_col else []), names)
    if time_col:
        rec = resample_uniform(table.pop(time_col), table, str(path), time_col)
    else:
        if fs is None or fs <= 0:
            raise ConfigError(f"{path}: give --time-col NAME or --fs HZ (> 0)")
        n = len(next(iter(table.values()))) if table else 0
        rec = Resampled(np.arange(n) / fs, table, float(fs), 0.0, 0.0, False)
    return rec, header


def read_records(args: argparse.Namespace) -> DiagnoseData:
    """The generic CSV path: one or two files as the options say, as diagnosis data."""
    path = Path(args.path)
    sources = parse_shafts(args.speed_col, args.angle_col, args.gear_ratio)
    shaft_cols = [s.column for s in sources if s.kind != "geared"]
    align = tuple(args.align.split(":", 1)) if args.align else None
    if align and (len(align) != 2 or not all(align)):
        raise ConfigError(f"--align {args.align!r}: expected COL1:COL2")
    spec = RecordSpec(args.input_col, args.output_col, tuple(sources), align, SPEED_UNITS[args.speed_unit],
                      args.differentiate_output, args.sample_rate)
    wanted = [args.input_col, args.output_col] + shaft_cols + list(align[:1] if align else [])
    rec1, header1 = _file(path, _names(args, "columns"), wanted, args.time_col, args.fs)
    for need, opt in ((args.input_col, "--input-col"), (args.output_col, "--output-col")):
        if need not in rec1.columns:
            raise InputDataError(f"{path}: no column {need!r} ({opt}); columns: {', '.join(header1)}")
    notes: dict = {"file": {"path": str(path), **rec1.as_dict()}}
    rec2, source = None, str(path)
    if args.second_file:
        t2name = args.second_time_col or args.time_col
        if not (args.time_col and t2name):
            raise ConfigError("--second-file needs time columns in both files (--time-col, --second-time-col)")
        path2 = Path(args.second_file)
        rec2, _ = _file(path2, _names(args, "second-columns"), shaft_cols + list(align[1:] if align else []),
                        t2name, None)
        notes["second_file"] = {"path": str(path2), **rec2.as_dict()}
        source = f"{path} + {path2}"
    columns = set(rec1.columns) | set(rec2.columns if rec2 else ())
    missing = [c for c in shaft_cols if c not in columns]
    if missing:
        raise InputDataError(f"{source}: no column {missing[0]!r} (--speed-col/--angle-col)")
    return build_data(rec1, rec2, spec, source, notes)
