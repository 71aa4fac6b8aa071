"""``online-id convert``: bench signals as CAN input frames, or a CAN log as bench signals.

``IN.{csv,mf4} OUT.{log,asc,blf,mf4}`` encodes the samples of a bench CSV
or an MDF 4 signal recording as the DBC's input frames;
``IN.{log,asc,blf,mf4} OUT.{csv,mf4}`` decodes and assembles a recording
as the service would (see :mod:`online_id.ingest.benchlog`) and writes the default
bench columns (``time_s, dyno_speed_rpm, engine_speed_rpm, dyno_torque_nm``,
torque positive = braking), which every offline command reads without a
config.  An ``.mf4`` output holds the other kind than the input (frames from
signals, signals from frames) unless ``--mf4`` says which.
"""

from __future__ import annotations

import argparse

from online_id.io.logformats import SUFFIXES
from online_id.records import ROLES
from online_id.progress import add_quiet_option
from online_id.cli import command_help


def add_subparser(subparsers: argparse._SubParsersAction) -> None:
    """Register the ``convert`` subcommand."""
    p = subparsers.add_parser(
        "convert",
        help=command_help("convert"),
        description="Encode a bench CSV or MDF 4 (.mf4) signal recording (time, dyno speed, engine speed, "
                    "dyno torque) into the input "
                    "frames of the DBC (DynoSpeed 0x101, EngineSpeed 0x102, DynoTorque 0x103 with "
                    "alive counters) and write a CAN log; the format follows the suffix: "
                    f"{', '.join(SUFFIXES)}. Or the other way: decode a CAN log with the config's DBC "
                    "and mapping, assemble the samples as the service does, and write the longest "
                    "gap-free stretch as a bench CSV (time_s, dyno_speed_rpm, engine_speed_rpm, "
                    "dyno_torque_nm), or as an MDF 4 signal recording (.mf4) with those channels. A .mf4 "
                    "output holds CAN frames (MDF bus logging) when the input holds signals, and signals when "
                    "it holds frames, unless --mf4 says which.",
    )
    p.add_argument("path", metavar="IN", help="bench CSV or MDF 4 signal recording, or CAN log (.log, .asc, .blf, "
                   "MDF 4 bus logging .mf4)")
    p.add_argument("out", metavar="OUT", help="CAN log to write (from signals), or CSV / .mf4 to write (from a log)")
    p.add_argument("--mf4", choices=["can", "signals"],
                   help="what an OUT.mf4 holds: CAN frames (MDF bus logging) or signals (default: the other kind "
                        "than IN)")
    p.add_argument("--config", metavar="FILE", help="YAML config (CSV columns and units; DBC and mapping of a log)")
    p.add_argument("--dbc", metavar="FILE", help="DBC with the input frames (default: the packaged online_id.dbc)")
    add_frame_options(p)
    add_quiet_option(p)
    p.set_defaults(func=run)


def add_frame_options(p: argparse.ArgumentParser) -> None:
    """Options shared with ``simulate --can-log``: decimation, jitter, channel."""
    p.add_argument("--decimate", action="append", metavar="ROLE=K",
                   help=f"send only every K-th sample of ROLE ({', '.join(ROLES)}); repeatable")
    p.add_argument("--jitter-us", type=float, default=0.0, metavar="US",
                   help="delay each frame by a random 0..US microseconds (default 0)")
    p.add_argument("--channel", default="can0", help="channel name written to the log (default can0)")


def run(args: argparse.Namespace) -> int:
    """Run the subcommand; returns the exit status."""
    from online_id.offline.convert import run_convert

    return run_convert(args)
