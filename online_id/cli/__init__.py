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


SUBCOMMANDS: dict[str, tuple[str, str]] = {
    "demo": ("demo", "the service on a simulated bench, live on a virtual CAN bus (no hardware needed)"),
    "run": ("run", "run the streaming service on a CAN bus"),
    "replay": ("replay", "replay a CAN log (.log, .asc, .blf, .mf4) through the service pipeline"),
    "report": ("report_cmd", "plot estimates, tracks, baselines and alerts of a CAN log or a saved state"),
    "simulate": ("simulate", "simulate an engine test bench (dyno + motored engine) run"),
    "identify": ("identify", "identify the driveline from a bench CSV or MDF 4 file, or a CAN log"),
    "diagnose": ("diagnose", "find what the model lacks in the residual, add it, report the error"),
    "evaluate": ("evaluate", "evaluate wear and fault detection: false alarms per hour, detection delays"),
    "evaluate-diagnose": ("evaluate_diagnose", "measure the diagnosis on randomised benches (confusion matrix)"),
    "evaluate-diagnose-rig": ("evaluate_rig",
                              "diagnose randomised multi-shaft rigs (order on each shaft, clean)"),
    "simulate-rig": ("evaluate_rig", "write a multi-shaft rig as two CSV files (randomised, or as two loggers "
                                     "of a measured rig)"),
    "evaluate-diagnose-chain": ("evaluate_chain",
                                "judge the diagnosis on independently built drivetrains and rigs, run as a user"),
    "convert": ("convert", "convert a bench CSV or MDF 4 signal recording into a CAN log of input frames, or a "
                           "CAN log into bench signals"),
    "ack": ("command", "acknowledge the latched alerts (they clear and detection restarts)"),
    "relearn": ("command", "forget the learned baselines and learn them anew (after a planned shaft change)"),
    "fleet": ("fleet", "table of the benches publishing to an MQTT broker (needs the [mqtt] extra)"),
    "monitor": ("monitor", "watch the service's output frames and health live, decoded with the DBC"),
    "archive": ("archive", "identify or diagnose an archive of recordings on a Dask cluster into one table "
                           "(needs the [archive] extra)"),
    "trend": ("trend", "resonance and damping per bench against the date: baseline, drift per month, alerts"),
}
"""Subcommand -> (module in ``online_id.cli``, one-line help).  A module is imported only when its command
runs: ``online-id --help`` and a command that reads a CSV do not load python-can, cantools, asammdf or
matplotlib (seconds and tens of MB)."""


def command_help(name: str) -> str:
    """The one-line help of subcommand ``name`` (for its module's ``add_subparser``)."""
    return SUBCOMMANDS[name][1]


def build_parser(command: str | None = None) -> argparse.ArgumentParser:
    """The parser; only ``command``'s module is imported and gives its arguments (None: none, e.g. for --help)."""
    import importlib

    parser = argparse.ArgumentParser(
        prog="online-id",
        description="Online identification of engine test-bench drivelines.",
    )
    parser.add_argument("--version", action="version", version=f"online-id {__version__}")
    parser.add_argument("--debug", action="store_true", help="show tracebacks of errors")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    module = SUBCOMMANDS[command][0] if command in SUBCOMMANDS else None
    done: set[str] = set()
    for name, (mod, text) in SUBCOMMANDS.items():
        if mod == module:
            if mod not in done:  # one module may give several commands (ack, relearn)
                importlib.import_module(f"online_id.cli.{mod}").add_subparser(sub)
                done.add(mod)
        else:
            sub.add_parser(name, help=text)  # listed in --help; its arguments come with its module
    return parser


def _command_of(argv: list[str]) -> str | None:
    """The subcommand named in ``argv``: its first word that is not an option of ``online-id`` itself."""
    for word in argv:
        if not word.startswith("-"):
            return word
    return None


def main(argv: list[str] | None = None) -> int:
    """Entry point of the ``online-id`` console script; returns the exit status.

    SIGINT and SIGTERM at any moment, the import of the command's modules included, end it with one line,
    nothing left behind and status 130 or 143; the service (``run``) with 0, as from its loop
    (:mod:`online_id.interrupt`).
    """
    from online_id import interrupt

    process_ends = argv is None  # the console script: a signal after the work is done changes nothing
    argv = sys.argv[1:] if argv is None else list(argv)
    try:
        status = _run(argv, process_ends)
    except BaseException as err:  # noqa: BLE001 -- only what a stop caused; anything else is raised again
        signum = interrupt.stopped_by()
        if signum is None or isinstance(err, SystemExit):
            raise
        # the signal cut an extension module's import or a library short and its own error came out
        status = _stopped(argv, interrupt.Interrupted(signum))
    if process_ends and interrupt.stopped_by() is not None:
        interrupt.end_process(status)
    return status


def _stopped(argv: list[str], err) -> int:
    """One line for a stop by ``err`` (an :class:`~online_id.interrupt.Interrupted`) and the status."""
    if _command_of(argv) == "run":  # the service: a stop is its normal end, in its start-up too
        print(f"online-id: stopped by {err.name} during start-up", file=sys.stderr)
        return 0
    print(f"interrupted by {err.name}", file=sys.stderr)
    return err.exit_status


def _run(argv: list[str], process_ends: bool) -> int:
    from online_id.interrupt import Interrupted, interruptible

    args = None
    with interruptible(process_ends):
        try:
            parser = build_parser(_command_of(argv))
            args = parser.parse_args(argv)
            return int(args.func(args) or 0)
        except OnlineIdError as err:
            if args is not None and args.debug:
                raise
            print(f"error: {printable(str(err))}", file=sys.stderr)
            return 2
        except Interrupted as err:
            return _stopped(argv, err)
        except KeyboardInterrupt:
            print("interrupted", file=sys.stderr)
            return 130
        except BrokenPipeError:
            # the reader went away (e.g. `| head`): not an error of ours
            devnull = os.open(os.devnull, os.O_WRONLY)
            os.dup2(devnull, sys.stdout.fileno())
            return 141
