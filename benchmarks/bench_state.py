"""The service's state snapshot with the cells' learned-from windows: size and time, side by side.

Usage::

    python benchmarks/bench_state.py [--repeats R]

The live service takes a snapshot of the pipeline's state every
``state.save_interval_s`` (60 s) in its receive loop (``Pipeline.get_state``)
and writes it in the worker. Since the recheck (``online_id/estimation/reference.py``)
the state holds, per learned cell, the 10 s window of its first estimates
(5,000 samples of speed and torque at 500 Hz, base64 float32). This
benchmark streams the default simulated bench through a pipeline until its
first cell is learned, then gives it 0, 4, 12 and 24 cells' windows (copies
of that window) and measures, interleaved, the snapshot (``get_state``), the
JSON write (``save_state``) and the file's size. Medians and minima over the
repeats; the ratio is against no windows.
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import platform
import statistics
import tempfile
import time
from pathlib import Path

from online_id.bench import evaluate as ev
from online_id.bench.scenario import BenchScenario, OperatingPoint
from online_id.bench.simulate import simulate_bench
from online_id.io.statefile import save_state
from online_id.service.pipeline import run_bench_data

CELLS = (0, 4, 12, 24)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=30)
    args = ap.parse_args()
    sc = dataclasses.replace(BenchScenario(), seed=3, operating_points=(OperatingPoint(1500.0, 45.0),))
    pipe = run_bench_data(simulate_bench(sc).to_data("bench"), ev.settings_for(ev.RunSpec("x", 3, sc)))
    windows = [w for ws in pipe.policy.checks.windows.values() for w in ws]
    if not windows:
        raise SystemExit("no cell learned on the bench: nothing to measure")
    one = windows[0]
    snap: dict[int, list[float]] = {n: [] for n in CELLS}
    write: dict[int, list[float]] = {n: [] for n in CELLS}
    size: dict[int, int] = {}
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "state.json"
        for _ in range(args.repeats):
            for n in CELLS:  # interleaved: the machine's drift spreads over every size alike
                pipe.policy.checks.windows = {k: [one] for k in range(n)}
                t0 = time.perf_counter()
                state = pipe.get_state()
                t1 = time.perf_counter()
                save_state(path, state)
                t2 = time.perf_counter()
                snap[n].append(t1 - t0)
                write[n].append(t2 - t1)
                size[n] = path.stat().st_size
    print(f"{platform.processor() or platform.machine()}, {os.cpu_count()} cores, Python "
          f"{platform.python_version()}, {args.repeats} repeats, window {len(one.y)} samples")
    print("| cells with windows | state file [kB] | snapshot median / min [ms] | ratio | write median / min [ms] |")
    print("|---:|---:|---:|---:|---:|")
    base = statistics.median(snap[0])
    for n in CELLS:
        m = statistics.median(snap[n])
        print(f"| {n} | {size[n] / 1024:.0f} | {1e3 * m:.2f} / {1e3 * min(snap[n]):.2f} | {m / base:.1f} | "
              f"{1e3 * statistics.median(write[n]):.1f} / {1e3 * min(write[n]):.1f} |")


if __name__ == "__main__":
    main()
