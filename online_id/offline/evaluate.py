"""The work of ``online-id evaluate``: the detection evaluation run, summarised, tabulated and plotted."""

from __future__ import annotations

import argparse
import dataclasses
import json
import multiprocessing
import os
import platform
import sys
import time
from pathlib import Path

import numpy as np

from online_id.bench import evaluate as ev
from online_id.errors import ConfigError, InputDataError
from online_id.io.outfile import atomic_output, check_output
from online_id.offline.bench_feed import run_spec
from online_id.report.figures import fmt, pyplot, save_figure


def table(summary: dict) -> str:
    """The summary as a Markdown table (the README quotes it)."""
    f = summary["fault_free"]
    lines = [
        f"Fault-free: {f['hours']:.1f} h in {f['runs']} runs, {f['false_alarms']} false alarms "
        f"({fmt(f['false_alarms_per_hour'], '.2f')} per hour, {f['false_fault_alarms']} at fault level"
        + (f"; {fmt(f['false_alarms_per_1000h'], '.1f')} per 1,000 h, 95 % interval "
           f"{fmt(f['false_alarms_per_1000h_ci'][0], '.1f')}-{fmt(f['false_alarms_per_1000h_ci'][1], '.1f')}"
           if f.get("false_alarms_per_1000h_ci") else "") + "); "
        f"estimate valid {100 * (f['valid_fraction'] or 0):.0f} % of the time; "
        f"|f0 error| against the linear truth (runs without backlash) median "
        f"{fmt(f['f0_error_pct_p50_abs'], '.3f')} %, 99th percentile {fmt(f['f0_error_pct_p99_abs'], '.3f')} %.",
        "",
        "Fault-free hours and false alarms by the undeclared effect present: "
        + ", ".join(f"{k} {v['hours']:.1f} h / {v['false_alarms']}" for k, v in f.get("by_effect", {}).items())
        + ".",
        "",
        "Fault-free hours and false alarms by dwell: "
        + ", ".join(f"{k} plateaus {v['hours']:.1f} h / {v['false_alarms']}" for k, v in f.get("by_dwell", {}).items())
        + ".",
        "",
        "| family | fault | runs | detected | warning delay median / worst [s] "
        "| fault-level delay median / worst [s] | false alarms before the fault "
        "| with backlash: detected, median [s] | without backlash: detected, median [s] "
        "| wrong kind after the fault: runs (first) / alarms |",
        "|---|---|---:|---:|---:|---:|---:|---:|---:|---:|",
    ]
    if f.get("withheld") is not None and f["runs"]:
        lines[1:1] = ["", "Alarms the detector asked for and the confirm withheld (second look, recheck of the cell's "
                      f"own data) in the fault-free hours: {_kinds(f['withheld'])}."]
    back = summary.get("revalid_after_change_s")
    if back:
        lines[1:1] = ["", f"After a change of operating point the estimate was valid again {back['median']:.1f} s "
                      f"after the ramp began (median of {back['changes']} changes in the fault runs; 90 % within "
                      f"{back['p90']:.1f} s, at most {back['max']:.1f} s)."]
    for r in summary["faults"]:
        by = r.get("by_plant", {})
        plants = " | ".join(f"{p['detected']}/{p['runs']}, {fmt(p['warning_delay_s_median'], '.1f')}" if p else "-"
                            for p in (by.get(kind) for kind in ev.PLANT_TYPES))
        lines.append(
            f"| {r.get('family', 'c')} | {r['case']} | {r['runs']} | {r['detected']} | {fmt(r['warning_delay_s_median'], '.1f')} / "
            f"{fmt(r['warning_delay_s_worst'], '.1f')} | {fmt(r['fault_delay_s_median'], '.1f')} / "
            f"{fmt(r['fault_delay_s_worst'], '.1f')} ({r['fault_level_reached']}/{r['runs']}) "
            f"| {r['false_alarms_before_fault']} | {plants} | {_wrong(r)} |")
    faults = [r for r in summary["faults"] if r.get("family", "c") in ev.FAMILIES  # not the a+b rows again
              and r.get("withheld_after_fault") is not None]
    if faults:
        before, after = ({k: sum((r.get(name) or {}).get(k, 0) for r in faults) for k in ("frequency", "damping")}
                         for name in ("withheld_before_fault", "withheld_after_fault"))
        lines += ["", f"Alarms withheld in the fault runs: before the fault {_kinds(before)}; after it "
                  f"{_kinds(after)} (each one after the fault delayed a detection or was of the other kind)."]
    crossing = summary.get("crossings")
    if crossing:
        lines += ["", *crossing_lines(crossing)]
    realism = summary.get("settings", {}).get("realism")
    if realism:
        lines[0:0] = [f"Input: CAN frames through the service's runtime, {100 * realism['frame_loss']:g} % lost, "
                      f"received up to {1000 * realism['jitter_s']:g} ms late; slow work adopted "
                      f"{realism['worker_lag_s']:g} s after submission.", ""]
    return "\n".join(lines)


