"""One or two records (each on a uniform grid of its own clock) -> :class:`DiagnoseData`.

No file I/O: the CLI reads the files (:mod:`online_id.offline.diagnose_records`)
and the rig evaluation passes simulated records; both end here.  A second
record is aligned on the first (:func:`online_id.diagnose.align.estimate_clock`
on a rotation signal both hold), interpolated at the first record's instants
and both are cut to their overlap; shafts come from
:mod:`online_id.diagnose.shafts`; the output may be differentiated and all
signals are decimated alike through the causal data path
(:func:`data_path`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from online_id.diagnose.align import ClockFit, Resampled, estimate_clock
from online_id.diagnose.bench_data import CausalPath, causal_path, filter_decimate
from online_id.diagnose.data import DiagnoseData
from online_id.diagnose.shafts import ShaftSource, resolve, speed_of
from online_id.errors import ConfigError, InputDataError

LEAD_DECIMATED = 2
"""Input lead of the baseline on decimated data.  Band-limiting input and output alike keeps their
relation the plant's, but sampled: the band-limited response of a plant to an input that moves between
the samples reaches back about a sample before it (a sinc's precursor).  On clean decimated plants a lead
of 0 or 1 left a spurious one- or two-sample "sensor delay" and negative-lag input correlation; 2 did not
(``tests/test_diagnose.py``)."""


def data_path(fs_hz: float, target_hz: float | None) -> CausalPath:
    """The anti-alias filter and decimation of the generic path (:mod:`online_id.diagnose.bench_data`).

    Every signal passes the same linear-phase FIR (``16 q + 1`` taps) with its group delay removed from
    all of them alike, so delays and feedback stay at the lag where they are.
    """
    return causal_path(fs_hz, target_hz) if target_hz else CausalPath(float(fs_hz), 1, 1)


def decimate_alike(signals: dict[str, np.ndarray], path: CausalPath) -> dict[str, np.ndarray]:
    """Every signal through ``path``; the filter's start-up samples are dropped from all alike."""
    if path.q == 1:
        return {k: np.asarray(v, dtype=float) for k, v in signals.items()}
    skip = path.numtaps // path.q + 1
    return {k: filter_decimate(v, path)[skip:] for k, v in signals.items()}


LEAD_CENTRED = 1
"""Input lead of the baseline on a full-rate output differentiated by central differences
(``np.gradient``): ``(y[k+1] - y[k-1]) / 2T`` holds the response to the input of sample ``k`` itself,
so a baseline without that lag took the missing tap for a one-sample sensor delay on every clean
encoder record (``tests/test_diagnose.py``)."""


def path_note(path: CausalPath, centred: bool = False) -> dict:
    """The data path as reported (JSON ``recording.data_path``), with the input lead it implies."""
    return {**path.as_dict(), "input_lead": input_lead_for(path, centred)}


def input_lead_for(path: CausalPath, centred: bool = False) -> int:
    """Baseline input lead the data path implies.

    :data:`LEAD_DECIMATED` when decimated; at full rate :data:`LEAD_CENTRED` when the output is a
    central difference (``centred``), else 0.
    """
    if path.q > 1:
        return LEAD_DECIMATED
    return LEAD_CENTRED if centred else 0


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
    output_centred: bool = False
    """The output column was already differentiated by central differences (a layout's encoder)."""


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
        notes["output_sensor"] = out_name  # the sensor a delay is reported on: the column, not its derivative
        out_name = f"d{out_name}/dt"
    path = data_path(fs, spec.sample_rate_hz)
    notes["data_path"] = path_note(path, spec.differentiate_output or spec.output_centred)
    sig = decimate_alike({"u": u, "y": y, **{f"w:{n}": w for n, w in speeds.items()}}, path)
    return DiagnoseData(sig["u"], sig["y"], path.fs_hz, spec.input_col, out_name,
                        {n: sig[f"w:{n}"] for n in speeds}, source=source,
                        shaft_rates=rates if len(rates) >= 2 else {}, notes=notes)
