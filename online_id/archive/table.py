"""The archive's results table: its columns, and its rows from what ``identify`` and ``diagnose`` found.

One row per operating point of each identified recording (segment), with
the recording's columns repeated; a recording that could not be identified
is one row with its ``status`` and one-line ``error``.  Rows are plain
dicts (no I/O here; :mod:`online_id.archive.store` writes them to Parquet).

Uncertainties
-------------
``f0_std_hz`` and ``zeta_std`` are the model's own standard deviations of
the driveline pole at that operating point, propagated from the ARMAX fit's
parameter covariance (:func:`~online_id.analysis.poles.pole_std`, as the
live service computes them).  ``rec_f0_spread_hz`` and ``rec_zeta_spread``
are the spread of the pole over the recording's operating points (what
``identify --json`` gives as ``f0_std_hz`` and ``zeta_std``).  ``c_s_std``
and ``d_s_std`` are in the table but null: identify gives no uncertainty for
the shaft's stiffness and damping yet.
"""

from __future__ import annotations

import datetime as dt
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np

from online_id.analysis.poles import DRIVELINE, pole_std

if TYPE_CHECKING:  # the table is read (trend) without loading the estimation
    from online_id.estimation.identification import IdentificationResult

OK = "ok"
NO_DRIVELINE = "no_driveline"
ERROR = "error"
DUPLICATE = "duplicate"
STATUSES = (OK, NO_DRIVELINE, ERROR, DUPLICATE)


@dataclass(frozen=True)
class Column:
    """A column of the table: name, type (string, int64, float64, timestamp), unit, meaning."""

    name: str
    type: str
    unit: str
    doc: str


def _c(name: str, type_: str = "float64", unit: str = "", doc: str = "") -> Column:
    return Column(name, type_, unit, doc)


COLUMNS: tuple[Column, ...] = (
    _c("bench", "string", doc="the bench the recording is from"),
    _c("bench_source", "string", doc="where the bench came from: mapping, mdf header, path, directory"),
    _c("start_time", "timestamp", "UTC", "the recording's start"),
    _c("start_source", "string", doc="where the start time came from: mapping, mdf header, file name, unknown"),
    _c("path", "string", doc="the recording as given on the command line"),
    _c("sha256", "string", doc="SHA-256 of the file's content (a re-run skips what the table holds)"),
    _c("size_bytes", "int64", "B"),
    _c("mtime_ns", "int64", "ns", "the file's modification time when it was read"),
    _c("mode", "string", doc="identify or diagnose"),
    _c("segment", "int64", doc="part of a long recording (0 for a recording in one piece)"),
    _c("segments", "int64", doc="parts the recording was cut into"),
    _c("segment_t0_s", "float64", "s", "the part's start in recording time"),
    _c("segment_t1_s", "float64", "s", "the part's end in recording time"),
    _c("status", "string", doc="ok, no_driveline (no invariant pole pair found), error, duplicate"),
    _c("error", "string", doc="one line: why the recording gave no result (or the original of a duplicate)"),
    _c("op_index", "int64", doc="the operating point's index in its recording (segment)"),
    _c("op_time", "timestamp", "UTC", "the operating point's start: start_time + t_start_s"),
    _c("speed_rpm", "float64", "rpm", "engine speed of the operating point"),
    _c("load_nm", "float64", "Nm", "mean dyno torque of the operating point"),
    _c("t_start_s", "float64", "s"), _c("t_end_s", "float64", "s"),
    _c("f0_hz", "float64", "Hz", "driveline resonance at the operating point"),
    _c("f0_std_hz", "float64", "Hz", "its standard deviation from the fit's covariance"),
    _c("zeta", "float64", "1", "driveline damping ratio at the operating point"),
    _c("zeta_std", "float64", "1", "its standard deviation from the fit's covariance"),
    _c("rec_f0_hz", "float64", "Hz", "the recording's driveline resonance (median over its operating points)"),
    _c("rec_f0_spread_hz", "float64", "Hz", "its spread over the operating points"),
    _c("rec_zeta", "float64", "1"), _c("rec_zeta_spread", "float64", "1"),
    _c("n_points", "int64", doc="operating points at which the driveline pair was found"),
    _c("c_s", "float64", "Nm/rad", "shaft stiffness"),
    _c("c_s_std", "float64", "Nm/rad", "null: identify gives no uncertainty of c_s yet"),
    _c("d_s", "float64", "Nm s/rad", "shaft damping"),
    _c("d_s_std", "float64", "Nm s/rad", "null: identify gives no uncertainty of d_s yet"),
    _c("J1", "float64", "kg m^2"), _c("J2", "float64", "kg m^2"),
    _c("fpe", "float64", "(rad/s)^2", "the fit's final prediction error at the operating point"),
    _c("validation_V", "float64", "(rad/s)^2", "one-step loss on the held-out rest of the plateau"),
    _c("model_na", "int64", doc="the ARMAX order chosen for the recording"),
    _c("warnings", "string", doc="identify's warnings, joined by ' | '"),
    _c("effects", "string", doc="diagnose: the effects found, 'kind(param=value, ...)' joined by '; '"),
    _c("diagnosis", "string", doc="diagnose: its result line (the first effect, or 'no significant effect')"),
)
NAMES = tuple(c.name for c in COLUMNS)
SORT_KEY = ("bench", "start_time", "path", "segment", "op_index")
"""The table's order: the same whatever order the tasks completed in."""


