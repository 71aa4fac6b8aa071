"""Start-up of the live service on a loaded machine: when the first valid estimate comes, with the cores shared.

Usage::

    python benchmarks/bench_startup.py [--plants 3] [--loads 0,1,2] [--seed 1] [--out DIR]

A bench PC runs other work beside the service (the test automation, a
logger, a GUI). This benchmark starts ``online-id run`` as its own process
on python-can's ``udp_multicast`` bus (kernel sockets with a finite receive
buffer, ``tests/live/harness.py``), feeds it a simulated bench at real time
from another process, and measures how long after the bench started the
first valid OidEstimate is published, while ``load`` other processes spin
at normal priority (``python -c "while True: pass"``, one per core at most
as many as given). Each plant is also run in-process through the same
runtime (the harness's ``first_valid_in_process``: ``online_id.service.runtime.Runtime``
with the inline worker): the stream time of its first valid estimate is
what the method needs, whatever the machine; the live figure minus it is
what the machine's load added (the refits, which run in the service's
worker process at nice +5, come later than the stream when they get less
of a core).

Plants are drawn as in the live test (resonance 15-35 Hz, damping ratio
0.04-0.12, two steady operating points of 35 s). Besides the start-up it
reports what was lost (kernel drops, missing frames) and whether the last
estimates are within 1 % of the true resonance.

Writes ``bench-startup.json`` and ``bench-startup.png`` into ``--out`` and
prints a table. Timing is noisy on a shared machine: say what else ran.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT / "tests" / "live"))

from harness import first_valid_in_process, live_config, live_plant, live_settings, run_live  # noqa: E402

from online_id.bench.simulate import simulate_bench  # noqa: E402
from online_id.io.dbc import encode_inputs, load_dbc  # noqa: E402

GROUP = "239.74.163.53"


def spin(n: int) -> list[subprocess.Popen]:
    return [subprocess.Popen([sys.executable, "-c", "while True: pass"]) for _ in range(n)]


def summarise(rows: list[dict], loads: list[int]) -> dict:
    """Per load: how many runs never published a valid estimate, and the median and worst of those that did."""
    summary = {}
    for load in loads:
        rs = [r for r in rows if r["load"] == load]
        live = np.array([r["live_s"] for r in rs], dtype=float)
        added = np.array([r["added_s"] for r in rs], dtype=float)
        ok = np.isfinite(live)
        summary[str(load)] = {"runs": len(rs), "never_valid": int((~ok).sum()),
                              "live_median_s": float(np.median(live[ok])) if ok.any() else None,
                              "live_max_s": float(np.max(live[ok])) if ok.any() else None,
                              "added_median_s": float(np.median(added[ok])) if ok.any() else None,
                              "added_max_s": float(np.max(added[ok])) if ok.any() else None}
    return summary


def print_summary(summary: dict) -> None:
    def f(x: float | None) -> str:
        return "-" if x is None else f"{x:.1f}"
    print("\n| busy processes | runs | never valid in the run | first valid, median / worst [s] | added by the load, "
          "median / worst [s] |")
    print("|---:|---:|---:|---:|---:|")
    for load, s in summary.items():
        print(f"| {load} | {s['runs']} | {s['never_valid']} | {f(s['live_median_s'])} / {f(s['live_max_s'])} | "
              f"{f(s['added_median_s'])} / {f(s['added_max_s'])} |")


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--plants", type=int, default=3)
    ap.add_argument("--loads", type=lambda s: [int(x) for x in s.split(",")], default=[0, 1, 2])
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--out", default="bench-startup-out")
    ap.add_argument("--from-results", metavar="JSON", help="print the summary of an earlier run's bench-startup.json")
    args = ap.parse_args()
    if args.from_results:
        rows = json.loads(Path(args.from_results).read_text())["rows"]
        print_summary(summarise(rows, sorted({r["load"] for r in rows})))
        return 0
    out_dir = Path(args.out)
    out_dir.mkdir(parents=True, exist_ok=True)
    rows = []
    result = {"machine": {"cpus": os.cpu_count(), "python": platform.python_version(),
                          "load_avg_start": os.getloadavg()}, "rows": rows}
    with tempfile.TemporaryDirectory() as tmp:
        work = Path(tmp)
        for k in range(args.plants):
            seed = args.seed * 1000 + k
            record = simulate_bench(live_plant(seed))
            truth = record.truth
            frames = encode_inputs(record.time_s, record.dyno_speed_rpm, record.engine_speed_rpm,
                                   record.dyno_torque_nm, db=load_dbc(None))
            t_inproc = first_valid_in_process(frames, live_settings(truth))
            for load in args.loads:
                run_dir = work / f"{seed}-{load}"
                config = live_config(truth, run_dir / "state")
                spinners = spin(load)
                try:
                    time.sleep(1.0)
                    run = run_live(frames, config, run_dir, GROUP)
                finally:
                    for p in spinners:
                        p.kill()
                        p.wait()
                valid = [(t, d) for t, _p, d, _k in run.estimates if d.get("Valid")]
                t_live = valid[0][0] - run.t_bench0 if valid else float("nan")
                f0 = float(np.median([d["ResonanceFreq"] for _t, d in valid[-50:]])) if valid else float("nan")
                n = run.counts
                row = {"seed": seed, "f0_hz": truth["f0_hz"], "load": load, "in_process_s": t_inproc,
                       "live_s": t_live, "added_s": t_live - t_inproc,
                       "f0_error_pct": 100.0 * (f0 / truth["f0_hz"] - 1.0),
                       "lost": None if not n else n["dropped"] + n["missing"] + (len(frames) - (n["frames_in"] - n["foreign"])),
                       "returncode": run.returncode}
                rows.append(row)
                when = (f"first valid {t_live:.1f} s after the bench started (+{row['added_s']:.1f} s)" if valid
                        else f"never valid in the {record.time_s[-1] - record.time_s[0]:.0f} s run")
                print(f"  plant {seed} ({truth['f0_hz']:.1f} Hz), {load} busy process(es): {when} (in-process "
                      f"{t_inproc:.1f} s of stream), frames lost {row['lost']}, f0 error {row['f0_error_pct']:+.2f} %",
                      flush=True)
    result["machine"]["load_avg_end"] = os.getloadavg()
    result["summary"] = summarise(rows, args.loads)
    (out_dir / "bench-startup.json").write_text(json.dumps(result, indent=2))
    print_summary(result["summary"])
    try:
        import matplotlib
        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
        fig, ax = plt.subplots(figsize=(6, 4))
        for seed in sorted({r["seed"] for r in rows}):
            rs = [r for r in rows if r["seed"] == seed]
            ax.plot([r["load"] for r in rs], [r["live_s"] for r in rs], "o-", label=f"plant {seed} (live)")
            ax.axhline(rs[0]["in_process_s"], ls=":", color=ax.lines[-1].get_color())
        ax.set_xlabel("busy processes beside the service")
        ax.set_ylabel("first valid estimate after the bench started [s]")
        ax.set_xticks(args.loads)
        ax.set_title(f"start-up under load ({os.cpu_count()} cores); dotted: in-process stream time")
        ax.legend(fontsize=8)
        fig.tight_layout()
        fig.savefig(out_dir / "bench-startup.png", dpi=110)
    except ImportError:  # pragma: no cover - matplotlib is optional
        pass
    print(f"(load average {result['machine']['load_avg_start'][0]:.1f} at start); {out_dir / 'bench-startup.json'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
