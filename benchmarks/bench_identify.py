"""Time, peak memory and accuracy of ``online-id identify``, old and new side by side.

Usage::

    python benchmarks/bench_identify.py [--durations 600 3600] [--repeats 3]
        [--old-rev 616c58d] [--skip-old-above 600] [--accuracy] [--workdir DIR]

For each duration a simulated bench recording at 1 kHz is written once
(``online-id simulate``: the default plant, J1 0.8, J2 0.35, c_s 6000, d_s 4,
four or eight operating points filling the duration). Then the command

    python -m online_id identify REC.csv --J1 0.8 --json

runs as a child process, alternately with the *old* package (``git archive``
of ``--old-rev``, the last commit before the fast identification) and the
*new* one (this checkout) on ``PYTHONPATH``, ``--repeats`` times each. Per
run: wall time, CPU time (user + system) and peak resident memory of the
child (``os.wait4``), and the errors of f0, zeta and c_s against the
simulation's truth. The table gives medians and the ratios old / new.

``--accuracy`` adds several truths (plants and seeds varied: resonance 12-36
Hz, damping ratio 0.02-0.12, four or six cylinders; 120 s plateaus), each
identified by old and new, to show that the bounded fit window loses no
accuracy.

The machine is whatever runs this: on a shared machine wall times vary with
the load, so old and new alternate and the CPU times are reported too. One
warm-up run per package compiles numba's cache first (not timed).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import subprocess
import sys
import time
from pathlib import Path

import yaml

REPO = Path(__file__).resolve().parents[1]
POINTS_1H = (1000, 1300, 1600, 1900, 2200, 2500, 2800, 3100)
POINTS_10MIN = (1000, 1500, 2000, 2500)
RAMP_S = 3.0

# plants for --accuracy: J1, J2, c_s, d_s, cylinders, speeds [rpm], seed
TRUTHS = [
    (0.8, 0.35, 6000.0, 4.0, 4, (1000, 1600, 2200), 11),
    (1.2, 0.25, 12000.0, 6.0, 6, (1200, 1800, 2400), 12),
    (0.5, 0.30, 2500.0, 1.5, 4, (1400, 2000, 2800), 13),
    (1.5, 0.45, 9000.0, 12.0, 4, (1100, 1700, 2300), 14),
    (0.6, 0.20, 9000.0, 2.0, 4, (1000, 1500, 2000), 15),
]


def scenario(points: tuple[int, ...], duration_s: float, **plant) -> dict:
    """A simulate scenario whose operating points fill ``duration_s`` seconds."""
    dwell = (duration_s - RAMP_S * (len(points) - 1)) / len(points)
    return {**plant, "ramp_s": RAMP_S,
            "operating_points": [{"speed_rpm": float(p), "duration_s": dwell} for p in points]}


def recording(workdir: Path, name: str, spec: dict, seed: int, python: str) -> Path:
    """Simulate ``spec`` once (kept in ``workdir``); returns the CSV path."""
    csv = workdir / f"{name}.csv"
    if not csv.exists():
        cfg = workdir / f"{name}.yaml"
        cfg.write_text(yaml.safe_dump(spec))
        env = {**os.environ, "PYTHONPATH": str(REPO)}
        subprocess.run([python, "-m", "online_id", "simulate", "--config", str(cfg), "--seed", str(seed),
                        "--out", str(csv)], check=True, env=env, stdout=subprocess.DEVNULL, cwd=workdir)
    return csv


def old_package(workdir: Path, rev: str) -> Path:
    """The package as of ``rev`` (``git archive``), unpacked once."""
    dest = workdir / f"old-{rev}"
    if not (dest / "online_id").exists():
        dest.mkdir(parents=True, exist_ok=True)
        archive = subprocess.run(["git", "-C", str(REPO), "archive", rev, "online_id"], check=True,
                                 capture_output=True).stdout
        subprocess.run(["tar", "-x", "-C", str(dest)], input=archive, check=True)
    return dest


def measured(python: str, package: Path, csv: Path, J1: float) -> dict:
    """One ``identify`` child: wall and CPU seconds, its own peak memory in MB (``os.wait4``), its result."""
    env = {**os.environ, "PYTHONPATH": str(package)}
    out_path = csv.with_suffix(f".{package.name}.json")
    t0 = time.perf_counter()
    with open(out_path, "w") as out, open(os.devnull, "w") as null:
        # cwd: python -m puts the working directory first on sys.path, ahead of PYTHONPATH
        proc = subprocess.Popen([python, "-m", "online_id", "identify", str(csv), "--J1", str(J1), "--json"],
                                env=env, stdout=out, stderr=null, cwd=csv.parent)
        _, status, usage = os.wait4(proc.pid, 0)
    wall = time.perf_counter() - t0
    proc.returncode = os.waitstatus_to_exitcode(status)
    if proc.returncode != 0:
        raise RuntimeError(f"identify {csv} with {package} failed (rc {proc.returncode})")
    doc = json.loads(out_path.read_text())
    windowed = "fit_window_s" in doc["operating_points"][0]
    if windowed != (package == REPO):
        raise RuntimeError(f"the child did not run the package in {package}")
    return {"wall": wall, "cpu": usage.ru_utime + usage.ru_stime, "rss_mb": usage.ru_maxrss / 1024,
            "driveline": doc["driveline"], "na": doc["model"]["na"]}


def errors(run: dict, truth: dict) -> dict:
    d = run["driveline"]
    return {k: 100.0 * (d[k] / truth[k] - 1.0) for k in ("f0_hz", "zeta", "c_s")}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--durations", type=float, nargs="*", default=[600.0, 3600.0])
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--old-rev", default="616c58d", help="the commit to compare with (default: before fast identify)")
    ap.add_argument("--skip-old-above", type=float, default=float("inf"), metavar="S",
                    help="run the old package only on recordings up to S seconds (it takes 16 min for 1 h)")
    ap.add_argument("--accuracy", type=int, nargs="?", const=len(TRUTHS), default=0, metavar="N",
                    help=f"also compare old and new on the first N of {len(TRUTHS)} truths (default all)")
    ap.add_argument("--workdir", type=Path, default=Path("/tmp/online-id-bench-identify"))
    args = ap.parse_args(argv)
    python = sys.executable
    args.workdir.mkdir(parents=True, exist_ok=True)
    old, new = old_package(args.workdir, args.old_rev), REPO
    packages = {"old": old, "new": new}
    print(f"# identify benchmark: {platform.node()} {platform.machine()}, {os.cpu_count()} CPUs, "
          f"Python {platform.python_version()}, load average {os.getloadavg()[0]:.1f} at the start; "
          f"old = {args.old_rev}, new = {REPO}")
    warm = recording(args.workdir, "warmup", scenario((1000, 2000), 43.0), seed=1, python=python)
    for package in packages.values():  # numba compiles into its cache once per package
        measured(python, package, warm, 0.8)
    for dur in args.durations:
        points = POINTS_10MIN if dur <= 1200 else POINTS_1H
        csv = recording(args.workdir, f"bench_{dur:g}s", scenario(points, dur), seed=1, python=python)
        truth = json.loads(csv.with_suffix(".truth.json").read_text())
        names = ["old", "new"] if dur <= args.skip_old_above else ["new"]
        runs: dict[str, list[dict]] = {n: [] for n in names}
        for _ in range(args.repeats):
            for n in names:
                runs[n].append(measured(python, packages[n], csv, truth["J1"]))
                r = runs[n][-1]
                print(f"  {dur:6g} s {n}: wall {r['wall']:7.1f} s  cpu {r['cpu']:7.1f} s  peak {r['rss_mb']:6.0f} MB  "
                      f"load {os.getloadavg()[0]:.1f}", flush=True)
        print(f"\n{dur:g} s at 1 kHz ({len(points)} operating points), {args.repeats} runs each, medians:")
        print("          wall [s]   cpu [s]  peak [MB]   f0 err %  zeta err %  c_s err %   na")
        for n in names:
            rs = runs[n]
            e = errors(rs[0], truth)
            print(f"  {n:5s} {statistics.median(r['wall'] for r in rs):10.1f} "
                  f"{statistics.median(r['cpu'] for r in rs):9.1f} {max(r['rss_mb'] for r in rs):10.0f} "
                  f"{e['f0_hz']:+10.4f} {e['zeta']:+11.2f} {e['c_s']:+10.2f} {rs[0]['na']:4d}")
        if len(names) == 2:
            ratio = {k: statistics.median(r[k] for r in runs["old"]) / statistics.median(r[k] for r in runs["new"])
                     for k in ("wall", "cpu")}
            print(f"  old/new: wall x{ratio['wall']:.1f}, cpu x{ratio['cpu']:.1f}\n", flush=True)
    if args.accuracy:
        print("accuracy on several truths (120 s plateaus at 1 kHz), error against the truth in %:")
        print("  truth                               f0 [Hz]   zeta  |  old f0   new f0 | old zeta new zeta "
              "| old c_s  new c_s | cpu old  new [s]")
        for J1, J2, c, d, n_cyl, speeds, seed in TRUTHS[: args.accuracy]:
            spec = scenario(speeds, 120.0 * len(speeds) + RAMP_S * (len(speeds) - 1),
                            J1=J1, J2=J2, c_s=c, d_s=d, n_cyl=n_cyl)
            csv = recording(args.workdir, f"truth_{seed}", spec, seed=seed, python=python)
            truth = json.loads(csv.with_suffix(".truth.json").read_text())
            res = {n: measured(python, packages[n], csv, J1) for n in ("old", "new")}
            eo, en = errors(res["old"], truth), errors(res["new"], truth)
            print(f"  J1 {J1} J2 {J2} c {c:g} d {d:g} {n_cyl}cyl {truth['f0_hz']:7.2f} {truth['zeta']:.4f} | "
                  f"{eo['f0_hz']:+.4f} {en['f0_hz']:+.4f} | {eo['zeta']:+6.2f} {en['zeta']:+6.2f}   | "
                  f"{eo['c_s']:+6.2f} {en['c_s']:+6.2f}  | {res['old']['cpu']:6.1f} {res['new']['cpu']:5.1f}",
                  flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
