"""``online-id convert``: bench signals as CAN input frames, or a CAN log as bench signals.

``IN.{csv,mf4} OUT.{log,asc,blf,mf4}`` encodes the samples of a bench CSV
or an MDF 4 signal recording as the DBC's input frames;
``IN.{log,asc,blf,mf4} OUT.{csv,mf4}`` decodes and assembles a recording
as the service would (see :mod:`online_id.benchlog`) and writes the default
bench columns (``time_s, dyno_speed_rpm, engine_speed_rpm, dyno_torque_nm``,
torque positive = braking), which every offline command reads without a
config.  An ``.mf4`` output holds the other kind than the input (frames from
signals, signals from frames) unless ``--mf4`` says which.
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
from pathlib import Path

from online_id.bench.simulate import RPM_PER_RAD_S, BenchRecord
from online_id.benchlog import is_can_log, read_bench, read_bench_log
from online_id.cli.simulate import write_csv
from online_id.config import load_config
from online_id.errors import ConfigError
from online_id.io.canlog import SUFFIXES, write_log
from online_id.io.outfile import check_output
from online_id.io.dbc import default_dbc_path, encode_inputs, load_dbc
from online_id.records import ROLES
from online_id.progress import add_quiet_option, progress_for
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
    p.add_argument("--dbc", metavar="FILE", help=f"DBC with the input frames (default: {default_dbc_path().name})")
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


def _writes_signals(args: argparse.Namespace, from_frames: bool) -> bool:
    """True when OUT gets bench signals (CSV, or a signal .mf4), False when it gets CAN frames."""
    suffix = Path(args.out).suffix.lower()
    if args.mf4 is not None and suffix != ".mf4":
        raise ConfigError(f"--mf4 applies to an OUT ending in .mf4, but got {args.out}")
    if suffix == ".mf4":
        return args.mf4 == "signals" if args.mf4 else from_frames
    if suffix == ".csv":
        return True
    if from_frames:
        raise ConfigError(f"{args.out}: a CAN log converts to a bench CSV or .mf4 signal recording; expected OUT "
                          f"with suffix .csv or .mf4")
    return False


def write_signals(d, out: str) -> None:
    """Bench data (SI) as the default bench columns, CSV or ``.mf4`` by the suffix."""
    write_csv(BenchRecord(d.time_s, d.dyno_speed_rad_s * RPM_PER_RAD_S, d.engine_speed_rad_s * RPM_PER_RAD_S,
                          d.dyno_torque_nm), Path(out))


def log_to_csv(args: argparse.Namespace) -> int:
    """``IN.{log,asc,blf,mf4} OUT.{csv,mf4}``."""
    _writes_signals(args, from_frames=True)
    if args.decimate or args.jitter_us:
        raise ConfigError("--decimate and --jitter-us apply to writing frames (IN.csv OUT.log), not to reading a log")
    settings = load_config(args.config)
    if args.dbc is not None:
        settings = dataclasses.replace(settings, dbc=args.dbc)
    with progress_for(args, "convert", "frames") as progress:
        log = read_bench_log(args.path, settings, progress)
    d = log.data
    write_signals(d, args.out)
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
    if _writes_signals(args, from_frames=False):  # signals to signals: CSV <-> .mf4
        data = read_bench(args.path, settings, lambda text: print(text, file=sys.stderr))
        write_signals(data, args.out)
        print(f"Wrote {len(data)} samples ({data.time_s[-1] - data.time_s[0]:.3f} s) from {args.path} to {args.out}.")
        return 0
    decimation = decimation_from_args(args.decimate)
    jitter_s = jitter_from_args(args.jitter_us)
    db = load_dbc(args.dbc)
    data = read_bench(args.path, settings, lambda text: print(text, file=sys.stderr))
    frames = encode_inputs(
        data.time_s, data.dyno_speed_rpm, data.engine_speed_rpm, data.dyno_torque_nm,
        db=db, decimation=decimation, jitter_s=jitter_s, source=str(args.path),
    )
    count = write_log(Path(args.out), frames, channel=args.channel)
    print(f"Wrote {count} frames ({len(data)} samples, {data.time_s[-1] - data.time_s[0]:.3f} s) "
          f"from {args.path} to {args.out}.")
    return 0
