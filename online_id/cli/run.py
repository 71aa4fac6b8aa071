"""``online-id run --config FILE``: the streaming service (what systemd starts)."""

from __future__ import annotations

import argparse

from online_id.config import load_config
from online_id.cli import command_help
from online_id.cli.bus_options import add_bus_options, with_bus_options


def add_subparser(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser(
        "run",
        help=command_help("run"),
        description="Read engine speed, dyno speed and dyno torque frames, identify the driveline online "
        "and publish estimate, quality, status and alert frames. Stops cleanly on SIGTERM/SIGINT.",
    )
    p.add_argument("--config", metavar="FILE", help="YAML configuration (see deploy/config.yaml)")
    add_bus_options(p)
    p.add_argument("--max-seconds", type=float, metavar="S", help="stop after S seconds (tests)")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from online_id.service.live import run_service

    s = with_bus_options(load_config(args.config), args)
    return run_service(s, max_s=args.max_seconds)
