"""``online-id archive identify|diagnose|simulate``: a test centre's recordings on a Dask cluster.

* ``archive identify PATHS_OR_GLOBS --out RESULTS``: every recording
  identified as ``online-id identify`` does, one task each (and one per
  segment of a long recording), the rows appended to the table in
  ``RESULTS`` (Parquet, with a CSV export); a re-run skips what the table
  holds and completes an interrupted one (:mod:`online_id.archive.batch`).
* ``archive diagnose ...``: the same, with ``online-id diagnose``'s effects.
* ``archive simulate DIR``: write a simulated archive (benches, months,
  slow wear and a sudden fault) as MDF 4 files with test-centre metadata.

The cluster: ``--scheduler tcp://HOST:8786`` (a running ``dask scheduler``
with its ``dask worker`` processes), else a local cluster of ``--workers``
processes.  Needs the ``archive`` extra (dask[distributed], pyarrow).
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

from online_id.cli import command_help
from online_id.errors import ConfigError

LOCAL_WORKERS = 2


def add_cluster_options(p: argparse.ArgumentParser) -> None:
    """``--scheduler`` and ``--workers`` (shared by the commands that run on Dask)."""
    g = p.add_mutually_exclusive_group()
    g.add_argument("--scheduler", metavar="tcp://HOST:8786",
                   help="run on this Dask scheduler's workers (started with `dask scheduler` and `dask worker`)")
    g.add_argument("--workers", type=int, metavar="N",
                   help=f"worker processes of the local Dask cluster (default {LOCAL_WORKERS})")


def add_subparser(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser(
        "archive", help=command_help("archive"),
        description="Identify or diagnose a test centre's archive of recordings on a Dask cluster (a local one "
                    "by default), into one results table; or write a simulated archive. Needs the archive extra: "
                    "pip install 'online-id[archive]'.")
    sub = p.add_subparsers(dest="archive_command", metavar="ACTION", required=True)
    for mode, text in (("identify", "identify every recording (f0, zeta, c_s, d_s per operating point)"),
                       ("diagnose", "identify and diagnose every recording (adds the effects found)")):
        q = sub.add_parser(mode, help=text, description=text.capitalize() + ": one task per recording on the "
                           "cluster, rows appended to RESULTS/results.parquet (and results.csv) as they complete; "
                           "a re-run skips what the table holds (by content hash) and completes an interrupted run.")
        q.add_argument("paths", nargs="+", metavar="PATH_OR_GLOB",
                       help="recordings (.mf4, bench CSV, CAN logs), directories (searched recursively) or "
                            "patterns ('archive/**/*.mf4')")
        q.add_argument("--out", required=True, type=Path, metavar="RESULTS", help="the results directory")
        q.add_argument("--config", metavar="FILE", help="YAML config (columns, units, identification, DBC)")
        add_cluster_options(q)
        q.add_argument("--bench-map", metavar="FILE.csv",
                       help="CSV pattern,bench[,start_time]: the bench (and start) of recordings whose path matches "
                            "the glob pattern; before the MDF header and the path")
        q.add_argument("--bench-pattern", metavar="REGEX",
                       help="regular expression with a group (?P<bench>...) finding the bench in the path "
                            "(default: bench07, bench_B3, testbed-4 ...)")
        if mode == "identify":
            q.add_argument("--segment-minutes", type=float, default=60.0, metavar="MIN",
                           help="cut recordings longer than 1.5 times this into parts of about this length, one "
                                "task each (default 60; 0: never)")
        q.add_argument("--flush-seconds", type=float, default=5.0, metavar="S",
                       help="write the rows that came in to the table every S seconds (default 5; 0: as each "
                            "task completes); a run that is killed loses at most these")
        q.add_argument("--quiet", action="store_true", help="no progress line")
        q.set_defaults(func=run_batch, mode=mode)
    s = sub.add_parser("simulate", help="write a simulated archive (MDF 4 with test-centre metadata)",
                       description="Simulate a test centre: benches with random drivelines, months of recordings, "
                       "slow wear on two benches and a sudden stiffness loss on one; write each recording as an "
                       "MDF 4 file DIR/BENCH/YYYY-MM/BENCH_YYYYMMDDTHHMMSS.mf4 and the truth as DIR/truth.json.")
    s.add_argument("out", type=Path, metavar="DIR")
    s.add_argument("--benches", type=int, default=6, help="benches (default 6)")
    s.add_argument("--months", type=float, default=6.0, help="months of recordings (default 6)")
    s.add_argument("--recordings", type=int, default=300, help="recordings in all (default 300)")
    s.add_argument("--dwell", type=float, default=30.0, metavar="S",
                   help="seconds at each of the three operating points of a recording (default 30)")
    s.add_argument("--seed", type=int, default=1)
    s.add_argument("--start", default="2025-01-06", metavar="DATE", help="first day (default 2025-01-06)")
    add_cluster_options(s)
    s.add_argument("--quiet", action="store_true", help="no progress line")
    s.set_defaults(func=run_simulate)


def _client(args: argparse.Namespace):
    from online_id.archive.runner import cluster

    return cluster(args.scheduler, args.workers or LOCAL_WORKERS)


def run_batch(args: argparse.Namespace) -> int:
    from online_id.archive import batch
    from online_id.archive.metadata import DEFAULT_BENCH_PATTERN, BenchMap, MetaRules
    from online_id.archive.runner import require_dask
    from online_id.archive.store import require_pyarrow
    from online_id.config import load_config

    require_dask()
    require_pyarrow()
    s = load_config(args.config)
    rules = MetaRules(BenchMap.load(args.bench_map) if args.bench_map else None,
                      args.bench_pattern or DEFAULT_BENCH_PATTERN)
    segment = getattr(args, "segment_minutes", 0.0)
    if segment is not None and not segment >= 0:
        raise ConfigError(f"--segment-minutes: expected a number >= 0, got {segment!r}")
    files = batch.expand(args.paths)  # before the cluster starts: a wrong pattern is said at once
    t0 = time.monotonic()
    print(f"online-id archive {args.mode}: {len(files)} recordings -> {args.out}", file=sys.stderr)
    with _client(args) as client:
        summary = batch.run(files, args.out, args.mode, s, client, rules=rules,
                            segment_s=60.0 * segment if segment else None, quiet=args.quiet,
                            say=lambda text: print(text, file=sys.stderr), flush_s=max(args.flush_seconds, 0.0))
    for line in summary.messages[:20]:
        print(f"  {line}", file=sys.stderr)
    if len(summary.messages) > 20:
        print(f"  ... and {len(summary.messages) - 20} more (the table's status and error columns)", file=sys.stderr)
    print(f"{summary.recordings} recordings: {summary.skipped} in the table already, {summary.duplicates} "
          f"duplicates, {summary.tasks} tasks run ({summary.ok} identified, {summary.failed} failed, "
          f"{summary.lost} lost) in {time.monotonic() - t0:.1f} s; {summary.rows} rows in "
          f"{Path(args.out) / 'results.parquet'} (and results.csv)")
    if summary.lost:
        print(f"{summary.lost} tasks were lost with their workers: run the same command again to complete the table")
        return 1
    return 0


def run_simulate(args: argparse.Namespace) -> int:
    from online_id.archive.metadata import parse_time
    from online_id.archive.runner import map_tasks, require_dask
    from online_id.archive.simulated import WriteJob, write_one, write_truth
    from online_id.bench.archive_sim import plan_archive
    from online_id.io.outfile import check_output

    require_dask()
    check_output(args.out, "archive", directory=True)
    start = parse_time(args.start, "--start")
    try:
        plan = plan_archive(args.benches, args.months, args.recordings, seed=args.seed, start=start,
                            dwell_s=args.dwell)
    except ValueError as err:
        raise ConfigError(str(err).replace("plan_archive: ", "archive simulate: ")) from None
    args.out.mkdir(parents=True, exist_ok=True)
    write_truth(plan, args.out)
    t0 = time.monotonic()
    with _client(args) as client:
        outs = map_tasks(client, write_one, [WriteJob(str(args.out), r) for r in plan.recordings],
                         label="archive simulate", quiet=args.quiet)
    bad = [o for o in outs if not o.ok]
    for o in bad[:10]:
        print(f"  {plan.recordings[o.index].name}: {o.error}", file=sys.stderr)
    conds = ", ".join(f"{b.name} {b.condition}" + (f" from {b.onset:%Y-%m-%d}" if b.onset else "")
                      for b in plan.benches)
    print(f"wrote {len(outs) - len(bad)} recordings of {len(plan.benches)} benches over "
          f"{plan.days:.0f} days to {args.out} in {time.monotonic() - t0:.1f} s ({conds}); truth in "
          f"{args.out / 'truth.json'}")
    return 1 if bad else 0
