"""``online-id report LOG_OR_STATE --out DIR``: plots and a summary of a replayed log or a saved state
(the work is :mod:`online_id.offline.report`)."""

from __future__ import annotations

import argparse
from pathlib import Path

from online_id.cli import command_help
from online_id.errors import InputDataError
from online_id.io.outfile import check_output


def add_subparser(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser(
        "report",
        help=command_help("report"),
        description="Replay a CAN log (.log, .asc, .blf) through the service pipeline, or read a state file "
        "of the service (.json), and write to DIR: frequency and damping against engine speed with the "
        "learned baselines (frequency_vs_speed.png, damping_vs_speed.png), f0 and zeta over time with "
        "baselines and alerts (tracks_over_time.png), report.json and report.md.",
    )
    p.add_argument("source", metavar="LOG_OR_STATE", help="CAN log (.log, .asc, .blf) or state file (.json)")
    p.add_argument("--out", metavar="DIR", required=True, help="directory for the figures and the summary")
    p.add_argument("--config", metavar="FILE", help="YAML configuration (DBC, mapping, model, detection)")
    p.add_argument("--resid", action="store_true",
                   help="(a CAN log) also identify the log per operating point as identify does and test the "
                        "residuals as MATLAB's resid: resid.png and a section in report.md and report.json")
    p.add_argument("--out-mf4", metavar="FILE.mf4",
                   help="also write the results as MDF 4 channels with units on the recording's time base: of a log, "
                        "the estimates, quality, state and alerts (as replay --out-mf4); of a state file, the alerts "
                        "and the pole tracks' points")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from online_id.offline.report import identify_residuals, load_source, write_report, write_results_mf4

    check_output(args.out, "report", directory=True)  # before the work, not after it
    if args.out_mf4:
        check_output(args.out_mf4, "results file")
    data = load_source(Path(args.source), args.config)
    if args.resid:
        if data.kind != "can_log":
            raise InputDataError(f"{args.source}: --resid needs a CAN log (a state file holds no samples to test)")
        identify_residuals(data, args.config)
    for path in write_report(data, Path(args.out)):
        print(f"wrote {path}")
    if args.out_mf4:
        write_results_mf4(data, args.out_mf4)
        print(f"wrote {args.out_mf4}")
    return 0