def _wrong(r: dict) -> str:
    """The wrong-kind cell of a fault row ("-" in a results.json of a version before the count)."""
    if "wrong_kind_runs" not in r:
        return "-"
    return f"{r['wrong_kind_runs']} ({r['wrong_kind_first']}) / {r['wrong_kind_alarms']}"


def crossing_lines(c: dict) -> list[str]:
    """The crossing section of the table: what the service did where an engine-order line crosses the
    resonance (outcomes per visit), and the false alarms there against elsewhere."""
    def outcomes(part: dict) -> str:
        return ", ".join(f"{k} {n}" for k, n in part["outcomes"].items()) or "none"

    def rate(part: dict) -> str:
        ci = part.get("false_alarms_per_1000h_ci")
        return (f"{fmt(part['false_alarms_per_1000h'], '.0f')} per 1,000 h, 95 % interval "
                f"{fmt(ci[0], '.0f')}-{fmt(ci[1], '.0f')}" if ci else "no hours")

    free, away, pre, post = c["fault_free"], c["fault_free_elsewhere"], c["before_fault"], c["after_fault"]
    valid = lambda part: f"{100 * part['valid_fraction']:.0f} %" if part.get("valid_fraction") is not None else "-"  # noqa: E731
    return [
        f"Order-line crossings (engine orders {', '.join(f'{o:g}' for o in c['orders'])} within 25 % of the "
        f"resonance; {c['visits']} visits in {c['runs']} runs):",
        "",
        "| where | visits | hours | estimate valid | false alarms | what the service did (visits) |",
        "|---|---:|---:|---:|---:|---|",
        f"| fault-free runs, at crossings | {free['visits']} | {free['hours']:.2f} | {valid(free)} "
        f"| {free['false_alarms']} ({rate(free)}) | {outcomes(free)} |",
        f"| fault-free runs, elsewhere | - | {away['hours']:.2f} | - | {away['false_alarms']} ({rate(away)}) | - |",
        f"| fault runs before the fault, at crossings | {pre['visits']} | {pre['hours']:.2f} | {valid(pre)} "
        f"| {pre['false_alarms']} | {outcomes(pre)} |",
        f"| fault runs after the fault, at crossings | {post['visits']} | {post['hours']:.2f} | {valid(post)} | - "
        f"| {outcomes(post)}; the first alarm of the fault's kind raised at a crossing in "
        f"{post['first_alarm_at_crossing']} of {post['fault_runs']} runs |",
        "",
        "held: estimate valid less than half the visit, no alarm; tracked: valid, no alarm; latched: the "
        "fault's alarm raised before the visit; warned / detected: a warning / fault-level alarm of the fault's "
        "kind raised in the visit (or the ramp after it); wrong kind: only an alarm of the other kind.",
    ]


def _kinds(counts: dict) -> str:
    """``{"frequency": 3, "damping": 1}`` as "3 frequency, 1 damping"."""
    return ", ".join(f"{counts.get(k, 0)} {k}" for k in ("frequency", "damping"))


