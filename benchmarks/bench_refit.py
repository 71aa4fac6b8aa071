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

Each is timed twice, interleaved: with the trust-region iteration the fits use
(:mod:`online_id.estimation.trust_region`: scipy's ``trf`` steps, each step's
subproblem from a QR factorisation) and with ``scipy.optimize.least_squares(method="trf")``
itself (an SVD per step), to show what the QR saves. The table gives the median and
the minimum over the repeats, the ratio of the medians to the warm refit's, and the
ratio of scipy's median to the QR's for the same refit.
"""

from __future__ import annotations

import argparse
import dataclasses
import statistics
import time

import numpy as np
from scipy.optimize import least_squares

from online_id.bench.scenario import BenchScenario, OperatingPoint
from online_id.bench.simulate import simulate_bench
from online_id.estimation.model import ArmaxOrders
from online_id.estimation.online import OnlineDriveline
from online_id.estimation import pem
from online_id.estimation.trust_region import LsqResult, trust_region_lsq
from online_id.estimation.window import solve

from machine import machine_line  # (benchmarks/machine.py, beside this script)


def scipy_trf(fun, jac, x0, *, ftol, xtol, gtol, max_nfev):
    """The same minimisation by scipy's ``least_squares(method="trf")`` (an SVD of the Jacobian per step)."""
    r = least_squares(fun, x0, jac=jac, method="trf", x_scale="jac", ftol=ftol, xtol=xtol, gtol=gtol,
                      max_nfev=max_nfev)
    return LsqResult(x=r.x, cost=float(r.cost), status=int(r.status), nfev=int(r.nfev), njev=int(r.njev))


def timed(job, minimiser) -> float:
    pem.trust_region_lsq = minimiser
    try:
        t0 = time.perf_counter()
        solve(job)
        return time.perf_counter() - t0
    finally:
        pem.trust_region_lsq = trust_region_lsq


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
    minimisers = {"qr": trust_region_lsq, "scipy": scipy_trf}
    for j in jobs.values():
        for m in minimisers.values():
            timed(j, m)  # compiled code and caches loaded before timing
    times: dict[tuple[str, str], list[float]] = {(k, m): [] for k in jobs for m in minimisers}
    for _ in range(args.repeats):
        for name, j in jobs.items():
            for m, fn in minimisers.items():
                times[name, m].append(timed(j, fn))
    print(f"{machine_line()}; window {len(job.y)} samples, {job.orders}")
    print(f"{'refit':6} {'solver':7} {'median [s]':>11} {'min [s]':>9} {'/ warm':>7} {'scipy / qr':>11}")
    ref = statistics.median(times["warm", "qr"])
    for (name, m), ts in times.items():
        med = statistics.median(ts)
        gain = f"{statistics.median(times[name, 'scipy']) / med:11.2f}" if m == "qr" else ""
        print(f"{name:6} {m:7} {med:11.4f} {min(ts):9.4f} {med / ref:7.1f} {gain}")

if __name__ == "__main__":
    main()
