"""``online-id convert``: a bench CSV as CAN input frames, or a CAN log as a bench CSV.

``IN.csv OUT.{log,asc,blf}`` encodes the samples as the DBC's input frames;
``IN.{log,asc,blf} OUT.csv`` decodes and assembles a recording as the service
would (see :mod:`online_id.benchlog`) and writes the default bench columns
(``time_s, dyno_speed_rpm, engine_speed_rpm, dyno_torque_nm``, torque
positive = braking), which every offline command reads without a config.
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
from pathlib import Path

from online_id.bench.simulate import RPM_PER_RAD_S, BenchRecord
from online_id.benchlog import is_can_log, read_bench_log
from online_id.cli.simulate import write_csv
from online_id.config import load_config
from online_id.errors import ConfigError
from online_id.io.canlog import SUFFIXES, write_log
from online_id.io.outfile import check_output
from online_id.io.dbc import default_dbc_path, encode_inputs, load_dbc
from online_id.records import ROLES
from online_id.report import TerminalProgress
from online_id.signals import read_bench_csv


def add_subparser(subparsers: argparse._SubParsersAction) -> None:
    """Register the ``convert`` subcommand."""
    p = subparsers.add_parser(
        "convert",
        help="convert a bench CSV into a CAN log of input frames, or a CAN log into a bench CSV",
        description="Encode a bench CSV (time, dyno speed, engine speed, dyno torque) into the input "
                    "frames of the DBC (DynoSpeed 0x101, EngineSpeed 0x102, DynoTorque 0x103 with "
                    "alive counters) and write a CAN log; the format follows the suffix: "
                    f"{', '.join(SUFFIXES)}. Or the other way: decode a CAN log with the config's DBC "
                    "and mapping, assemble the samples as the service does, and write the longest "
                    "gap-free stretch as a bench CSV (time_s, dyno_speed_rpm, engine_speed_rpm, "
                    "dyno_torque_nm).",
    )
    p.add_argument("path", metavar="IN", help="bench CSV file, or CAN log (.log, .asc, .blf)")
    p.add_argument("out", metavar="OUT", help="CAN log to write (from a CSV), or CSV to write (from a log)")
    p.add_argument("--config", metavar="FILE", help="YAML config (CSV columns and units; DBC and mapping of a log)")
    p.add_argument("--dbc", metavar="FILE", help=f"DBC with the input frames (default: {default_dbc_path().name})")
    add_frame_options(p)
    p.set_defaults(func=run)


def add_frame_options(p: argparse.ArgumentParser) -> None:
    """Options shared with ``simulate --can-log``: decimation, jitter, channel."""
    p.add_argument("--decimate", action="append", metavar="ROLE=K",
                   help=f"send only every K-th sample of ROLE ({', '.join(ROLES)}); repeatable")
    p.add_argument("--jitter-us", type=float, default=0.0, metavar="US",
                   help="delay each frame by a random 0..US microseconds (default 0)")
    p.add_argument("--channel", default="can0", help="channel name written to the log (default can0)")


def decimation_from_args(items: list[str] | None) -> dict[str, int]:
    """``["dyno_torque=2"]`` -> ``{"dyno_torque": 2}`` with errors naming the option."""
    out: dict[str, int] = {}
    for item in items or ():
        role, _, k = item.partition("=")
        role = role.strip()
        try:
            factor = int(k)
        except ValueError:
            factor = 0
        if role not in ROLES or factor < 1:
            raise ConfigError(f"--decimate: expected ROLE=K with ROLE in {', '.join(ROLES)} and "
                              f"an integer K >= 1, but got {item!r}")
        out[role] = factor
    return out


def jitter_from_args(jitter_us: float) -> float:
    if not jitter_us >= 0.0:
        raise ConfigError(f"--jitter-us: expected a number >= 0, but got {jitter_us!r}")
    return jitter_us * 1e-6


def log_to_csv(args: argparse.Namespace) -> int:
    """``IN.{log,asc,blf} OUT.csv``."""
    if Path(args.out).suffix.lower() != ".csv":
        raise ConfigError(f"{args.out}: a CAN log converts to a bench CSV; expected OUT with suffix .csv")
    if args.decimate or args.jitter_us:
        raise ConfigError("--decimate and --jitter-us apply to writing frames (IN.csv OUT.log), not to reading a log")
    settings = load_config(args.config)
    if args.dbc is not None:
        settings = dataclasses.replace(settings, dbc=args.dbc)
    progress = TerminalProgress("convert")
    try:
        log = read_bench_log(args.path, settings, progress)
    finally:
        progress.close()
    d = log.data
    write_csv(BenchRecord(d.time_s, d.dyno_speed_rad_s * RPM_PER_RAD_S, d.engine_speed_rad_s * RPM_PER_RAD_S,
                          d.dyno_torque_nm), Path(args.out))
    note = log.note()
    if note:
        print(note, file=sys.stderr)
    print(f"Wrote {len(d)} samples ({d.time_s[-1] - d.time_s[0]:.3f} s) from {log.frames} frames of {args.path} "
          f"to {args.out}; {log.counters.bad_frames} frames unusable, {log.unknown_frames} of other IDs.")
    return 0


def run(args: argparse.Namespace) -> int:
    """Run the subcommand; returns the exit status."""
    check_output(args.out)  # before the work, not after it
    if is_can_log(args.path):
        return log_to_csv(args)
    settings = load_config(args.config)
    decimation = decimation_from_args(args.decimate)
    jitter_s = jitter_from_args(args.jitter_us)
    db = load_dbc(args.dbc)
    data = read_bench_csv(args.path, settings.columns, settings.units)
    frames = encode_inputs(
        data.time_s, data.dyno_speed_rpm, data.engine_speed_rpm, data.dyno_torque_nm,
        db=db, decimation=decimation, jitter_s=jitter_s, source=str(args.path),
    )
    count = write_log(Path(args.out), frames, channel=args.channel)
    print(f"Wrote {count} frames ({len(data)} samples, {data.time_s[-1] - data.time_s[0]:.3f} s) "
          f"from {args.path} to {args.out}.")
    return 0