def plot(results: list[ev.RunResult], path: Path) -> None:
    """Detection delays per case, and the f0 error of every fault-free run over time."""
    plt = pyplot()

    fig, (ax1, ax2) = plt.subplots(1, 2, figsize=(13, 4.8))
    table = {c[0]: c for c in ev.FAULT_CASES + ev.FAMILY_CASES}  # label -> (label, stiffness factor, ...)
    labels = sorted(table, key=lambda c: (table[c][1] == 1.0, -table[c][1]))  # losses by size, then damping
    groups = [(fam, case) for fam in ev.FAMILIES for case in labels
              if any(r.case == case and r.family == fam for r in results)]
    several = len({fam for fam, _ in groups}) > 1
    cases = [f"({fam}) {case}" if several else case for fam, case in groups]
    for i, (fam, case) in enumerate(groups):
        rs = [r for r in results if r.case == case and r.family == fam]
        w = [r.warning_delay_s for r in rs if r.warning_delay_s is not None]
        f = [r.fault_delay_s for r in rs if r.fault_delay_s is not None]
        ax1.scatter(np.full(len(w), i - 0.1), w, color="tab:orange", label="warning" if i == 0 else None)
        ax1.scatter(np.full(len(f), i + 0.1), f, color="tab:red", marker="s", label="fault level" if i == 0 else None)
        missed = len(rs) - len(w)
        if missed:
            ax1.annotate(f"{missed} of {len(rs)}\nmissed", (i, 0.02), xycoords=("data", "axes fraction"),
                         ha="center", va="bottom", color="k", fontsize=8)
    ax1.axhline(20.0, color="grey", ls=":", lw=1)
    ax1.axhline(60.0, color="grey", ls="--", lw=1)
    ax1.set_xticks(range(len(cases)), cases, rotation=30 if several else 20, ha="right" if several else "center")
    ax1.set_ylabel("detection delay [s]")
    ax1.set_title("delay from the fault to the alarm (dotted 20 s, dashed 60 s)")
    if cases:
        ax1.legend(loc="upper left")
    ax1.grid(alpha=0.3)
    labelled: set[bool] = set()
    for r in results:
        if r.case == "fault-free" and r.f0_err_pct:
            gap = "backlash" in r.effects  # apparent resonance below the linear truth
            ax2.plot(np.arange(len(r.f0_err_pct)) / 60.0, r.f0_err_pct, lw=0.5, alpha=0.7,
                     color="tab:red" if gap else "tab:blue",
                     label=None if gap in labelled else ("with backlash" if gap else "without backlash"))
            labelled.add(gap)
    if labelled:
        ax2.legend(loc="center right")
    else:
        ax2.text(0.5, 0.5, "no fault-free runs in these results", ha="center", va="center",
                 transform=ax2.transAxes, color="grey")
    ax2.set_xlabel("valid estimates, one per second [min]")
    ax2.set_ylabel("f0 error [%]")
    ax2.set_title("fault-free runs: f0 error of the valid estimates")
    ax2.grid(alpha=0.3)
    save_figure(fig, path)


def _defaults(args: argparse.Namespace) -> None:
    quick = {"hours": 0.5, "fault_plants": 2, "jobs": min(2, os.cpu_count() or 1)}
    full = {"hours": 10.0, "fault_plants": 4, "jobs": os.cpu_count() or 1}
    for key, value in (quick if args.quick else full).items():
        if getattr(args, key) is None:
            setattr(args, key, value)
    if args.quick and args.families == "c":
        args.families = "a,b"
    families = tuple(f.strip() for f in args.families.split(",") if f.strip())
    bad = [f for f in families if f not in ev.FAMILIES]
    if bad or not families:
        raise ConfigError(f"--families: expected a comma-separated list of {', '.join(ev.FAMILIES)}, "
                          f"but got {args.families!r}")
    args.families = families
    labels = {c[0] for c in ev.FAULT_CASES + ev.FAMILY_CASES}
    cases = None if args.cases is None else tuple(c.strip() for c in args.cases.split(",") if c.strip())
    if cases is not None and (not cases or any(c not in labels for c in cases)):
        raise ConfigError(f"--cases: expected labels among {', '.join(sorted(labels))}, but got {args.cases!r}")
    args.cases = cases
    args.realism = _realism(args)
    if args.plant_type not in ("any",) + ev.PLANT_TYPES:
        raise ConfigError(f"--plant-type: expected one of any, {', '.join(repr(x) for x in ev.PLANT_TYPES)}, but got "
                          f"{args.plant_type!r}")


