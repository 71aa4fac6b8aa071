"""``online-id evaluate-diagnose-rig`` and ``online-id simulate-rig``: the generic diagnosis on multi-shaft rigs.

``simulate-rig`` writes one randomised rig as two CSV files (drive side and
sensor side, each on its own clock) for ``online-id diagnose --second-file``;
``evaluate-diagnose-rig`` runs :func:`online_id.evaluation.diagnose_rigs.evaluate`.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

from dataclasses import replace

from typing import TYPE_CHECKING
from online_id.errors import ConfigError
from online_id.io.jsonout import dumps
from online_id.io.outfile import check_output
from online_id.progress import Progress, add_quiet_option
from online_id.cli import command_help

if TYPE_CHECKING:
    from online_id.bench.rig import RigRecording, RigSpec


def add_subparser(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser(
        "evaluate-diagnose-rig", help=command_help("evaluate-diagnose-rig"),
        description="Randomised rigs (motor, 2-3 gear stages, load motor; two records on drifting clocks): "
        "a rotation-order disturbance on each shaft in turn and clean rigs, through clock alignment and "
        "the generic diagnosis; reports order exact / shaft right rates and the false-effect rate.")
    p.add_argument("--cases", type=int, default=10, help="rigs per shaft position and clean rigs (default 10)")
    p.add_argument("--seed", type=int, default=1000, help="first seed (default 1000)")
    p.add_argument("--magnitude", type=float, default=0.3,
                   help="disturbance torque over the PRBS torque reflected to its shaft (default 0.3)")
    p.add_argument("--jobs", type=int, default=1, help="worker processes (default 1)")
    p.add_argument("--calibrate", action="store_true",
                   help="clean rigs only, baseline only: the largest order-grid line ratio per rig (sets the "
                   "line threshold; use seeds apart from the evaluation's); writes rig-calibration.json")
    p.add_argument("--out", metavar="DIR", required=True, help="write rig-evaluation.json here")
    add_quiet_option(p)
    p.set_defaults(func=run)
    s = subparsers.add_parser("simulate-rig", help=command_help("simulate-rig"),
                              description="Simulate a rig and write it as two files, DIR/drive.csv and "
                              "DIR/sensor.csv; prints the truth as JSON. Layout 'shafts' (the evaluation's "
                              "randomised rigs): drive.csv time_s, torque_demand_nm, motor_angle_<unit>; "
                              "sensor.csv time_s and the other shafts' angles, on a clock offset and drifting. "
                              "Layout 'loggers' (as two loggers of a measured rig write it): drive.csv time_s, "
                              "drive and load torque set-points and measurements; sensor.csv time_s, "
                              "encoder1..encoderK (cumulative angles at both ends of every compliant shaft) and "
                              "the shaft torques; one clock, the sensor logger starting about 1 s later; a "
                              "strong once-per-revolution torque on the motor shaft.")
    s.add_argument("--seed", type=int, default=1)
    s.add_argument("--layout", default="shafts", help="what the two files hold: shafts or loggers (default shafts)")
    s.add_argument("--angle-unit", metavar="UNIT",
                   help="unit the encoder angles are written in: deg, rad, rev or counts (the encoder's own "
                   "counts) (default: rad for shafts, deg for loggers)")
    s.add_argument("--speeds", type=int, choices=(1, 3), default=1,
                   help="loggers: one motor speed for 60 s, or three plateaus of 30 s (default 1)")
    s.add_argument("--plateau-s", type=float, metavar="S", help="length of each speed plateau (default 30; "
                   "loggers with one speed 60)")
    s.add_argument("--order-shaft", type=int, metavar="I", help="shafts: disturbed shaft (0 = motor); none = clean")
    s.add_argument("--magnitude", type=float, default=0.3)
    s.add_argument("--out", metavar="DIR", required=True)
    s.set_defaults(func=run_simulate)


def run(args: argparse.Namespace) -> int:
    from online_id.evaluation.diagnose_rigs import calibrate, evaluate

    if args.cases < 1 or args.jobs < 1:
        raise ConfigError(f"--cases and --jobs must be >= 1, got {args.cases} and {args.jobs}")
    check_output(args.out, "out", directory=True)
    t0 = time.perf_counter()
    with Progress("evaluate-diagnose-rig", quiet=args.quiet) as bar:
        def progress(i: int, n: int, r: dict) -> None:
            bar.count(i, n, f"{i}/{n} cases (seed {r['seed']}, {r['true_shaft'] or 'clean'})")

        if args.calibrate:
            summary = calibrate(args.cases, args.seed, args.jobs, Path(args.out), progress)
        else:
            summary = evaluate(args.cases, args.seed, args.magnitude, args.jobs, Path(args.out), progress)
    summary["wall_s"] = time.perf_counter() - t0
    print(dumps(summary, indent=1))
    return 0


def written_angles(spec: RigSpec, unit: str) -> tuple[RigSpec, str]:
    """``spec`` writing its encoder angles in ``unit`` (deg, rad, rev, countsN, or counts: the encoder's
    own), and the unit's full name."""
    from online_id.units import angle_factor

    unit = unit.strip().lower()
    if unit == "counts":
        unit = f"counts{spec.counts_per_rev}"
    scale = 1.0 / angle_factor(unit, "--angle-unit")
    return replace(spec, angle_scale=scale, angle_suffix="counts" if unit.startswith("counts") else unit), unit


