"""``online-id replay LOG``: a CAN log through exactly the pipeline of the live service."""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

from online_id.config import load_config
from online_id.io.outfile import check_output
from online_id.progress import add_quiet_option, progress_for
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
    p.add_argument("--out-mf4", metavar="FILE.mf4",
                   help="write the estimates, quality, state and alerts as MDF 4 channels with units, on the log's "
                        "time base (docs/sysid.md lists the channels)")
    add_quiet_option(p)
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from online_id.offline.replay import ResultsRuntime, keep, replay, restore, state_file, write_results
    from online_id.report.figures import fmt

    s = load_config(args.config)
    if args.out_mf4:
        check_output(args.out_mf4, "results file")
    runtime = ResultsRuntime(s)
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
    if args.out_mf4:
        write_results(args.out_mf4, args.log, runtime, list(runtime.pipeline.alerts))
        result["results_file"] = args.out_mf4
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
    if args.out_mf4:
        print(f"wrote {args.out_mf4}")
    return 0
