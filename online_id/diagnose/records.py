"""One or two records (each on a uniform grid of its own clock) -> :class:`DiagnoseData`.

No file I/O: the CLI reads the files (:mod:`online_id.cli.diagnose_records`)
and the rig evaluation passes simulated records; both end here.  A second
record is aligned on the first (:func:`online_id.diagnose.align.estimate_clock`
on a rotation signal both hold), interpolated at the first record's instants
and both are cut to their overlap; shafts come from
:mod:`online_id.diagnose.shafts`; the output may be differentiated and all
signals are decimated alike.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from online_id.diagnose.align import ClockFit, Resampled, estimate_clock
from online_id.diagnose.data import DiagnoseData
from online_id.diagnose.shafts import ShaftSource, resolve, speed_of
from online_id.errors import ConfigError, InputDataError
from online_id.estimation.preprocess import decimate, decimation_factor


@dataclass(frozen=True)
class RecordSpec:
    """Which columns are what (the generic path's options)."""

    input_col: str
    output_col: str
    shafts: tuple[ShaftSource, ...] = ()
    align: tuple[str, str] | None = None
    speed_unit_factor: float = 1.0
    differentiate_output: bool = False
    sample_rate_hz: float | None = None


def _rotation_speed(rec: Resampled, col: str, spec: RecordSpec) -> np.ndarray:
    kind = next((s.kind for s in spec.shafts if s.column == col), None)
    if kind is None:  # an --align column that is no shaft: monotonic means a cumulative angle
        d = np.diff(rec.columns[col])
        kind = "angle" if np.all(d >= 0) or np.all(d <= 0) else "speed"
    return speed_of(kind, rec.columns[col], rec.fs_hz, spec.speed_unit_factor)


def merge(rec1: Resampled, rec2: Resampled, spec: RecordSpec, source: str) -> tuple[dict, np.ndarray, dict]:
    """Record 2 on record 1's grid after aligning its clock; returns columns, times and the clock note."""
    shaft_cols = [s.column for s in spec.shafts if s.kind != "geared"]
    c1 = spec.align[0] if spec.align else next((c for c in shaft_cols if c in rec1.columns), None)
    c2 = spec.align[1] if spec.align else next((c for c in shaft_cols if c in rec2.columns), None)
    for c, which, rec in ((c1, "first", rec1), (c2, "second", rec2)):
        if c is None:
            raise ConfigError(f"{source}: the {which} file has no shaft column to align the clocks on; "
                              "give --align COL1:COL2")
        if c not in rec.columns:
            raise InputDataError(f"{source}: the {which} file has no column {c!r} (--align)")
    clock = estimate_clock(rec1.time_s, _rotation_speed(rec1, c1, spec), rec2.time_s,
                           _rotation_speed(rec2, c2, spec), rec1.fs_hz, source=source)
    columns, t = _overlap(rec1, rec2, clock, source)
    note = {**clock.as_dict(), "aligned_on": f"{c1} / {c2}", "overlap_s": float(t[-1] - t[0])}
    return columns, t, note


def _overlap(rec1: Resampled, rec2: Resampled, clock: ClockFit, source: str) -> tuple[dict, np.ndarray]:
    t2 = clock.to_clock2(rec1.time_s)
    idx = np.flatnonzero((t2 >= rec2.time_s[0]) & (t2 <= rec2.time_s[-1]))
    if idx.size < 100:
        raise InputDataError(f"{source}: the aligned records overlap in only {idx.size} samples")
    sl = slice(idx[0], idx[-1] + 1)
    out = {n: c[sl] for n, c in rec1.columns.items()}
    for n, c in rec2.columns.items():
        if n in out:
            raise InputDataError(f"{source}: column {n!r} is in both files; rename one")
        out[n] = np.interp(t2[sl], rec2.time_s, c)
    return out, rec1.time_s[sl]


def build_data(rec1: Resampled, rec2: Resampled | None, spec: RecordSpec, source: str,
               notes: dict | None = None) -> DiagnoseData:
    """The diagnosis data of one record, or of two aligned records (see module notes)."""
    notes = dict(notes or {})
    columns, fs = dict(rec1.columns), rec1.fs_hz
    if rec2 is not None:
        columns, _, notes["clock"] = merge(rec1, rec2, spec, source)
    for need, opt in ((spec.input_col, "--input-col"), (spec.output_col, "--output-col")):
        if need not in columns:
            raise InputDataError(f"{source}: no column {need!r} ({opt})")
    speeds, rates = resolve(list(spec.shafts), columns, fs, source, spec.speed_unit_factor)
    u, y = columns[spec.input_col], columns[spec.output_col]
    out_name = spec.output_col
    if spec.differentiate_output:
        y = np.gradient(y) * fs
        out_name = f"d{out_name}/dt"
    q = decimation_factor(fs, min(spec.sample_rate_hz, fs)) if spec.sample_rate_hz else 1
    dec = (lambda x: decimate(x, q)) if q > 1 else (lambda x: np.asarray(x, dtype=float))
    if q > 1:
        notes["decimated_to_hz"] = fs / q
    return DiagnoseData(dec(u), dec(y), fs / q, spec.input_col, out_name,
                        {n: dec(w) for n, w in speeds.items()}, source=source,
                        shaft_rates=rates if len(rates) >= 2 else {}, notes=notes)
