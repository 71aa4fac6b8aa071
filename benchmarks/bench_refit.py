"""Seconds per window refit of the streaming estimator, warm and cold, side by side.

Usage::

    python benchmarks/bench_refit.py [--repeats R] [--seed S]

The default simulated bench (one operating point) is streamed through
:class:`~online_id.estimation.online.OnlineDriveline` for 25 s; its last
refit job (the 10 s window at 500 Hz, 5,000 samples, na = nb = nc = 10) is
then solved again and again, interleaved:

* ``warm``  -- a few trust-region steps from the current solution (the refit of
  every second at a steady point);
* ``cold``  -- Hannan-Rissanen, the recursive estimate and the current solution
  as starts, each to convergence, the lowest loss kept (after a change of
  operating point, every other refit while the estimate is not valid or its
  resonance has just moved by more than 0.5 %, and the multi-start checks).

The table gives the median and the minimum over the repeats and the ratio of
the medians.
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import platform
import statistics
import time

import numpy as np

from online_id.bench.scenario import BenchScenario, OperatingPoint
from online_id.bench.simulate import simulate_bench
from online_id.estimation.model import ArmaxOrders
from online_id.estimation.online import OnlineDriveline
from online_id.estimation.window import solve


def last_job(seed: int):
    """The refit job of a steady window after 25 s of the default bench."""
    sc = dataclasses.replace(BenchScenario(), seed=seed, operating_points=(OperatingPoint(1800.0, 25.0),))
    rec = simulate_bench(sc)
    est = OnlineDriveline(ArmaxOrders(10, 10, 10, 1), input_rate_hz=sc.fs_hz, model_rate_hz=500.0,
                          forgetting=0.9999, pulses_per_rev=2, auto_refit=False)
    w = np.pi / 30.0
    for y, n, u in zip(rec.dyno_speed_rpm * w, rec.engine_speed_rpm * w, rec.dyno_torque_nm):
        est.update(float(y), float(n), float(u))
        if est.refit_due:
            job = est.refit_job()
            if job is not None:
                est.complete(job, solve(job))
    est.window.due = True
    job = est.window.prepare()
    if job is None:
        raise SystemExit("bench_refit: the window did not give a refit job")
    return job


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=7)
    ap.add_argument("--seed", type=int, default=21)
    args = ap.parse_args()
    job = last_job(args.seed)
    jobs = {"warm": dataclasses.replace(job, mode="warm"), "cold": dataclasses.replace(job, mode="cold")}
    for j in jobs.values():
        solve(j)  # compiled code and caches loaded before timing
    times: dict[str, list[float]] = {k: [] for k in jobs}
    for _ in range(args.repeats):
        for name, j in jobs.items():
            t0 = time.perf_counter()
            solve(j)
            times[name].append(time.perf_counter() - t0)
    print(f"{platform.processor() or platform.machine()}, {os.cpu_count()} cores, Python {platform.python_version()}; "
          f"load average {os.getloadavg()[0]:.2f}; window {len(job.y)} samples, {job.orders}")
    print(f"{'refit':6} {'median [s]':>11} {'min [s]':>9} {'ratio':>7}")
    ref = statistics.median(times["warm"])
    for name, ts in times.items():
        med = statistics.median(ts)
        print(f"{name:6} {med:11.4f} {min(ts):9.4f} {med / ref:7.1f}")


if __name__ == "__main__":
    main()