def blank_row(**values: Any) -> dict[str, Any]:
    """A row with every column None, then ``values``."""
    unknown = set(values) - set(NAMES)
    if unknown:
        raise KeyError(f"not columns of the archive table: {', '.join(sorted(unknown))}")
    row: dict[str, Any] = dict.fromkeys(NAMES)
    row.update(values)
    return row


def _num(x: Any) -> float | None:
    return float(x) if x is not None and np.isfinite(x) else None


def identification_rows(base: dict[str, Any], result: "IdentificationResult",
                        load_nm: list[float]) -> list[dict[str, Any]]:
    """One row per operating point of ``result`` (``base``: the recording's columns; ``load_nm``: the mean
    dyno torque of each point)."""
    drive = result.driveline
    mode = result.sorting.driveline
    status = OK if drive is not None else NO_DRIVELINE
    start: dt.datetime | None = base.get("start_time")
    rows = []
    for i, (p, load) in enumerate(zip(result.points, load_nm)):
        pole = next((q for q in p.poles if q.cls == DRIVELINE), None)
        f_std = z_std = None
        if pole is not None and p.fit is not None:
            na = p.fit.orders.na
            f_std, z_std = pole_std(p.fit.A, pole.z, p.fit.covariance[:na, :na], p.dt)
        t0 = p.plateau.t_start_s
        rows.append(blank_row(
            **base, status=status, op_index=i,
            op_time=None if start is None else start + dt.timedelta(seconds=float(t0)),
            speed_rpm=float(p.speed_rpm), load_nm=_num(load), t_start_s=float(t0), t_end_s=float(p.plateau.t_end_s),
            f0_hz=_num(pole.f_hz) if pole else None, f0_std_hz=_num(f_std),
            zeta=_num(pole.zeta) if pole else None, zeta_std=_num(z_std),
            rec_f0_hz=_num(mode.f0_hz) if mode else None, rec_f0_spread_hz=_num(mode.f0_std_hz) if mode else None,
            rec_zeta=_num(mode.zeta) if mode else None, rec_zeta_spread=_num(mode.zeta_std) if mode else None,
            n_points=mode.n_points if mode else 0,
            c_s=_num(drive.c_s) if drive else None, d_s=_num(drive.d_s) if drive else None,
            J1=_num(drive.J1) if drive else None, J2=_num(drive.J2) if drive else None,
            fpe=_num(p.fit.fpe) if p.fit else None, validation_V=_num(p.validation_V),
            model_na=result.orders.na, warnings=" | ".join(result.warnings) or None,
        ))
    return rows


def effects_text(effects: list[dict[str, Any]]) -> str | None:
    """``kind(param=value, ...)`` of each effect (as in ``diagnose --json``'s ``effects``), joined by '; '."""
    def text(v: Any) -> str:
        if isinstance(v, float):
            return f"{v:.4g}"
        if isinstance(v, dict):
            return "{" + ", ".join(f"{k}: {text(x)}" for k, x in v.items()) + "}"
        return str(v)

    parts = [f"{e['kind']}(" + ", ".join(f"{k}={text(v)}" for k, v in (e.get("params") or {}).items()) + ")"
             for e in effects]
    return "; ".join(parts) or None


def sort_rows(rows: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """``rows`` in the table's order (:data:`SORT_KEY`; unknown start times last within a bench)."""
    def key(r: dict[str, Any]) -> tuple:
        t = r.get("start_time")
        return (r.get("bench") or "", t is None, t.timestamp() if t is not None else 0.0, r.get("path") or "",
                r.get("segment") or 0, -1 if r.get("op_index") is None else r["op_index"])

    return sorted(rows, key=key)
