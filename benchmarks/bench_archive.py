"""Throughput of `online-id archive identify` against the workers, the overhead per task, the table's identity.

Runs the same recordings (the first N of an archive, by default a fresh simulated one) into a new table on:

* a LocalCluster of 1 worker process,
* a LocalCluster of 2 worker processes,
* a `dask scheduler` with 2 `dask worker` processes started as separate processes on loopback,

and reports for each the wall time (without the cluster's start), recordings per minute, the CPU and wall time
the tasks spent inside the workers, and the overhead per task: ``(wall x workers - sum of task wall) / tasks``
(scheduling, transfer, pickling, and the workers' idle time at the tail).  A batch of trivial tasks gives
Dask's own overhead per task.  The three tables must be byte-identical (results.csv).

    OMP_NUM_THREADS=1 .venv/bin/python benchmarks/bench_archive.py [--archive DIR] [--recordings 40]
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from online_id.archive import batch
from online_id.archive.runner import cluster, map_tasks
from online_id.archive.store import CSV
from online_id.config import load_config


def _noop(x: int) -> int:
    return x


def measure(label: str, files: list[str], out: Path, scheduler: str | None, workers: int, s) -> dict:
    with cluster(scheduler, workers) as client:
        n_workers = len(client.scheduler_info(n_workers=-1)["workers"])
        t0 = time.perf_counter()
        noop = map_tasks(client, _noop, list(range(500)), quiet=True)
        t_noop = time.perf_counter() - t0
        t0 = time.perf_counter()
        summary = batch.run(files, out, "identify", s, client, quiet=True)
        wall = time.perf_counter() - t0
    tasks = [o for o in summary.outcomes if o.ok]
    task_wall = sum(o.wall_s for o in tasks)
    task_cpu = sum(o.cpu_s for o in tasks)
    n = max(len(summary.outcomes), 1)
    res = {"label": label, "workers": n_workers, "recordings": len(files), "tasks": len(summary.outcomes),
           "wall_s": round(wall, 2), "recordings_per_min": round(60.0 * len(files) / wall, 1),
           "task_wall_s": round(task_wall, 2), "task_cpu_s": round(task_cpu, 2),
           "overhead_per_task_s": round((wall * n_workers - task_wall) / n, 3),
           "noop_overhead_per_task_ms": round(1000.0 * t_noop / len(noop), 2), "failed": summary.failed,
           "lost": summary.lost}
    print(json.dumps(res), flush=True)
    return res


def external(tmp: Path) -> tuple[str, list[subprocess.Popen]]:
    dask = str(Path(sys.executable).parent / "dask")
    env = dict(os.environ, OMP_NUM_THREADS="1", OPENBLAS_NUM_THREADS="1")
    file = tmp / "scheduler.json"
    procs = [subprocess.Popen([dask, "scheduler", "--host", "127.0.0.1", "--port", "0", "--no-dashboard",
                               "--scheduler-file", str(file)], env=env, stderr=subprocess.DEVNULL)]
    while not (file.exists() and file.stat().st_size):
        time.sleep(0.1)
    for name in ("wa", "wb"):
        procs.append(subprocess.Popen([dask, "worker", "--scheduler-file", str(file), "--nthreads", "1",
                                       "--no-dashboard", "--name", name, "--host", "127.0.0.1"], env=env,
                                      stderr=subprocess.DEVNULL))
    address = json.loads(file.read_text())["address"]
    from distributed import Client

    with Client(address) as c:
        c.wait_for_workers(2, timeout=120)
    return address, procs


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--archive", type=Path, help="archive directory (default: simulate one of --recordings)")
    p.add_argument("--recordings", type=int, default=40)
    p.add_argument("--config", help="YAML config of the identification")
    args = p.parse_args()
    s = load_config(args.config)
    with tempfile.TemporaryDirectory() as d:
        tmp = Path(d)
        root = args.archive
        if root is None:
            root = tmp / "archive"
            subprocess.run([sys.executable, "-m", "online_id", "archive", "simulate", str(root), "--benches", "6",
                            "--recordings", str(args.recordings), "--quiet"], check=True)
        files = batch.expand([str(root)])[: args.recordings]
        print(f"{len(files)} recordings of {root}; CPU: {_cpu()}", flush=True)
        results = [measure("LocalCluster, 1 worker", files, tmp / "r1", None, 1, s),
                   measure("LocalCluster, 2 workers", files, tmp / "r2", None, 2, s)]
        address, procs = external(tmp)
        try:
            results.append(measure("dask scheduler + 2 dask worker processes", files, tmp / "r3", address, 2, s))
        finally:
            for q in procs:
                q.terminate()
                q.wait()
        tables = [(tmp / r / CSV).read_bytes() for r in ("r1", "r2", "r3")]
        print(f"tables identical: {tables[0] == tables[1] == tables[2]} ({len(tables[0])} bytes)")
        return 0 if tables[0] == tables[1] == tables[2] else 1


def _cpu() -> str:
    try:
        return next(line.split(":", 1)[1].strip() for line in open("/proc/cpuinfo") if line.startswith("model name"))
    except (OSError, StopIteration):
        return "unknown"


if __name__ == "__main__":
    raise SystemExit(main())
