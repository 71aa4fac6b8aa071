"""Microseconds per sample of the recursive ARMAX update, method by method.

Usage::

    python benchmarks/bench_recursive.py [--samples N] [--repeats R]

Methods, at na = nb = nc = 2, 4, 8, 16 (6 to 48 parameters):

* ``rels.update``   -- :class:`RecursiveArmax` ``update`` called per sample from Python;
* ``rels.block``    -- :class:`RecursiveArmax` ``update_block`` (numba loop);
* ``numpy``         -- a plain per-sample NumPy RELS (``np.outer``), defined below;
* ``filterpy``      -- :class:`KalmanArmax` ``update`` (filterpy ``KalmanFilter``).

The methods are interleaved within each repeat; the table reports the median
(and minimum) over repeats and the ratio of the median to ``numpy``.
"""

from __future__ import annotations

import argparse
import os
import platform
import statistics
import sys
import time
from collections.abc import Callable

import filterpy
import numba
import numpy as np
import scipy.signal as sig

from online_id.estimation.kalman import KalmanArmax
from online_id.estimation.model import ArmaxOrders
from online_id.estimation.rels import RecursiveArmax


class NumpyRels:
    """Straightforward per-sample RELS in NumPy (the reference for the ratios)."""

    def __init__(self, orders: ArmaxOrders, lam: float = 0.999, p0: float = 1e3) -> None:
        self.o = orders
        self.lam = lam
        n = orders.n_params
        self.theta = np.zeros(n)
        self.P = np.eye(n) * p0
        self.yh = np.zeros(orders.na)
        self.uh = np.zeros(orders.nk + orders.nb)
        self.eh = np.zeros(orders.nc)

    def update(self, y: float, u: float) -> float:
        o = self.o
        if self.uh.size:
            self.uh[1:] = self.uh[:-1]
            self.uh[0] = u
        phi = np.concatenate((-self.yh, self.uh[o.nk :], self.eh))
        e = y - phi @ self.theta  # e = y - phi^T theta
        Pphi = self.P @ phi
        K = Pphi / (self.lam + phi @ Pphi)  # K = P phi / (lam + phi^T P phi)
        self.theta += K * e  # theta += K e
        P = (self.P - np.outer(K, Pphi)) / self.lam  # P = (P - K phi^T P) / lam
        self.P = 0.5 * (P + P.T)
        eps = y - phi @ self.theta
        if self.yh.size:
            self.yh[1:] = self.yh[:-1]
            self.yh[0] = y
        if self.eh.size:
            self.eh[1:] = self.eh[:-1]
            self.eh[0] = eps
        return float(e)


def per_sample(update: Callable[[float, float], float], y: list[float], u: list[float]) -> None:
    for yt, ut in zip(y, u):
        update(yt, ut)


def machine() -> str:
    return (
        f"{platform.processor() or platform.machine()}, nproc={os.cpu_count()}, "
        f"Python {platform.python_version()}, numpy {np.__version__}, numba {numba.__version__}, "
        f"filterpy {filterpy.__version__}, {platform.system()} {platform.release()}"
    )


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--samples", type=int, default=20000, help="samples per timed run (default 20000)")
    parser.add_argument("--repeats", type=int, default=7, help="repeats per method (default 7)")
    parser.add_argument(
        "--slow-samples",
        type=int,
        default=None,
        help="samples per run for numpy and filterpy (default samples/4: they are slow)",
    )
    args = parser.parse_args(argv)
    n_fast = args.samples
    n_slow = args.slow_samples or max(args.samples // 4, 1)

    rng = np.random.default_rng(0)
    u = rng.standard_normal(n_fast)
    e = 0.1 * rng.standard_normal(n_fast)
    y = sig.lfilter([0, 1.0, 0.5], [1, -1.2, 0.5], u) + sig.lfilter([1, 0.3], [1, -1.2, 0.5], e)
    y_list, u_list = y.tolist(), u.tolist()

    methods = ["rels.update", "rels.block", "numpy", "filterpy"]
    rows = []
    for order in (2, 4, 8, 16):
        orders = ArmaxOrders(order, order, order)
        # warm-up (numba compile or cache load)
        RecursiveArmax(orders).update_block(y[:10], u[:10])
        RecursiveArmax(orders).update(1.0, 1.0)
        times: dict[str, list[float]] = {m: [] for m in methods}
        for _ in range(args.repeats):
            for m in methods:
                if m == "rels.update":
                    est = RecursiveArmax(orders)
                    t0 = time.perf_counter()
                    per_sample(est.update, y_list, u_list)
                    times[m].append((time.perf_counter() - t0) / n_fast)
                elif m == "rels.block":
                    est = RecursiveArmax(orders)
                    t0 = time.perf_counter()
                    est.update_block(y, u)
                    times[m].append((time.perf_counter() - t0) / n_fast)
                elif m == "numpy":
                    ref = NumpyRels(orders)
                    t0 = time.perf_counter()
                    per_sample(ref.update, y_list[:n_slow], u_list[:n_slow])
                    times[m].append((time.perf_counter() - t0) / n_slow)
                else:
                    kal = KalmanArmax(orders, lam=0.999)
                    t0 = time.perf_counter()
                    per_sample(kal.update, y_list[:n_slow], u_list[:n_slow])
                    times[m].append((time.perf_counter() - t0) / n_slow)
        stats = {m: (statistics.median(t) * 1e6, min(t) * 1e6) for m, t in times.items()}
        rows.append((orders.n_params, stats))

    print(f"Machine: {machine()}")
    print(
        f"Samples per run: {n_fast} (rels), {n_slow} (numpy, filterpy); "
        f"repeats: {args.repeats}; cells: median (min) us/sample"
    )
    print()
    ratio_heads = [f"{m} / numpy" for m in methods if m != "numpy"]
    print("| params | " + " | ".join(methods + ratio_heads) + " |")
    print("|---:|" + "---:|" * (2 * len(methods) - 1))
    for n, res in rows:
        ref = res["numpy"][0]
        cells = [f"{res[m][0]:.2f} ({res[m][1]:.2f})" for m in methods]
        ratios = [f"{res[m][0] / ref:.3f}" for m in methods if m != "numpy"]
        print(f"| {n} | " + " | ".join(cells) + " | " + " | ".join(ratios) + " |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
