"""A chain case written as a user's files, the truth beside them, and the command line a user types.

The command lines are built from a semantic description of the layout (which file and column holds
the input, the output, each shaft's angle and its unit, whether the loggers share a clock), with the
documented option names of ``online-id diagnose``; nothing here knows how the diagnosis works.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from online_id.evaluation.chain_world import Column

RIG_SETTINGS = ("--na", "auto", "--nc", "8", "--sim-horizon", "0.1")
"""Model settings of a rig's command: those of the documented rig example, at the recording's own rate."""


@dataclass(frozen=True)
class AngleColumn:
    """A cumulative angle column, the shaft it turns with and its unit (``deg``, ``rad``, ``rev``, ``countsN``)."""

    name: str
    shaft: str
    unit: str


@dataclass(frozen=True)
class RigDescription:
    """What a user knows of a two-logger rig recording (see module notes)."""

    first_file: str
    time_col: str
    input_col: str
    output_col: str
    second_file: str | None = None
    second_time_col: str | None = None
    angles: tuple[AngleColumn, ...] = ()
    same_clock: bool = False
    clock_offset_s: float | None = None
    differentiate_output: bool = False
    torques: tuple[tuple[str, str], ...] = ()
    """``(column, shaft)``: a torque acting on that shaft (the load motor's measured torque)."""
    settings: tuple[str, ...] = field(default=RIG_SETTINGS)


def rig_command(d: RigDescription) -> list[str]:
    """``diagnose ...`` arguments (without the program name) for a rig described by ``d``."""
    argv = ["diagnose", d.first_file]
    if d.second_file:
        argv += ["--second-file", d.second_file]
    argv += ["--time-col", d.time_col]
    if d.second_file and d.second_time_col:
        argv += ["--second-time-col", d.second_time_col]
    argv += ["--input-col", d.input_col, "--output-col", d.output_col]
    for a in d.angles:
        argv += ["--angle-col", f"{a.name}:{a.shaft}:{a.unit}"]
    for col, shaft in d.torques:
        argv += ["--torque-col", f"{col}:{shaft}"]
    if d.same_clock:
        argv.append("--same-clock")
        if d.clock_offset_s is not None:
            argv += ["--clock-offset-s", repr(float(d.clock_offset_s))]
    if d.differentiate_output:
        argv.append("--differentiate-output")
    return argv + list(d.settings) + ["--json"]


@dataclass(frozen=True)
class BenchDescription:
    """What a user knows of a bench CSV: the file, its config, the engine's pulses per revolution if given on
    the command line, and a recorded test-torque demand column."""

    csv: str
    config: str
    pulses_per_rev: float | None = None
    demand_col: str | None = None


def bench_command(d: BenchDescription) -> list[str]:
    """``diagnose ...`` arguments (without the program name) for a bench CSV described by ``d``."""
    argv = ["diagnose", d.csv, "--config", d.config]
    if d.pulses_per_rev is not None:
        argv += ["--pulses-per-rev", f"{d.pulses_per_rev:g}"]
    if d.demand_col:
        argv += ["--demand-col", d.demand_col]
    return argv + ["--json"]


def describe(spec: dict) -> BenchDescription | RigDescription:
    """The user's description of a case's files."""
    f = spec["files"]
    if f["layout"] == "bench":
        ppr = spec["engine"]["cylinders"] / 2
        return BenchDescription(f["csv"], f["config"], ppr if f["pulses_per_rev_in"] == "option" else None,
                                f["demand"])
    load = next((e["shaft"] for e in f["encoders"] if e["element"] == (spec.get("control") or {}).get("element")), None)
    torques = ((f["drive_columns"]["load_meas"], load),) if load and "load_meas" in f["drive_columns"] else ()
    return RigDescription(first_file=f["drive"], second_file=f["sensor"], time_col=f["drive_time"],
                          second_time_col=f["sensor_time"], input_col=f["drive_columns"][f["input"]],
                          output_col=f["output_column"],
                          angles=tuple(AngleColumn(e["column"], e["shaft"], e["unit"]) for e in f["encoders"]),
                          same_clock=True, differentiate_output=True, torques=torques)


def command(spec: dict) -> list[str]:
    d = describe(spec)
    return bench_command(d) if isinstance(d, BenchDescription) else rig_command(d)


def bench_config(spec: dict) -> str:
    """The config YAML that names a bench CSV's columns and units (JSON-quoted strings are YAML)."""
    f = spec["files"]
    c = f["columns"]
    q = json.dumps
    lines = ["# bench columns and units of bench.csv",
             "columns: {" + ", ".join(f"{k}: {q(c[k])}" for k in ("time", "dyno_speed", "engine_speed",
                                                                   "dyno_torque")) + "}",
             f"units: {{time: {f['time_unit']}, speed: {q(f['speed_unit'])}, torque_sign: {f['torque_sign']}}}"]
    if f["pulses_per_rev_in"] == "config":
        lines.append(f"model: {{pulses_per_rev: {spec['engine']['cylinders'] / 2:g}}}")
    return "\n".join(lines) + "\n"


def write_csv(path: Path, columns: list[Column]) -> None:
    """A CSV with a header line, one column per :class:`Column` in its format."""
    data = np.column_stack([c.values for c in columns])
    np.savetxt(path, data, fmt=[c.fmt for c in columns], delimiter=",",
               header=",".join(c.name for c in columns), comments="")


def strict_json(x, **kwargs) -> str:
    """``x`` as strict JSON (numpy numbers as Python's, NaN and Infinity as null); this room writes no
    JSON through ``online_id.io`` (it judges the tool from outside)."""
    return json.dumps(_plain(x), allow_nan=False, **kwargs)


def _plain(x):
    if isinstance(x, dict):
        return {str(k): _plain(v) for k, v in x.items()}
    if isinstance(x, (list, tuple, np.ndarray)):
        return [_plain(v) for v in x]
    if isinstance(x, (np.floating, float)):
        return float(x) if np.isfinite(x) else None
    if isinstance(x, (np.integer,)):
        return int(x)
    if isinstance(x, np.bool_):
        return bool(x)
    return x


def write_case(spec: dict, files: dict[str, list[Column]], directory: Path, extra: dict | None = None) -> list[str]:
    """Write the case's data files, its config (bench) and ``truth.json`` into ``directory``; return the
    ``diagnose`` arguments to run there."""
    directory.mkdir(parents=True, exist_ok=True)
    for name, columns in files.items():
        write_csv(directory / name, columns)
    if spec["layout"] == "bench":
        (directory / spec["files"]["config"]).write_text(bench_config(spec), encoding="utf-8")
    argv = command(spec)
    truth = dict(spec, command=["online-id"] + argv, rows={k: int(len(v[0].values)) for k, v in files.items()},
                 **(extra or {}))
    (directory / "truth.json").write_text(strict_json(truth, indent=1) + "\n",
                                          encoding="utf-8")
    return argv
