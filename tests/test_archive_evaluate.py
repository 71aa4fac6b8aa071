"""`online-id evaluate` as Dask tasks: the same runs as the process pool, and the false-alarm rate per 1,000 hours
with its interval."""

import json

import pytest

from online_id.bench.evaluate import rate_per_1000h
from online_id.cli import main


@pytest.mark.parametrize("events, hours, low, high", [
    (0, 3000.0, 0.0, 1.2296),  # no false alarm in 3,000 h: at most 1.23 per 1,000 h (95 %)
    (5, 1000.0, 1.6235, 11.668),  # Garwood's interval of 5 events
    (1, 26.0, 0.9738, 214.3),
])
def test_the_false_alarm_rate_per_1000_hours_has_the_exact_poisson_interval(events, hours, low, high):
    got = rate_per_1000h(events, hours)
    assert got["false_alarms_per_1000h"] == pytest.approx(1000.0 * events / hours)
    assert got["false_alarms_per_1000h_ci"] == pytest.approx([low, high], rel=1e-3, abs=1e-9)
    assert rate_per_1000h(0, 0.0)["false_alarms_per_1000h_ci"] is None


@pytest.mark.slow
def test_evaluate_on_a_local_dask_cluster_gives_the_runs_of_the_process_pool(tmp_path, capsys):
    """One fault-free run of 72 s on each path, its whole record compared as each path hands it back (a fault
    run too, 228 s of bench with alarms and delays, took 21 CPU s more on each path: both runs are the same
    ``run_spec`` in a worker process, the paths differ only in how the task gets there and back)."""
    pytest.importorskip("distributed")
    args = ["evaluate", "--hours", "0.02", "--fault-plants", "0", "--jobs", "2"]
    assert main(args + ["--out", str(tmp_path / "pool")]) == 0
    assert main(args + ["--dask", "--out", str(tmp_path / "dask")]) == 0
    text = capsys.readouterr().out
    assert "per 1,000 h, 95 % interval" in text
    pool, dask = (json.loads((tmp_path / d / "results.json").read_text()) for d in ("pool", "dask"))

    def runs(doc):
        return [{k: v for k, v in r.items() if k != "elapsed_s"} for r in doc["runs"]]

    assert len(runs(pool)) == 1 and runs(dask) == runs(pool)
    f = dask["summary"]["fault_free"]
    assert f["false_alarms_per_1000h"] == pytest.approx(1000.0 * f["false_alarms"] / f["hours"])
    assert dask["summary"]["settings"]["dask"] == "local cluster, 2 workers"


@pytest.mark.slow
def test_evaluate_diagnose_cases_on_a_local_dask_cluster_are_the_process_pools(tmp_path):
    """The diagnosis evaluation's cases as Dask tasks give the cases of the process pool; a task that fails is a
    failed case on every path, never left out. One case that runs (12-16 CPU s on each path; a second case, of
    the structures family, compared nothing else) and, on the cluster, one that fails after it."""
    pytest.importorskip("distributed")
    from online_id.evaluation import diagnose_benches as ev

    jobs = [("sensor_delay", 41, "bench", ("no_demand",))]
    pool = ev.run_cases(jobs, 2)
    dask = ev.run_cases(jobs + [("no_such_kind", 1, "bench", ("no_demand",))], 2, dask=True)

    def same(r):
        return {k: ({kk: vv for kk, vv in v.items() if kk != "seconds"} if isinstance(v, dict) else v)
                for k, v in r.items() if k != "seconds"}

    assert len(dask) == 2 and [same(r) for r in dask[:1]] == [same(r) for r in pool], _differences(
        same(dask[0]), same(pool[0]))
    failed = dask[1]
    assert failed["kind"] == "no_such_kind" and "no_such_kind" in failed["no_demand"]["error"]


def _differences(a, b, path: str = "") -> list[str]:
    """Where two results differ (``path: a != b``), for the failure message."""
    if isinstance(a, dict) and isinstance(b, dict):
        return [d for k in sorted(set(a) | set(b), key=str)
                for d in (_differences(a[k], b[k], f"{path}/{k}") if k in a and k in b else [f"{path}/{k}: missing"])]
    if isinstance(a, list) and isinstance(b, list) and len(a) == len(b):
        return [d for i, (x, y) in enumerate(zip(a, b)) for d in _differences(x, y, f"{path}[{i}]")]
    return [] if a == b or (a != a and b != b) else [f"{path}: {a!r} != {b!r}"]