def _realism(args: argparse.Namespace) -> ev.BenchRealism | None:
    """The frames, loss, jitter and worker's lag asked for (``--bench-realism`` fills what is not given);
    None: perfect samples, slow work inline."""
    given = {"frame_loss": args.frame_loss, "jitter_s": args.frame_jitter, "worker_lag_s": args.worker_lag}
    if args.bench_realism:
        args.crossings = True
        given = {k: getattr(ev.BENCH_REALISM, k) if v is None else v for k, v in given.items()}
    if all(v is None for v in given.values()):
        return None
    try:
        return ev.BenchRealism(**{k: 0.0 if v is None else v for k, v in given.items()})
    except ValueError:
        raise ConfigError(f"Expected --frame-loss in [0, 1), --frame-jitter >= 0 and --worker-lag >= 0, but got "
                          f"{args.frame_loss}, {args.frame_jitter}, {args.worker_lag}") from None


def run_evaluate(args: argparse.Namespace) -> int:
    """``online-id evaluate`` with the parsed arguments ``args``."""
    _defaults(args)
    if not (args.hours >= 0 and args.fault_plants >= 0 and args.jobs >= 1):
        raise ConfigError(f"Expected --hours >= 0, --fault-plants >= 0 and --jobs >= 1, but got "
                          f"{args.hours}, {args.fault_plants}, {args.jobs}")
    if args.out is not None:
        check_output(args.out, "results", directory=True)
        try:
            args.out.mkdir(parents=True, exist_ok=True)
        except OSError as err:
            raise InputDataError(f"{args.out}: cannot create the output directory ({err.strerror})") from None
    if args.from_results is not None:
        return _from_results(args)
    specs = ev.plan(args.hours, args.fault_plants, args.seed, args.families, args.cases, args.plant_type,
                    crossings=args.crossings, realism=args.realism)
    specs.sort(key=lambda s: -s.scenario.duration_s)  # longest first: the pool finishes together
    total_s = sum(s.scenario.duration_s for s in specs)
    where = (f"Dask scheduler {args.scheduler}" if args.scheduler else
             f"a local Dask cluster of {args.jobs} processes" if args.dask else f"{args.jobs} processes")
    print(f"online-id evaluate: {len(specs)} runs, {total_s / 3600:.1f} simulated hours, {where}", file=sys.stderr)
    t0 = time.monotonic()
    results: list[ev.RunResult] = []
    done_s = 0.0
    settings = {"hours": args.hours, "fault_plants": args.fault_plants, "plant_type": args.plant_type,
                "seed": args.seed,
                "families": list(args.families), "cases": list(args.cases) if args.cases else None,
                "jobs": args.jobs, "crossings": args.crossings,
                "realism": None if args.realism is None else dataclasses.asdict(args.realism),
                "machine": f"{platform.machine()}, {os.cpu_count()} cores, Python {platform.python_version()}"}
    failed: list[str] = []

    def record(r: ev.RunResult) -> None:
        nonlocal done_s
        results.append(r)
        done_s += r.duration_s
        if args.out is not None:  # a long evaluation that is stopped keeps the runs so far
            _write_results(args.out, results, dict(settings, elapsed_s=round(time.monotonic() - t0, 1)),
                           complete=len(results) == len(specs))
        what = (f"{r.false_alarms} false alarms" if r.case == "fault-free"
                else f"alarm after {fmt(r.warning_delay_s, '.1f')} s")
        print(f"[{len(results):3d}/{len(specs)}] {100 * done_s / total_s:5.1f}%  ({r.family}) {r.case:16s} "
              f"seed {r.seed:5d}  "
              f"{r.duration_s / 60:5.1f} min simulated in {r.elapsed_s:5.1f} s  {what}", file=sys.stderr)

    if args.dask or args.scheduler:
        from online_id.archive.runner import cluster, map_tasks

        settings["dask"] = args.scheduler or f"local cluster, {args.jobs} workers"

        def done(o) -> None:
            if o.ok:
                record(o.value)
                return
            spec = specs[o.index]
            failed.append(f"({spec.family}) {spec.case} seed {spec.seed}: {o.error}")
            print(f"[failed] ({spec.family}) {spec.case} seed {spec.seed}: {o.error}", file=sys.stderr)

        with cluster(args.scheduler, args.jobs) as client:
            map_tasks(client, run_spec, specs, label="evaluate", on_done=done, quiet=True)
    else:
        ctx = multiprocessing.get_context("fork")
        with ctx.Pool(args.jobs) as pool:
            for r in pool.imap_unordered(run_spec, specs):
                record(r)
    elapsed = time.monotonic() - t0
    settings["elapsed_s"] = round(elapsed, 1)
    _write(args, results, settings, complete=not failed)
    if not args.json:
        print(f"\n{total_s / 3600:.1f} simulated hours in {elapsed / 60:.1f} min"
              + (f"; results in {args.out}/ (results.json, table.md, evaluation.png)" if args.out else ""))
    if failed:
        print(f"{len(failed)} of {len(specs)} runs failed and are left out of the summary; first: {failed[0]}",
              file=sys.stderr)
        return 1
    return 0


