"""``online-id evaluate-diagnose-chain``: the diagnosis judged on the chain family, run as a user runs it."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from online_id.cli import command_help
from online_id.errors import ConfigError


def add_subparser(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser(
        "evaluate-diagnose-chain", help=command_help("evaluate-diagnose-chain"),
        description="Simulate randomised drivetrains built independently of the bench simulator (a chain of "
        "2-6 inertias with gear stages on rigs, unmeasured masses, a four-stroke engine of 3-6 cylinders, a dyno "
        "or load motor under PI speed control with a PRBS, 3-4 plateaus of 30-45 s), each clean or with one "
        "effect; write each as a user's files (a bench CSV with its config, or a two-logger rig with degree "
        "and count encoders), run `online-id diagnose ... --json` on them as a child process and score the "
        "answer against the truth (docs/evaluation-chain.md). Development seeds 60000-60199, held-out seeds "
        "90000 and up (docs/evaluation-seeds.md).")
    p.add_argument("--seed", type=int, default=60000, help="first seed (default 60000, the development range)")
    p.add_argument("--cases", type=int, default=18, metavar="N", help="cases: seeds SEED..SEED+N-1 (default 18)")
    p.add_argument("--jobs", type=int, default=2, help="worker processes (default 2)")
    p.add_argument("--quick", action="store_true", help="three plateaus of 30 s at 1 kHz (other cases than the full "
                   "settings draw from the same seeds)")
    p.add_argument("--timeout", type=float, default=1800.0, metavar="S", help="seconds per diagnosis (default 1800)")
    p.add_argument("--keep-data", action="store_true", help="keep the data files of every case (default: only "
                   "truth, config, the tool's output and the score; the data are redrawn from the seed)")
    p.add_argument("--layout", choices=("bench", "rig"), help="run only the seeds of SEED..SEED+N-1 whose case "
                   "is of this layout")
    p.add_argument("--program", metavar="PATH", help="the online-id executable to judge (default: this "
                   "installation's, as `python -m online_id`), e.g. another checkout's .venv/bin/online-id")
    p.add_argument("--out", metavar="DIR", default="chain-eval", help="output directory (default chain-eval)")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from online_id.evaluation.chain import run_family

    if args.cases < 1 or args.jobs < 1 or args.timeout <= 0 or args.seed < 0:
        raise ConfigError("--cases and --jobs must be >= 1, --timeout > 0, --seed >= 0")
    seeds = list(range(args.seed, args.seed + args.cases))
    if args.layout:
        from online_id.evaluation.chain_cases import draw_case

        seeds = [s for s in seeds if draw_case(s, args.quick)["layout"] == args.layout]
        if not seeds:
            raise ConfigError(f"no {args.layout} case among seeds {args.seed}..{args.seed + args.cases - 1}")
    program = None
    if args.program:
        if not Path(args.program).is_file():
            raise ConfigError(f"--program {args.program}: no such file")
        program = [str(Path(args.program).resolve())]
    out = Path(args.out)
    print(f"chain family: {len(seeds)} cases of seeds {args.seed}-{args.seed + args.cases - 1}"
          f"{' (quick)' if args.quick else ''}{', ' + args.layout + ' only' if args.layout else ''}, "
          f"{args.jobs} jobs, output in {out}/", file=sys.stderr, flush=True)
    _records, summary = run_family(seeds, out, quick=args.quick, jobs=args.jobs, timeout_s=args.timeout,
                                   keep_data=args.keep_data, program=program)
    print((out / "table.md").read_text(encoding="utf-8"))
    print(f"results: {out / 'results.json'}, {out / 'table.md'}, {out / 'confusion.png'}")
    return 0
