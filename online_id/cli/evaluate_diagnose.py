"""``online-id evaluate-diagnose``: the diagnosis on randomised benches, confusion matrix and figures."""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

from online_id.errors import ConfigError
from online_id.io.jsonout import dumps
from online_id.cli import command_help
from online_id.cli.dask_options import add_dask_options


def add_subparser(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser(
        "evaluate-diagnose", help=command_help("evaluate-diagnose"),
        description="Simulate randomised benches (compression pulses, PI speed control, PRBS, "
        "3-4 plateaus of 30-45 s, noise and quantisation), each clean or with one undeclared effect, "
        "write each as a bench CSV and diagnose it as `online-id diagnose` does, from torque and both "
        "speeds only and again with the recorded torque demand; calibrate the acceptance thresholds "
        "of each path on clean benches with their own seeds, then report the kind named first, "
        "parameter errors and the false-effect rate with 95 % intervals.")
    p.add_argument("--cases", type=int, default=30, metavar="N", help="test cases per kind (default 30)")
    p.add_argument("--calibration-cases", type=int, default=30, metavar="N",
                   help="clean calibration benches (default 30)")
    p.add_argument("--seed", type=int, default=1, help="first test seed (default 1)")
    p.add_argument("--thresholds", metavar="JSON",
                   help="use these thresholds instead of calibrating ({kind: value}, or per path "
                   "{no_demand: {...}, demand: {...}} as thresholds.json holds them); 'defaults': the ones "
                   "the diagnosis ships with")
    p.add_argument("--jobs", type=int, default=2, help="worker processes (default 2)")
    add_dask_options(p, "a case whose task fails is a failed case")
    p.add_argument("--family", choices=("bench", "structures"), default="bench",
                   help="bench family of the test cases: bench (the first), or structures (unmeasured masses "
                   "between or beyond the measured ones, cylinder imbalance, high orders, broadband resonances, "
                   "soft to stiff plants)")
    p.add_argument("--calibration-family", action="append", choices=("bench", "structures"), default=None,
                   help="families of the clean calibration benches (repeatable; default: --family)")
    p.add_argument("--paths", choices=("both", "no_demand", "demand"), default="both",
                   help="diagnose without the recorded demand, with it, or both (default)")
    p.add_argument("--quick", action="store_true", help="3 cases per kind, 6 calibration benches")
    p.add_argument("--include", metavar="DIR", action="append", default=[],
                   help="also summarise the finished test cases of an earlier run (its cases.jsonl); "
                   "give the same --thresholds")
    p.add_argument("--calibration-from", metavar="DIR",
                   help="calibrate on the clean benches of an earlier run (its calibration.jsonl) "
                   "with today's rule instead of simulating them")
    p.add_argument("--out", metavar="DIR", default="diagnose-eval", help="output directory")
    p.set_defaults(func=run)


def _progress(label: str, sink: Path):
    t0 = time.monotonic()
    sink.parent.mkdir(parents=True, exist_ok=True)
    sink.write_text("", encoding="utf-8")

    def report(i: int, n: int, r: dict) -> None:
        with sink.open("a", encoding="utf-8") as fh:  # finished cases survive an interrupted run
            fh.write(dumps(r) + "\n")
        el = time.monotonic() - t0
        print(f"\r{label}: {i}/{n} cases, {el:.0f} s, eta {el / i * (n - i):.0f} s  ({r['case']})   ",
              end="", file=sys.stderr, flush=True)
        if i == n:
            print(file=sys.stderr)
    return report


def _read_cases(path: Path) -> list[dict]:
    try:
        return [json.loads(x) for x in path.read_text(encoding="utf-8").splitlines() if x.strip()]
    except (OSError, ValueError) as err:
        raise ConfigError(f"{path}: cannot read earlier cases: {err}") from err


def run(args: argparse.Namespace) -> int:
    from online_id.evaluation import diagnose_benches as ev
    from online_id.bench.diagnose_cases import KINDS

    from online_id.io.outfile import check_output

    check_output(args.out, "output", directory=True)  # before the benches, not after them
    n_test, n_cal = (3, 6) if args.quick else (args.cases, args.calibration_cases)
    if n_test < (0 if args.include else 1) or n_cal < 0 or args.jobs < 1:
        raise ConfigError("--cases (0 only with --include) and --jobs must be >= 1, "
                          "--calibration-cases >= 0")
    t0 = time.monotonic()
    paths = ev.PATHS if args.paths == "both" else (args.paths,)
    calibration = []
    if args.thresholds == "defaults":  # the thresholds the diagnosis ships with
        from online_id.diagnose.bench_diagnosis import THRESHOLDS, THRESHOLDS_DEMAND

        thresholds = {"no_demand": dict(THRESHOLDS), "demand": dict(THRESHOLDS_DEMAND)}
    elif args.thresholds:
        try:
            thresholds = json.loads(Path(args.thresholds).read_text(encoding="utf-8"))
        except (OSError, ValueError) as err:
            raise ConfigError(f"{args.thresholds}: cannot read thresholds: {err}") from err
        if not all(p in thresholds for p in ev.PATHS):
            thresholds = {p: thresholds for p in ev.PATHS}
    else:
        if args.calibration_from:
            calibration = _read_cases(Path(args.calibration_from) / "calibration.jsonl")
        else:
            jobs = [("clean", ev.CALIBRATION_SEED0 + i, fam, paths)
                    for fam in (args.calibration_family or [args.family]) for i in range(n_cal)]
            calibration = ev.run_cases(jobs, args.jobs, _progress("calibration (clean benches)",
                                                                  Path(args.out) / "calibration.jsonl"),
                                       dask=args.dask, scheduler=args.scheduler)
        thresholds = ev.calibrate_paths(calibration)
        Path(args.out).mkdir(parents=True, exist_ok=True)
        (Path(args.out) / "thresholds.json").write_text(dumps(thresholds, indent=1) + "\n",
                                                        encoding="utf-8")
    jobs = [(k, args.seed + i, args.family, paths) for i in range(n_test) for k in KINDS]
    results = (ev.run_cases(jobs, args.jobs, _progress("test benches", Path(args.out) / "cases.jsonl"),
                            dask=args.dask, scheduler=args.scheduler) if jobs else [])
    for d in args.include:
        results += _read_cases(Path(d) / "cases.jsonl")
    seconds = time.monotonic() - t0
    summaries = {}
    for path in paths:
        summaries[path] = ev.summarise(results, thresholds[path], path)
        summaries[path]["seconds"] = seconds
        summaries[path]["command"] = " ".join(["online-id"] + sys.argv[1:]) if sys.argv else ""
    files = ev.write_outputs(Path(args.out), summaries, calibration, results)
    for path in paths:
        print(f"thresholds ({path}): " + ", ".join(f"{k} {v:.4g}" for k, v in thresholds[path].items()))
    for path in paths:
        print()
        print(ev.table(summaries[path]))
    print(f"\n{len(results)} test and {len(calibration)} calibration cases in {seconds:.0f} s")
    for f in files:
        print(f"wrote {f}")
    return 0
