"""``online-id trend RESULTS [--bench B] --out DIR``: wear trends per bench from an archive table.

Reads the table ``online-id archive identify`` wrote (a results directory,
its ``results.parquet`` or ``results.csv``) and, per bench and operating
point, fits the resonance and the damping against the recording date
(:mod:`online_id.archive.trend`): the baseline of the first healthy weeks,
a change model (none, wear from an onset, a sudden change), the drift per
month with its 95 % interval, and alerts in the live service's words.
Writes ``trend_BENCH.png`` per bench, ``fleet.md`` and ``fleet.csv`` (one
row per bench, operating point and quantity) and ``trend.json``.
"""

from __future__ import annotations

import argparse
import csv
import datetime as dt
import json
import sys
from pathlib import Path

import numpy as np

from online_id.cli import command_help
from online_id.errors import ConfigError, InputDataError


def add_subparser(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser(
        "trend", help=command_help("trend"),
        description="Per bench and operating point: the resonance and damping of every recording against its "
                    "date, the baseline of the first healthy weeks, the change (none, wear from an onset, a "
                    "sudden change), the drift per month with its 95 %% interval, and alerts as the live service "
                    "words them. Writes a PNG per bench, fleet.md, fleet.csv and trend.json.")
    p.add_argument("results", metavar="RESULTS", help="results directory of `online-id archive identify`, or its "
                   "results.parquet / results.csv")
    p.add_argument("--bench", metavar="B", help="only this bench")
    p.add_argument("--out", required=True, type=Path, metavar="DIR", help="where to write the plots and tables")
    p.add_argument("--baseline-weeks", type=float, default=4.0, metavar="W",
                   help="the first W weeks of each bench are its healthy baseline (default 4)")
    p.add_argument("--band-rpm", type=float, default=100.0, metavar="RPM",
                   help="speeds within this of each other are one operating point (default 100)")
    p.add_argument("--warn-freq-pct", type=float, default=1.0, metavar="PCT",
                   help="resonance change that raises a warning (default 1 %%, about 2 %% of stiffness)")
    p.add_argument("--fault-freq-pct", type=float, default=2.5, metavar="PCT",
                   help="resonance change that raises a fault (default 2.5 %%, about 5 %% of stiffness)")
    p.add_argument("--warn-damping-pct", type=float, default=20.0, metavar="PCT",
                   help="damping change that raises a warning (default 20 %%)")
    p.add_argument("--fault-damping-pct", type=float, default=40.0, metavar="PCT",
                   help="damping change that raises a fault (default 40 %%)")
    p.add_argument("--json", action="store_true", help="print trend.json's document instead of the table")
    p.set_defaults(func=run)


FLEET_COLUMNS = ("bench", "quantity", "speed_rpm", "recordings", "baseline", "model", "change_pct",
                 "drift_pct_per_month", "drift_ci_low", "drift_ci_high", "onset", "level", "alert_date", "message")


def _f(x: float | None, spec: str) -> str:
    return "-" if x is None or not np.isfinite(x) else format(x, spec)


def fleet_markdown(benches) -> str:
    """The fleet table: one line per bench with its verdict, then one per operating point and quantity."""
    from online_id.monitoring.detection import FREQUENCY

    lines = ["| bench | verdict | onset (resonance) |", "|---|---|---|"]
    for b in benches:
        onset = b.onset_s(FREQUENCY)
        lines.append(f"| {b.bench} | {b.verdict()} | "
                     f"{dt.datetime.fromtimestamp(onset, dt.timezone.utc):%Y-%m-%d} |" if onset else
                     f"| {b.bench} | {b.verdict()} | - |")
    lines += ["", "| bench | quantity | rpm | recordings | baseline | model | change % | drift %/month [95 %] "
              "| onset | alert | from |", "|---|---|---:|---:|---:|---|---:|---|---|---|---|"]
    for b in benches:
        for s in b.series:
            r = s.as_row()
            spec = ".3f" if r["quantity"] == "resonance" else ".4f"
            drift = (f"{_f(r['drift_pct_per_month'], '+.2f')} [{_f(r['drift_ci_low'], '+.2f')}, "
                     f"{_f(r['drift_ci_high'], '+.2f')}]") if r["drift_ci_low"] is not None else "-"
            lines.append(f"| {r['bench']} | {r['quantity']} | {r['speed_rpm']} | {r['recordings']} | "
                         f"{_f(r['baseline'], spec)} | {r['model'] or '-'} | {_f(r['change_pct'], '+.2f')} | {drift} | "
                         f"{r['onset'] or '-'} | {r['level'] or '-'} | {r['alert_date'] or '-'} |")
    return "\n".join(lines)


def run(args: argparse.Namespace) -> int:
    from online_id.archive.store import read_rows
    from online_id.archive.trend import TrendSettings, trends
    from online_id.archive.trend_plot import plot_bench
    from online_id.io.outfile import atomic_output, check_output

    try:
        settings = TrendSettings(baseline_days=7.0 * args.baseline_weeks, band_rpm=args.band_rpm,
                                 warn_freq_pct=args.warn_freq_pct, fault_freq_pct=args.fault_freq_pct,
                                 warn_damping_pct=args.warn_damping_pct, fault_damping_pct=args.fault_damping_pct)
    except ValueError as err:
        raise ConfigError(f"trend: {err}") from None
    check_output(args.out, "trend", directory=True)
    rows = read_rows(args.results)
    usable = [r for r in rows if r["status"] == "ok" and r["start_time"] is not None]
    if args.bench is not None and not any(r["bench"] == args.bench for r in rows):
        names = ", ".join(sorted({str(r["bench"]) for r in rows})) or "none"
        raise InputDataError(f"{args.results}: no bench {args.bench!r} in the table (benches: {names})")
    benches = trends(rows, settings, args.bench)
    if not benches:
        raise InputDataError(f"{args.results}: no identified recording with a start time to trend "
                             f"({len(rows)} rows, {len(usable)} usable)")
    args.out.mkdir(parents=True, exist_ok=True)
    files = [plot_bench(b, settings, args.out / f"trend_{_safe(b.bench)}.png") for b in benches]
    text = fleet_markdown(benches)
    table = [s.as_row() for b in benches for s in b.series]
    with atomic_output(args.out / "fleet.md") as tmp:
        tmp.write_text(text + "\n")
    with atomic_output(args.out / "fleet.csv") as tmp, open(tmp, "w", newline="") as f:
        w = csv.DictWriter(f, FLEET_COLUMNS)
        w.writeheader()
        w.writerows(table)
    doc = {"settings": settings.__dict__, "rows_read": len(rows), "rows_used": len(usable),
           "benches": [{"bench": b.bench, "level": b.level, "verdict": b.verdict(),
                        "onset": _iso(b.onset_s()), "series": [s.as_row() for s in b.series]} for b in benches]}
    with atomic_output(args.out / "trend.json") as tmp:
        tmp.write_text(json.dumps(doc, indent=1, default=float) + "\n")
    if args.json:
        json.dump(doc, sys.stdout, indent=1, default=float)
        sys.stdout.write("\n")
        return 0
    skipped = len(rows) - len(usable)
    print(f"online-id trend {args.results}: {len(usable)} rows of {len({r['path'] for r in usable})} recordings"
          + (f" ({skipped} rows without a result or a start time left out)" if skipped else ""))
    print(text)
    for f in files + [args.out / n for n in ("fleet.md", "fleet.csv", "trend.json")]:
        print(f"wrote {f}")
    return 0


def _iso(t: float | None) -> str | None:
    return None if t is None else dt.datetime.fromtimestamp(t, dt.timezone.utc).strftime("%Y-%m-%d")


def _safe(name: str) -> str:
    return "".join(c if c.isalnum() or c in "-_." else "_" for c in name)
