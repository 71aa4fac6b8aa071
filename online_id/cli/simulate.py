"""``online-id simulate``: simulate a bench run, write the CSV and the truth JSON."""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import json
from pathlib import Path

from online_id.errors import ConfigError
from online_id.io.outfile import atomic_output, check_output
from online_id.progress import add_quiet_option, progress_for
from online_id.cli import command_help

def add_subparser(subparsers: argparse._SubParsersAction) -> None:
    """Register the ``simulate`` subcommand."""
    parser = subparsers.add_parser(
        "simulate",
        help=command_help("simulate"),
        description="Simulate a closed-loop bench run with PRBS test torque and write "
                    "the measured signals (CSV) and the simulation truth (JSON).",
    )
    parser.add_argument("--config", type=Path, metavar="SCENARIO.yaml",
                        help="scenario file (default: the built-in paper-like bench)")
    parser.add_argument("--seed", type=int, help="random seed (overrides the scenario)")
    parser.add_argument("--out", type=Path, default=Path("bench.csv"),
                        help="CSV file to write (default: bench.csv), or an MDF 4 signal recording (.mf4) with "
                             "the same channels")
    parser.add_argument("--truth", type=Path,
                        help="truth JSON file (default: <out stem>.truth.json next to --out)")
    parser.add_argument("--can-log", type=Path, metavar="FILE.{log,asc,blf,mf4}",
                        help="also write the measured signals as CAN input frames (online_id.dbc) "
                             "to this log; the format follows the suffix")
    parser.add_argument("--with-demand", action="store_true",
                        help="CSV: add the test-torque demand (the PRBS) as a column torque_demand_nm, as a "
                             "bench that records its demand would (diagnose then uses it)")
    add_quiet_option(parser)
    parser.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    """Run the subcommand; returns the exit status."""
    from online_id.bench.scenario import BenchScenario, load_scenario
    from online_id.bench.simulate import simulate_bench
    from online_id.offline.bench_files import write_can_log, write_csv

    scenario = load_scenario(args.config) if args.config else BenchScenario()
    if args.seed is not None:
        if args.seed < 0:
            raise ConfigError(f"Expected --seed >= 0, but got {args.seed}.")
        scenario = dataclasses.replace(scenario, seed=args.seed)
    out = Path(args.out)
    truth_path = Path(args.truth) if args.truth else out.with_name(f"{out.stem}.truth.json")
    if args.can_log is not None:
        from online_id.io.logformats import SUFFIXES

        if Path(args.can_log).suffix.lower() not in SUFFIXES:  # fail before simulating
            raise ConfigError(f"--can-log: expected a file ending in {', '.join(SUFFIXES)}, "
                              f"but got {str(args.can_log)!r}")
    for path, what in ((out, "bench CSV"), (truth_path, "truth file"), (args.can_log, "CAN log")):
        if path is not None:
            check_output(path, what)  # before simulating, not after
    with progress_for(args, "simulate") as progress:
        record = simulate_bench(scenario, progress=progress)
    # every output under a temporary name, all renamed only when all are written
    can_log = atomic_output(args.can_log) if args.can_log is not None else contextlib.nullcontext()
    with atomic_output(out) as out_tmp, atomic_output(truth_path) as truth_tmp, can_log as can_tmp:
        write_csv(record, out_tmp, demand=args.with_demand)
        truth_tmp.write_text(json.dumps(record.truth, indent=2) + "\n", encoding="utf-8")
        can_note = ""
        if can_tmp is not None:
            count = write_can_log(record, can_tmp)
            can_note = f" Wrote {count} CAN frames to {args.can_log}."
    t = record.truth
    print(
        f"Simulated {scenario.duration_s:.1f} s ({record.time_s.size} samples at "
        f"{scenario.fs_hz:g} Hz, seed {scenario.seed}) of a bench with J1 = {t['J1']:g}, "
        f"J2 = {t['J2']:g} kg m^2, c_s = {t['c_s']:g} Nm/rad, d_s = {t['d_s']:g} Nm s/rad: "
        f"first torsional mode f0 = {t['f0_hz']:.3f} Hz, zeta = {t['zeta']:.4f}. "
        f"Wrote {out} and {truth_path}.{can_note}"
    )
    return 0
