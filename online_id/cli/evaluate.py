"""``online-id evaluate``: false alarms per hour and detection delays on simulated benches."""

from __future__ import annotations

import argparse
from pathlib import Path

from online_id.cli import command_help
from online_id.cli.dask_options import add_dask_options


def add_subparser(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser(
        "evaluate",
        help=command_help("evaluate"),
        description="Simulate fault-free bench hours (random plants, operating points, noise, friction drift "
        "and undeclared effects) and runs with stiffness losses of 5/10/20 %% and damping changes of +-50 %%; "
        "feed each through the service pipeline and report false alarms per hour and the detection delay "
        "(median and worst). The full default (10 h, 4 plants) takes about 20 minutes on two cores.",
    )
    p.add_argument("--hours", type=float, default=None, help="fault-free hours to simulate (default 10)")
    p.add_argument("--fault-plants", type=int, default=None,
                   help="random plants on which every fault case runs (default 4)")
    p.add_argument("--seed", type=int, default=1, help="seed of the random plants and conditions (default 1)")
    p.add_argument("--jobs", type=int, default=None, help="parallel processes (default: all cores)")
    add_dask_options(p, "a case that fails is reported and left out")
    p.add_argument("--out", type=Path, metavar="DIR", help="write results.json, table.md and evaluation.png here")
    p.add_argument("--json", action="store_true", help="print the summary as one JSON document")
    p.add_argument("--families", default="c", metavar="LIST",
                   help="scenario families, comma-separated: a (first run of a fresh service, short plateaus), "
                   "b (a later run with the state of an earlier healthy run, at other operating points), "
                   "c (long dwells at one point); default c")
    p.add_argument("--cases", metavar="LIST",
                   help="only these fault cases, comma-separated labels (e.g. 'stiffness -10 %%,damping +50 %%')")
    p.add_argument("--plant-type", default="any", metavar="TYPE",
                   help="fault plants of this type only: any, backlash or 'no backlash' (default any; about 30 %% of "
                   "the random plants have backlash)")
    r = p.add_argument_group("what a bench adds (docs/evaluation.md; default: none of it, perfect samples)")
    r.add_argument("--crossings", action="store_true",
                   help="every fault-free run and every run of families a and b also visits an operating point "
                   "where an engine-order line lies within 25 %% of the resonance; report what the service did there")
    r.add_argument("--frame-loss", type=float, default=None, metavar="FRACTION",
                   help="feed CAN frames (DBC-encoded, decoded by the service's runtime) and drop this fraction")
    r.add_argument("--frame-jitter", type=float, default=None, metavar="SECONDS",
                   help="feed CAN frames, each received up to this much late (in order)")
    r.add_argument("--worker-lag", type=float, default=None, metavar="SECONDS",
                   help="feed CAN frames and adopt slow work (refits, checks, backlash test) this many stream "
                   "seconds after it was submitted, as the service's worker process does")
    r.add_argument("--bench-realism", action="store_true",
                   help="all of it: --crossings --frame-loss 0.01 --frame-jitter 0.002 --worker-lag 0.5 "
                   "(each can be given otherwise)")
    p.add_argument("--quick", action="store_true",
                   help="a bounded check: --hours 0.5 --fault-plants 2 --families a,b --jobs 2 unless given")
    p.add_argument("--from-results", type=Path, metavar="results.json",
                   help="no simulation: summarise, tabulate and plot the runs of an earlier results.json")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from online_id.offline.evaluate import run_evaluate

    return run_evaluate(args)
