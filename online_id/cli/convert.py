"""``online-id convert IN.csv OUT.{log,asc,blf}``: a bench CSV as CAN input frames."""

from __future__ import annotations

import argparse
from pathlib import Path

from online_id.config import load_config
from online_id.errors import ConfigError
from online_id.io.canlog import SUFFIXES, write_log
from online_id.io.dbc import default_dbc_path, encode_inputs, load_dbc
from online_id.records import ROLES
from online_id.signals import read_bench_csv


def add_subparser(subparsers: argparse._SubParsersAction) -> None:
    """Register the ``convert`` subcommand."""
    p = subparsers.add_parser(
        "convert",
        help="convert a bench CSV into a CAN log of input frames",
        description="Encode a bench CSV (time, dyno speed, engine speed, dyno torque) into the input "
                    "frames of the DBC (DynoSpeed 0x101, EngineSpeed 0x102, DynoTorque 0x103 with "
                    "alive counters) and write a CAN log; the format follows the suffix: "
                    f"{', '.join(SUFFIXES)}.",
    )
    p.add_argument("path", metavar="IN.csv", help="bench CSV file")
    p.add_argument("out", metavar="OUT.{log,asc,blf}", help="CAN log to write")
    p.add_argument("--config", metavar="FILE", help="YAML config (CSV columns and units)")
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


def run(args: argparse.Namespace) -> int:
    """Run the subcommand; returns the exit status."""
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