def write_rig(out: Path, rec: RigRecording) -> tuple[Path, Path]:
    """The two records as ``out/drive.csv`` and ``out/sensor.csv`` (times to the ns, counts whole)."""
    from online_id.io.table_csv import write_csv_columns

    counts = rec.spec.angle_suffix == "counts"
    fmt = {n: "%.9f" if n == "time_s" else ("%.7f" if "torque" in n else ("%.0f" if counts else "%.10g"))
           for n in (*rec.drive, *rec.sensor)}
    out.mkdir(parents=True, exist_ok=True)
    files = out / "drive.csv", out / "sensor.csv"
    write_csv_columns(files[0], rec.drive, fmt)
    write_csv_columns(files[1], rec.sensor, fmt)
    return files


def run_simulate(args: argparse.Namespace) -> int:
    import numpy as np

    from online_id.bench.rig import LAYOUTS, encoder_shafts, loggers_rig, lowest_mode_hz, simulate_rig
    from online_id.evaluation.diagnose_rigs import rig_spec

    if args.layout not in LAYOUTS:
        raise ConfigError(f"--layout: expected one of {', '.join(LAYOUTS)}, but got {args.layout!r}")
    out = Path(args.out)
    check_output(args.out, "out", directory=True)
    if args.layout == "loggers":
        spec = loggers_rig(np.random.default_rng(args.seed), speeds=(1.0,) if args.speeds == 1 else (0.9, 1.0, 1.1))
    else:
        spec = rig_spec(args.seed, args.order_shaft, args.magnitude)
    if args.plateau_s is not None:
        if not args.plateau_s > 2.0:
            raise ConfigError(f"--plateau-s must be > 2, got {args.plateau_s}")
        spec = replace(spec, plateau_s=args.plateau_s)
    spec, unit = written_angles(spec, args.angle_unit or ("deg" if args.layout == "loggers" else "rad"))
    write_rig(out, simulate_rig(spec, args.seed))
    d = spec.disturbance
    truth = {"layout": spec.layout, "names": list(spec.names), "ratios": list(spec.ratios),
             "angle_unit": unit, "counts_per_rev": spec.counts_per_rev,
             "clock_offset_s": spec.clock_offset_s, "clock_drift_ppm": spec.clock_drift_ppm,
             "sensor_start_s": spec.sensor_start_s, "lowest_mode_hz": lowest_mode_hz(spec),
             "motor_speed_rpm": [w * 30.0 / np.pi / spec.speed_factors()[-1] for w in spec.load_speed_rad_s],
             "disturbance": None if d is None else {"shaft": spec.names[d.shaft], "order": d.order,
                                                    "amplitude_nm": d.amplitude_nm}}
    if spec.layout == "loggers":
        truth["encoders"] = {f"encoder{k}": {"shaft": name, "rate": rate}
                             for k, (name, rate) in enumerate(encoder_shafts(spec), 1)}
    print(dumps(truth, indent=1))
    return 0