def _from_results(args: argparse.Namespace) -> int:
    path = args.from_results
    try:
        doc = json.loads(path.read_text())
        results = [ev.RunResult(**r) for r in doc["runs"]]
        args.families = tuple(doc["summary"].get("settings", {}).get("families", ["c"]))
        settings = doc["summary"].get("settings", {})
        complete = bool(doc.get("complete", True))
    except OSError as err:
        raise InputDataError(f"{path}: cannot read the results ({err.strerror})") from None
    except (ValueError, KeyError, TypeError, AttributeError) as err:
        raise InputDataError(f"{path}: not a results.json of online-id evaluate ({err})") from None
    if not complete:
        print(f"online-id evaluate: {path} is partial (the evaluation was stopped or is still running): "
              f"{len(results)} runs so far", file=sys.stderr)
    _write(args, results, settings, complete)
    return 0


def _write_results(out: Path, results: list[ev.RunResult], settings: dict, complete: bool = True) -> dict:
    """``results.json`` (atomically): the summary and every run; ``complete`` is false while runs are left,
    and ``--from-results`` tabulates such a file as it stands."""
    results = sorted(results, key=lambda r: (r.case, r.seed))
    summary = ev.summarize(results)
    summary["settings"] = settings
    with atomic_output(out / "results.json") as tmp:
        tmp.write_text(json.dumps({"summary": summary, "complete": complete,
                                   "runs": [r.as_dict() for r in results]}, indent=1) + "\n")
    return summary


def _write(args: argparse.Namespace, results: list[ev.RunResult], settings: dict, complete: bool = True) -> None:
    results.sort(key=lambda r: (r.case, r.seed))
    if args.out is not None:
        summary = _write_results(args.out, results, settings, complete)
    else:
        summary = ev.summarize(results)
        summary["settings"] = settings
    text = table(summary)
    if args.out is not None:
        (args.out / "table.md").write_text(text + "\n")
        plot(results, args.out / "evaluation.png")
    if args.json:
        json.dump(summary, sys.stdout, indent=2)
        sys.stdout.write("\n")
    else:
        print(text)
