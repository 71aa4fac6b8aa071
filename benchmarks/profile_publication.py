"""Where a publishing frame's CPU time goes: the live loop's work on it, step by step, in-process.

Usage::

    python benchmarks/profile_publication.py [--seconds 40] [--unpaced] [--inline]

The frames of ``bench_live``'s simulated bench go through ``Runtime`` as the
live loop takes them (``publications`` -> ``first_frame`` -> ``frames`` ->
``finish``), paced at real time (the process sleeps until a frame is due, so
that the caches go cold between publications as in the service), with the
service's worker process (``--inline``: the inline worker, replay's schedule).
For every frame that publishes, the loop thread's CPU time
(``time.thread_time_ns``) of the pipeline up to the publication's estimate and
of packing its OidEstimate, and of these the steps: decoding, assembly, the
model's update, the estimate and, in it, the roots of A, the poles, the
recursive model's polynomials and the candidate poles.  The timers around the
steps add about a microsecond each.  No bus: ``bench_live`` measures the
service with its sends.

To compare two versions of the code side by side, run it alternately from
each checkout (``cd /tmp && PYTHONPATH=OTHER_CHECKOUT python
THIS_CHECKOUT/benchmarks/profile_publication.py``), several times each.
"""

from __future__ import annotations

import argparse
import gc
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT.parent / "tests" / "live"))

from bench_live import _bench  # noqa: E402
from harness import live_settings  # noqa: E402
from machine import machine_line  # noqa: E402

import online_id.estimation.online as online  # noqa: E402
from online_id.service.offload import InlineWorker, ProcessWorker  # noqa: E402
from online_id.service.runtime import Runtime  # noqa: E402

STEPS = ("decode", "assemble", "update", "estimate", "roots", "poles", "recursive polynomials", "candidates")


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--seconds", type=float, default=40.0)
    ap.add_argument("--unpaced", action="store_true", help="frames back to back (warm caches)")
    ap.add_argument("--inline", action="store_true", help="the inline worker (replay's schedule)")
    args = ap.parse_args()
    print(f"machine: {machine_line()}; code: {Path(online.__file__).parents[2]}", flush=True)
    record, frames = _bench(args.seconds)
    worker = InlineWorker() if args.inline else ProcessWorker()
    rt = Runtime(live_settings(record.truth), worker=worker)
    rt.pipeline.warm_up()
    cpu = time.thread_time_ns
    spent: dict[str, int] = {}

    def timed(owner, name: str, step: str) -> None:
        f = getattr(owner, name)

        def wrapper(*a, **k):
            c0 = cpu()
            try:
                return f(*a, **k)
            finally:
                spent[step] = spent.get(step, 0) + cpu() - c0

        setattr(owner, name, wrapper)

    p = rt.pipeline
    for owner, name, step in ((rt.decoder, "decode", "decode"), (p.assembler, "push", "assemble"),
                              (p.estimator, "update", "update"), (p.estimator, "estimate", "estimate"),
                              (online, "polynomial_roots", "roots"), (online, "poles_of_roots", "poles"),
                              (p.estimator.rels, "polynomials", "recursive polynomials"),
                              (p.estimator, "_candidates", "candidates")):
        timed(owner, name, step)
    rows = []
    gc.freeze()
    t0, ts0 = time.perf_counter(), frames[0][0]
    try:
        for t, ident, data in frames:
            ahead = t - ts0 - (time.perf_counter() - t0)
            if not args.unpaced and ahead > 2e-4:
                time.sleep(ahead)
            spent.clear()
            c0 = cpu()
            pubs = rt.publications(t, ident, data)
            if pubs:
                c1 = cpu()
                rt.first_frame(pubs[0])
                c2 = cpu()
                rows.append([c1 - c0, c2 - c1] + [spent.get(s, 0) for s in STEPS])
                rt.frames(pubs, skip_first=True)
            more = rt.finish()
            if more:
                rt.frames(more)
    finally:
        worker.close()
    r = np.array(rows, dtype=float) / 1e3
    print(f"{len(r)} publications, {'paced at real time' if not args.unpaced else 'unpaced'}, "
          f"{'inline worker' if args.inline else 'worker process'}; CPU time [us]")
    print(f"{'':24s} {'p50':>7s} {'p90':>7s} {'p99':>7s} {'max':>7s}")
    for k, name in enumerate(("pipeline to the estimate", "encoding the OidEstimate") + STEPS):
        x = r[:, k]
        print(f"{name:24s} {np.percentile(x, 50):7.1f} {np.percentile(x, 90):7.1f} {np.percentile(x, 99):7.1f} "
              f"{x.max():7.1f}")
    total = r[:, 0] + r[:, 1]
    print(f"{'both':24s} {np.percentile(total, 50):7.1f} {np.percentile(total, 90):7.1f} "
          f"{np.percentile(total, 99):7.1f} {total.max():7.1f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
