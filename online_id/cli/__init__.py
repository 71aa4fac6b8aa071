"""Command line: ``online-id SUBCOMMAND ...`` (one module per subcommand)."""

from __future__ import annotations

import os

# The matrices here are small (tens of parameters): multi-threaded BLAS only adds
# contention, so numpy is kept single-threaded unless the user asks otherwise.
for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import argparse  # noqa: E402
import sys  # noqa: E402

from online_id import __version__  # noqa: E402
from online_id.errors import OnlineIdError, printable  # noqa: E402


def build_parser() -> argparse.ArgumentParser:
    from online_id.cli import command, convert, demo, diagnose, evaluate, identify, replay, report_cmd, run, simulate
    from online_id.cli import evaluate_diagnose, evaluate_rig, fleet, monitor

    parser = argparse.ArgumentParser(
        prog="online-id",
        description="Online identification of engine test-bench drivelines.",
    )
    parser.add_argument("--version", action="version", version=f"online-id {__version__}")
    parser.add_argument("--debug", action="store_true", help="show tracebacks of errors")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    for module in (demo, run, replay, report_cmd, simulate, identify, diagnose, evaluate, evaluate_diagnose,
                   evaluate_rig, convert, command, fleet, monitor):
        module.add_subparser(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    """Entry point of the ``online-id`` console script; returns the exit status."""
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        return int(args.func(args) or 0)
    except OnlineIdError as err:
        if args.debug:
            raise
        print(f"error: {printable(str(err))}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        return 130
    except BrokenPipeError:
        # the reader went away (e.g. `| head`): not an error of ours
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())
        return 141
