"""``online-id replay LOG``: a CAN log through exactly the pipeline of the live service."""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

from online_id.config import load_config
from online_id.errors import EstimationError, InputDataError
from online_id.io.canlog import count_frames, read_log
from online_id.io.outfile import check_output
from online_id.io.statefile import load_state, save_state
from online_id.progress import Progress, add_quiet_option, progress_for
from online_id.records import FrameFault
from online_id.report import fmt
from online_id.runtime import Runtime
from online_id.cli import command_help


def add_subparser(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser(
        "replay",
        help=command_help("replay"),
        description="Feed a candump .log, .asc, .blf or MDF 4 bus logging .mf4 file through the same decoder, assembler, estimator "
        "and encoder as the live service, as fast as possible (or in real time), and report the final "
        "estimate, the status changes and the alerts (times in seconds from the start of the log).",
    )
    p.add_argument("log", metavar="LOG", help="CAN log file (.log, .asc, .blf or MDF 4 bus logging .mf4)")
    p.add_argument("--config", metavar="FILE", help="YAML configuration (DBC, mapping, model)")
    p.add_argument("--realtime", action="store_true", help="pace the frames by their timestamps")
    p.add_argument("--state", metavar="DIR", type=Path,
                   help="load the service's state (baselines, latched alarms) from DIR/online-id-state.json at "
                   "start and save it there at the end, as online-id run keeps it (replay a day of logs one "
                   "after another)")
    p.add_argument("--json", action="store_true", help="print one JSON document")
    add_quiet_option(p)
    p.set_defaults(func=run)


def state_file(directory: Path) -> Path:
    """The state file in ``directory`` (the name the live service uses)."""
    from online_id.service import STATE_FILE

    if directory.exists() and not directory.is_dir():
        raise InputDataError(f"{directory}: --state expects a directory, but this is a file")
    check_output(directory, "state", directory=True)  # before the replay, not after it
    return directory / STATE_FILE


def restore(runtime: Runtime, path: Path) -> bool:
    """Load a saved state as an earlier run's into ``runtime``'s pipeline; False if there is none yet."""
    state = load_state(path)
    if state is None:
        return False
    try:
        runtime.pipeline.load_state(state, new_run=True)
    except (EstimationError, KeyError, TypeError, ValueError) as err:
        raise InputDataError(f"{path}: not a state of this version of online-id ({err})") from None
    return True


def keep(runtime: Runtime, path: Path) -> None:
    """Save the pipeline's state to ``path`` (atomically); an unwritable place is a one-line error."""
    try:
        save_state(path, runtime.pipeline.get_state())
    except OSError as err:
        raise InputDataError(f"{path}: cannot save the state ({err.strerror or err})") from None


def replay(path: str, runtime: Runtime, realtime: bool = False, progress: Progress | None = None,
           require_match: bool = False) -> int:
    """Feed every frame of the log; returns the number of frames published.

    Raises :class:`InputDataError` when the log holds no frame, or (with
    ``require_match``) none of an ID the config maps; a log that ends early
    is used up to the cut, with a warning on stderr.
    """
    published = 0
    t_first = None
    wall0 = time.monotonic()
    cut: list[str] = []
    total = count_frames(path) if progress is not None and progress.enabled else None
    ids: set[int] = set()
    for k, (t_s, ident, data, is_ext, is_err) in enumerate(read_log(path, cut.append)):
        ids.add(ident)
        if t_first is None:
            t_first = t_s
        if realtime:
            delay = (t_s - t_first) - (time.monotonic() - wall0)
            if delay > 0:
                time.sleep(delay)
        published += len(runtime.on_frame(t_s, ident, data, is_ext, is_err))
        if progress is not None and k % 2000 == 0:
            progress.count(k, total, f"t = {t_s - t_first:.1f} s")
    if t_first is None:
        raise InputDataError(f"{path}: no CAN frames in the log" + (" (it ends early)" if cut else ""))
    if require_match and runtime.pipeline.counters.faults[FrameFault.UNKNOWN_ID] == runtime.frames_in:
        raise InputDataError(no_match(path, runtime, ids))
    for text in cut:
        print(text, file=sys.stderr)
    published += len(runtime.tick(runtime.pipeline.t_s))
    return published


def no_match(path: str, runtime: Runtime, ids: set[int]) -> str:
    """The error for a log none of whose frames has an ID the config maps."""
    wanted = ", ".join(f"0x{fid:X}" for fid in sorted(runtime.decoder.frame_ids))
    seen = sorted(ids)
    shown = ", ".join(f"0x{fid:X}" for fid in seen[:8]) + (f" and {len(seen) - 8} more" if len(seen) > 8 else "")
    return (f"{path}: none of its {runtime.frames_in} frames has an ID the config maps ({wanted}; "
            f"{runtime.decoder.source}, config keys dbc and mapping); the log holds IDs {shown}")


def run(args: argparse.Namespace) -> int:
    s = load_config(args.config)
    runtime = Runtime(s)
    path = state_file(args.state) if args.state is not None else None
    restored = restore(runtime, path) if path is not None else False
    runtime.pipeline.run_label = Path(args.log).name
    t0 = time.monotonic()
    with progress_for(args, "replay", "frames") as progress:
        published = replay(args.log, runtime, args.realtime, progress, require_match=True)
    elapsed = time.monotonic() - t0
    result = runtime.pipeline.result()
    result["frames_in"] = runtime.frames_in
    result["frames_out"] = published
    if path is not None:
        keep(runtime, path)
        result["state_file"] = {"path": str(path), "restored": restored, "saved": True}
    if args.json:
        json.dump(result, sys.stdout, indent=2)
        sys.stdout.write("\n")
        return 0
    d = result["driveline"]
    print(f"online-id replay {args.log}: {runtime.frames_in} frames in {elapsed:.1f} s "
          f"({runtime.frames_in / max(elapsed, 1e-9):,.0f} frames/s), {published} frames published")
    if path is not None:
        print(f"  state            {'restored from' if restored else 'none yet in'} {path}, saved at the end")
    print(f"  final state      {result['state']}")
    print(f"  resonance  f0    {fmt(d['f0_hz'], '.3f')} Hz   damping ratio {fmt(d['zeta'], '.4f')}   "
          f"valid {d['valid']}")
    print(f"  shaft      c_s   {fmt(d['c_s'], '.1f')} Nm/rad   d_s {fmt(d['d_s'], '.3f')} Nms/rad")
    c = result["counters"]
    print(f"  samples {c['samples']}, gaps {c['gaps']}, timeouts {c['timeouts']}, bad frames {c['bad_frames']}, "
          f"missing frames {c['missing_frames']}, foreign frames {c['frames_unknown_id']}")
    print("  status changes: " + ", ".join(f"{e['t_s']:.1f} s {e['state']}" for e in result["status_changes"][:12])
          + (" ..." if len(result["status_changes"]) > 12 else ""))
    for b in result["baseline"]:
        print(f"  baseline {b['band_rpm'][0]:.0f}-{b['band_rpm'][1]:.0f} rpm, {fmt(b['load_nm'], '.1f')} Nm: "
              f"f0 {fmt(b['f0_hz'], '.3f')} +- {fmt(b['f0_std_hz'], '.3f')} Hz, {b['count']} estimates, "
              f"{b['kind']}" + (f" from {b['source']}" if b['source'] else ""))
    for a in result["alerts"]:
        print(f"  alert at {a['t_s']:.1f} s: {a['kind']} {a['message']}")
    return 0
