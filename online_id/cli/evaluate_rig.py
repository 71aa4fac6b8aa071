"""``online-id evaluate-diagnose-rig`` and ``online-id simulate-rig``: the generic diagnosis on multi-shaft rigs.

``simulate-rig`` writes one randomised rig as two CSV files (drive side and
sensor side, each on its own clock) for ``online-id diagnose --second-file``;
``evaluate-diagnose-rig`` runs :func:`online_id.rig_evaluation.evaluate`.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

from online_id.errors import ConfigError
from online_id.io.outfile import check_output
from online_id.io.table_csv import write_csv_columns
from online_id.cli import command_help


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
    p.set_defaults(func=run)
    s = subparsers.add_parser("simulate-rig", help=command_help("simulate-rig"),
                              description="Simulate a rig and write DIR/drive.csv (time_s, torque_demand_nm, "
                              "motor_angle_rad) and DIR/sensor.csv (time_s, the other shafts' angles) on "
                              "two clocks; prints the truth as JSON.")
    s.add_argument("--seed", type=int, default=1)
    s.add_argument("--order-shaft", type=int, metavar="I", help="disturbed shaft (0 = motor); none = clean")
    s.add_argument("--magnitude", type=float, default=0.3)
    s.add_argument("--out", metavar="DIR", required=True)
    s.set_defaults(func=run_simulate)


def run(args: argparse.Namespace) -> int:
    from online_id.rig_evaluation import calibrate, evaluate

    if args.cases < 1 or args.jobs < 1:
        raise ConfigError(f"--cases and --jobs must be >= 1, got {args.cases} and {args.jobs}")
    check_output(args.out, "out", directory=True)
    t0 = time.perf_counter()
    if args.calibrate:
        summary = calibrate(args.cases, args.seed, args.jobs, Path(args.out))
    else:
        summary = evaluate(args.cases, args.seed, args.magnitude, args.jobs, Path(args.out))
    summary["wall_s"] = time.perf_counter() - t0
    print(json.dumps(summary, indent=1, default=float))
    return 0


def run_simulate(args: argparse.Namespace) -> int:
    from online_id.bench.rig import simulate_rig
    from online_id.rig_evaluation import rig_spec

    out = Path(args.out)
    check_output(args.out, "out", directory=True)
    out.mkdir(parents=True, exist_ok=True)
    spec = rig_spec(args.seed, args.order_shaft, args.magnitude)
    rec = simulate_rig(spec, args.seed)
    fmt = {n: "%.9f" if n == "time_s" else "%.7f" for n in (*rec.drive, *rec.sensor)}  # us, encoder counts
    write_csv_columns(out / "drive.csv", rec.drive, fmt)
    write_csv_columns(out / "sensor.csv", rec.sensor, fmt)
    d = spec.disturbance
    print(json.dumps({"names": list(spec.names), "ratios": list(spec.ratios),
                      "clock_offset_s": spec.clock_offset_s, "clock_drift_ppm": spec.clock_drift_ppm,
                      "disturbance": None if d is None else {"shaft": spec.names[d.shaft], "order": d.order,
                                                             "amplitude_nm": d.amplitude_nm}}, indent=1))
    return 0
