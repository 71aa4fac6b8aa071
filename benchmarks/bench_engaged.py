#!/usr/bin/env python3
"""What the engaged flank costs: the CPU of a replay with ``detection.engaged_flank`` on and off.

On a shaft that showed backlash the service runs the backlash test every 6 s of a visit
(:mod:`online_id.monitoring.engaged`), in the worker process live, inline in a replay. This runs
``online-id evaluate``'s family (a) run (``stiffness -10 %``) of each plant with the flank on and off,
interleaved, and prints the process CPU time of each run, the median ratio on/off per plant, the number
of backlash tests and the CPU per test; and the warning delay of each, so the effect is shown beside the cost.

Usage::

    python benchmarks/bench_engaged.py [--plants 12701,11704,13701] [--repeats 3]

Run by hand (README, Benchmarks); OMP_NUM_THREADS=1 is set.
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import platform
import statistics
import sys
import time

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")


def main(argv: list[str] | None = None) -> int:
    from online_id.bench import evaluate as ev
    from online_id.diagnose import linearity

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--plants", default="12701,11704,13701", help="family (a) plant seeds (comma separated)")
    ap.add_argument("--repeats", type=int, default=3)
    args = ap.parse_args(argv)
    seeds = [int(x) for x in args.plants.split(",") if x.strip()]
    print(f"python {platform.python_version()}, {platform.machine()}, {os.cpu_count()} cpus; "
          f"{args.repeats} repeats, interleaved")
    # count the backlash tests and their CPU (inline worker: they run in this process)
    spent = {"n": 0, "cpu": 0.0}
    test = linearity.backlash_test

    def timed(*a, **k):
        t0 = time.process_time()
        try:
            return test(*a, **k)
        finally:
            spent["n"] += 1
            spent["cpu"] += time.process_time() - t0

    import online_id.service.pipeline as pipeline
    pipeline.backlash_test = timed
    print("| plant | backlash | run CPU on / off, median [s] | on / off | tests on / off | CPU per test [s] "
          "| warning delay on / off [s] |")
    print("|---|---|---:|---:|---:|---:|---:|")
    for seed in seeds:
        spec = ev.family_spec(seed, "stiffness -10 %", "a")
        base = ev.settings_for(spec)
        cpu = {True: [], False: []}
        tests = {True: 0, False: 0}
        per_test: list[float] = []
        delay = {}
        for _ in range(args.repeats):
            for on in (True, False):
                s = dataclasses.replace(base, detection=dataclasses.replace(base.detection, engaged_flank=on))
                spent.update(n=0, cpu=0.0)
                t0 = time.process_time()
                r = ev.run(spec, s)
                cpu[on].append(time.process_time() - t0)
                tests[on] = spent["n"]
                if spent["n"]:
                    per_test.append(spent["cpu"] / spent["n"])
                delay[on] = r.warning_delay_s
        gap = spec.scenario.effects.backlash
        on, off = statistics.median(cpu[True]), statistics.median(cpu[False])

        def d(x):
            return "missed" if x is None else f"{x:.1f}"

        print(f"| {seed} | {'%.2f mrad' % (1e3 * gap.gap_rad) if gap else 'none'} | {on:.2f} / {off:.2f} "
              f"| {on / off:.3f} | {tests[True]} / {tests[False]} "
              f"| {statistics.median(per_test) if per_test else float('nan'):.3f} "
              f"| {d(delay[True])} / {d(delay[False])} |", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
