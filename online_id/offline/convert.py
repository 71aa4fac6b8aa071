"""The work of ``online-id convert``: bench signals as CAN input frames, or a CAN log as bench signals."""

from __future__ import annotations

import argparse
import dataclasses
import sys
from pathlib import Path

from online_id.bench.simulate import RPM_PER_RAD_S, BenchRecord
from online_id.ingest.benchlog import is_can_log, read_bench, read_bench_log
from online_id.offline.bench_files import write_csv
from online_id.config import load_config
from online_id.errors import ConfigError
from online_id.io.canlog import write_log
from online_id.io.outfile import check_output
from online_id.io.dbc import encode_inputs, load_dbc
from online_id.records import ROLES
from online_id.progress import progress_for


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


def run_convert(args: argparse.Namespace) -> int:
    """``online-id convert`` with the parsed arguments ``args``."""
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
