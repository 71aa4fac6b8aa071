"""``online-id demo``: the service on a simulated bench, live, on a virtual CAN bus.

No hardware needed.  The bench simulator produces a record with known truth
(the seed paper's experiment: unfired engine, dyno speed control, PRBS test
torque, four operating points).  Its samples are encoded into CAN frames
with the DBC and sent on a python-can virtual bus, paced in (accelerated)
real time; the streaming service runs on that bus exactly as it would on
``can0``; a consumer on the same bus decodes the published frames (checking
their CRC) and shows the estimate converging, then a summary against the
truth.  ``--offline`` runs the batch identification of the paper instead.
"""

from __future__ import annotations

import argparse

from online_id.cli import command_help


def add_subparser(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser(
        "demo",
        help=command_help("demo"),
        description=__doc__.split("\n\n")[0],
    )
    p.add_argument("--seed", type=int, default=0, help="simulation seed (default 0)")
    p.add_argument("--out", metavar="DIR", default="demo-output", help="where to write CSV, truth, JSON and plot")
    p.add_argument("--speed", type=float, default=5.0, help="how many times faster than real time (default 5)")
    p.add_argument("--offline", action="store_true",
                   help="batch identification per operating point (the paper's Fig. 5/6) instead of the service")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    if args.speed <= 0:
        from online_id.errors import ConfigError

        raise ConfigError(f"--speed: expected a number > 0, got {args.speed!r}")
    from online_id.io.outfile import check_output

    check_output(args.out, "demo output", directory=True)  # before the demo, not after it
    if not args.offline:
        from online_id.cli.demo_live import run_live

        return run_live(args)
    from online_id.offline.demo import run_offline

    return run_offline(args)
