"""The archive on Dask (online_id.archive, `online-id archive`): a LocalCluster of processes, a scheduler and two
workers as separate processes with one killed mid-batch, the client killed mid-run and the re-run completing
the table with each recording once; failures as rows; the table the same whatever the workers."""

import datetime as dt
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("distributed")
pytest.importorskip("pyarrow")

from online_id.archive import batch  # noqa: E402
from online_id.archive.metadata import BenchMap, MetaRules, resolve  # noqa: E402
from online_id.archive.runner import cluster, map_tasks  # noqa: E402
from online_id.archive.store import CSV, PARTS, ResultStore, read_rows  # noqa: E402
from online_id.archive.table import blank_row  # noqa: E402
from online_id.cli import main  # noqa: E402
from online_id.config import load_config  # noqa: E402
from online_id.errors import ConfigError, InputDataError  # noqa: E402

CONFIG = "identification:\n  na: [8]\n"  # one model order: short recordings, fast tests
N_RECORDINGS = 6


@pytest.fixture(scope="session")
def archive(tmp_path_factory):
    """A small simulated archive (2 benches, 6 recordings of 3 x 12 s) and two files that fail."""
    from online_id.archive.simulated import WriteJob, write_one, write_truth
    from online_id.bench.archive_sim import plan_archive

    root = tmp_path_factory.mktemp("archive")
    plan = plan_archive(2, 6.0, N_RECORDINGS, seed=3, dwell_s=12.0)
    for r in plan.recordings:
        write_one(WriteJob(str(root / "recordings"), r))
    write_truth(plan, root)
    bad = root / "recordings" / "bad"
    bad.mkdir()
    (bad / "bench9_20250301T080000.mf4").write_bytes(b"MDF     4.10    " + bytes(200))  # cut short
    t = np.arange(2000) / 1000.0
    (bad / "bench9_20250302T080000.csv").write_text(  # no excitation: a constant torque
        "time_s,dyno_speed_rpm,engine_speed_rpm,dyno_torque_nm\n" + "".join(f"{x:.3f},1500,1500,10\n" for x in t))
    (root / "config.yaml").write_text(CONFIG)
    return root


def settings(archive):
    return load_config(str(archive / "config.yaml"))


def recordings(archive):
    return batch.expand([str(archive / "recordings")])


@pytest.fixture(scope="session")
def reference(archive, tmp_path_factory):
    """The table of a run on a LocalCluster of one worker process."""
    out = tmp_path_factory.mktemp("reference") / "results"
    with cluster(workers=1) as client:
        summary = batch.run(recordings(archive), out, "identify", settings(archive), client, quiet=True)
    return out, summary


def by_recording(rows):
    out = {}
    for r in rows:
        out.setdefault(r["path"], []).append(r)
    return out


def test_metadata_comes_from_the_mapping_the_header_or_the_path(tmp_path):
    when = dt.datetime(2025, 3, 4, 7, 30, tzinfo=dt.timezone.utc)
    m = resolve("/data/tb/bench07/run_20250301T101500.mf4", MetaRules(), when, {"test_bed": "TB-3"})
    assert (m.bench, m.bench_source, m.start_time, m.start_source) == ("TB-3", "mdf header", when, "mdf header")
    m = resolve("/data/tb/bench07/run_20250301T101500.mf4", MetaRules())
    assert (m.bench, m.bench_source, m.start_source) == ("07", "path", "file name")
    assert m.start_time == dt.datetime(2025, 3, 1, 10, 15, tzinfo=dt.timezone.utc)
    m = resolve("/data/cell4/run.csv", MetaRules())
    assert (m.bench, m.bench_source, m.start_time, m.start_source) == ("cell4", "directory", None, "unknown")
    mapping = tmp_path / "benches.csv"
    mapping.write_text("pattern,bench,start_time\n*/cell4/*,B04,2025-02-01T06:00:00\n*bench07*,B07,\n")
    rules = MetaRules(BenchMap.load(mapping))
    m = resolve("/data/cell4/run.csv", rules, when, {"bench": "X"})
    assert (m.bench, m.bench_source, m.start_source) == ("B04", "mapping", "mapping")
    m = resolve("/data/tb/bench07/run.mf4", rules, when)
    assert (m.bench, m.bench_source, m.start_time, m.start_source) == ("B07", "mapping", when, "mdf header")
    mapping.write_text("pattern,bench,start_time\n*,B1,2025-02-30\n")
    with pytest.raises(InputDataError, match=r"benches.csv, line 2, column start_time: expected an ISO 8601"):
        BenchMap.load(mapping)
    mapping.write_text("pattern,where\n")
    with pytest.raises(InputDataError, match=r"line 1: expected the columns pattern,bench"):
        BenchMap.load(mapping)
    with pytest.raises(ConfigError, match=r"needs a named group"):
        MetaRules(bench_pattern="bench(\\d+)")


def test_the_store_appends_parts_reads_each_row_once_and_refuses_a_second_writer(tmp_path):
    rows = [blank_row(path=f"/r/{k}.mf4", sha256=f"h{k}", segment=0, op_index=i, bench="B1", status="ok",
                      f0_hz=20.0 + k, start_time=dt.datetime(2025, 1, 1 + k, tzinfo=dt.timezone.utc))
            for k in range(3) for i in range(2)]
    about = {"mode": "identify", "settings": "abc"}
    with ResultStore(tmp_path / "res", about, flush_s=1e9) as store:
        store.add(rows[:2])
        store.flush()
        store.add(rows[2:4] + rows[:2])  # a recording written twice (a run killed after its part was written)
        with pytest.raises(InputDataError, match="another online-id archive run is writing this table"):
            with ResultStore(tmp_path / "res", about):
                pass
    assert len(list((tmp_path / "res" / PARTS).glob("*.parquet"))) == 2
    # a run killed while it wrote a part leaves that part's temporary file: never read, and removed by the
    # next run that opens the table
    stale = tmp_path / "res" / PARTS / ".part-20261208T010528-3947-00002.soo35qqi.partial.parquet"
    stale.write_bytes(b"PAR1 cut short")
    got = read_rows(tmp_path / "res")
    assert [(r["sha256"], r["op_index"]) for r in got] == [("h0", 0), ("h0", 1), ("h1", 0), ("h1", 1)]
    with ResultStore(tmp_path / "res", about) as store:
        assert not stale.exists()
        store.add(rows[4:])
        merged = store.compact()
    assert len(merged) == 6 and not list((tmp_path / "res" / PARTS).glob("*.parquet"))
    assert read_rows(tmp_path / "res" / CSV) == read_rows(tmp_path / "res")
    with pytest.raises(ConfigError, match="this table was made with settings 'abc'"):
        with ResultStore(tmp_path / "res", {"mode": "identify", "settings": "xyz"}):
            pass


def test_the_runner_keeps_submission_order_and_turns_failures_into_outcomes():
    before = dict(os.environ)
    with cluster(workers=2) as client:
        outs = map_tasks(client, _square_or_fail, list(range(7)), quiet=True)
        # the workers run with glibc's own trim threshold, not Dask's eager one (it costs the fits CPU)
        trim = client.run(os.environ.get, "MALLOC_TRIM_THRESHOLD_")
    assert set(trim.values()) == {None}
    assert dict(os.environ) == before  # the nannies' pre-spawn variables (PYTHONHASHSEED) are not left behind
    assert [o.index for o in outs] == list(range(7))
    assert [o.value for o in outs if o.ok] == [0, 1, 4, 16, 25, 36]
    bad = outs[3]
    assert not bad.ok and not bad.lost and bad.error == "ValueError: three is not wanted here"
    assert len({o.worker for o in outs}) == 2  # both worker processes took tasks


def _square_or_fail(x):
    if x == 3:
        raise ValueError("three is not\nwanted here")
    time.sleep(0.2)
    return x * x


@pytest.mark.slow
def test_archive_identify_on_a_local_cluster(archive, reference, tmp_path):
    out, summary = reference
    files = recordings(archive)
    assert summary.recordings == N_RECORDINGS + 2 and summary.failed == 2 and summary.lost == 0
    rows = read_rows(out)
    per = by_recording(rows)
    assert sorted(per) == sorted(files)  # every recording once, the failures too
    truth = {str(archive / "recordings" / r["file"]): r for r in
             __import__("json").loads((archive / "truth.json").read_text())["recordings"]}
    for path, rs in per.items():
        if "bad" in path:
            (r,) = rs
            assert r["status"] == "error" and r["error"].startswith(path) and "\n" not in r["error"]
            assert r["bench"] == "9" and r["bench_source"] == "path"
            continue
        assert [r["op_index"] for r in rs] == [0, 1, 2] and {r["status"] for r in rs} == {"ok"}
        t = truth[path]
        assert rs[0]["bench"] == t["bench"] and rs[0]["bench_source"] == "mdf header"
        assert rs[0]["start_time"] == dt.datetime.fromisoformat(t["start"])
        for r in rs:
            assert abs(r["f0_hz"] / t["f0_hz"] - 1.0) < 0.01
            assert 0.0 < r["f0_std_hz"] < 0.05 * r["f0_hz"] and 0.0 < r["zeta_std"] < r["zeta"]
            assert r["c_s"] > 0 and r["c_s_std"] is None and r["d_s_std"] is None
            assert r["op_time"] == r["start_time"] + dt.timedelta(seconds=r["t_start_s"])
    errs = {Path(r["path"]).suffix: r["error"] for r in rows if r["status"] == "error"}
    assert "no excitation" in errs[".csv"] and "cannot read the MDF 4 file" in errs[".mf4"]
    # a re-run reads nothing again; a copy under another name is one duplicate row
    copy = archive / "copy"
    copy.mkdir(exist_ok=True)
    shutil.copy2(files[0], copy / "same.mf4")
    target = tmp_path / "again"
    shutil.copytree(out, target)
    with cluster(workers=2) as client:
        again = batch.run(files + [str(copy / "same.mf4")], target, "identify", settings(archive), client,
                          quiet=True)
    assert (again.skipped, again.duplicates, again.tasks) == (N_RECORDINGS + 2, 1, 0)
    rows2 = read_rows(target)
    dup = [r for r in rows2 if r["status"] == "duplicate"]
    assert len(dup) == 1 and dup[0]["error"] == f"same content as {files[0]}"
    assert [r for r in rows2 if r["status"] != "duplicate"] == rows
    with pytest.raises(ConfigError, match="this table was made with mode 'identify'"):
        with cluster(workers=1) as client:
            batch.run(files[:1], target, "diagnose", settings(archive), client, quiet=True)


def _dask(*args):
    return [str(Path(sys.executable).parent / "dask"), *args]


@pytest.fixture
def scheduler(tmp_path):
    """A `dask scheduler` and two `dask worker` processes (no nanny: a killed worker stays dead) on loopback."""
    env = dict(os.environ, OMP_NUM_THREADS="1", OPENBLAS_NUM_THREADS="1")
    file = tmp_path / "scheduler.json"
    procs = [subprocess.Popen(_dask("scheduler", "--host", "127.0.0.1", "--port", "0", "--no-dashboard",
                                    "--scheduler-file", str(file)), env=env,
                              stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)]
    try:
        for _ in range(300):
            if file.exists() and file.stat().st_size:
                break
            time.sleep(0.1)
        for name in ("wa", "wb"):
            procs.append(subprocess.Popen(_dask("worker", "--scheduler-file", str(file), "--nthreads", "1",
                                                "--no-nanny", "--no-dashboard", "--name", name,
                                                "--host", "127.0.0.1"), env=env,
                                          stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL))
        import json

        address = json.loads(file.read_text())["address"]
        from distributed import Client

        with Client(address, timeout="30s") as c:
            c.wait_for_workers(2, timeout=120)
        yield address, procs
    finally:
        # (a scheduler that lost a worker may take 20 s and more to close itself: its close is not under test)
        for p in reversed(procs):
            if p.poll() is None:
                p.terminate()
        deadline = time.monotonic() + 5.0
        for p in procs:
            try:
                p.wait(timeout=max(deadline - time.monotonic(), 0.1))
            except subprocess.TimeoutExpired:
                p.kill()
                p.wait()


@pytest.mark.slow
def test_a_worker_killed_mid_batch_and_the_client_killed_mid_run(archive, reference, scheduler, tmp_path):
    address, procs = scheduler
    files = recordings(archive)
    ref = (reference[0] / CSV).read_bytes()

    # 1. one of the two workers is killed once the first recording is done: its tasks go to the other
    killed = []

    def kill_b(_outcome):
        if not killed:
            procs[2].send_signal(signal.SIGKILL)
            killed.append(True)

    out = tmp_path / "killed_worker"
    with cluster(address) as client:
        summary = batch.run(files, out, "identify", settings(archive), client, quiet=True, flush_s=0.0,
                            on_task=kill_b)
    assert killed and procs[2].wait(timeout=10) == -signal.SIGKILL
    if summary.lost:  # the scheduler gave up on a task: the re-run does it
        with cluster(address) as client:
            summary = batch.run(files, out, "identify", settings(archive), client, quiet=True)
        assert summary.lost == 0 and summary.tasks >= 1
    assert (out / CSV).read_bytes() == ref  # each recording once, the same rows as one local worker gave

    # 2. the client is killed mid-run (SIGKILL: no clean-up); the re-run completes the table
    out2 = tmp_path / "killed_client"
    cmd = [sys.executable, "-m", "online_id", "archive", "identify", str(archive / "recordings"), "--out", str(out2),
           "--scheduler", address, "--config", str(archive / "config.yaml"), "--flush-seconds", "0", "--quiet"]
    run = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    deadline = time.monotonic() + 120
    while time.monotonic() < deadline and len(list((out2 / PARTS).glob("*.parquet"))) < 3:
        time.sleep(0.05)
    run.send_signal(signal.SIGKILL)
    assert run.wait(timeout=10) == -signal.SIGKILL
    partial = read_rows(out2)
    assert 0 < len(by_recording(partial)) < N_RECORDINGS + 2
    assert main(["archive", "identify", str(archive / "recordings"), "--out", str(out2), "--scheduler", address,
                 "--config", str(archive / "config.yaml"), "--quiet"]) == 0
    assert (out2 / CSV).read_bytes() == ref
    rows = read_rows(out2)
    assert len(rows) == len({(r["sha256"] or r["path"], r["segment"], r["op_index"]) for r in rows})


def test_the_service_and_the_offline_commands_run_without_dask(tmp_path):
    """With dask, distributed and pyarrow hidden, the rest imports and runs; archive says what to install."""
    code = (
        "import sys, importlib.abc\n"
        "class Hide(importlib.abc.MetaPathFinder):\n"
        "    def find_spec(self, name, path=None, target=None):\n"
        "        if name.split('.')[0] in ('dask', 'distributed', 'pyarrow'):\n"
        "            raise ImportError(f'No module named {name!r}', name=name)\n"
        "sys.meta_path.insert(0, Hide())\n"
        "import online_id.service.live, online_id.service.pipeline, online_id.cli.identify, online_id.cli.diagnose\n"
        "import online_id.cli.evaluate, online_id.cli.replay, online_id.cli.trend, online_id.cli.archive\n"
        "import online_id.archive.runner, online_id.archive.trend, online_id.archive.table\n"
        "from online_id.cli import main\n"
        "rc1 = main(['archive', 'identify', sys.argv[1], '--out', sys.argv[2]])\n"
        "rc2 = main(['trend', sys.argv[2], '--out', sys.argv[2]])\n"
        "print('RC', rc1, rc2, [m for m in sys.modules if m.split('.')[0] in ('dask', 'distributed', 'pyarrow')])\n"
    )
    res = subprocess.run([sys.executable, "-c", code, str(tmp_path), str(tmp_path / "out")], capture_output=True,
                         text=True, timeout=120)
    assert res.stdout.strip().splitlines()[-1] == "RC 2 2 []", res.stderr
    errs = res.stderr.strip().splitlines()
    assert errs[0].startswith("error: this command runs on Dask, which is not installed")
    assert "pip install 'online-id[archive]'" in errs[0]
    assert errs[1].startswith("error: the results table needs pyarrow") and len(errs) == 2


@pytest.mark.slow
def test_a_long_recording_is_cut_into_segments_each_a_task(archive, tmp_path):
    """The windows of :func:`segments`, and one window identified as its own task (in this process)."""
    from online_id.archive import recording as rec

    assert rec.segments((0.0, 80.0), 60.0) == [None]  # up to 1.5 segments: whole
    assert rec.segments((0.0, 100.0), 60.0) == [(0.0, 50.0), (50.0, 100.0)]
    assert rec.segments((0.0, 100.0), None) == [None]
    assert rec.segments((10.0, 190.0), 60.0) == [(10.0, 70.0), (70.0, 130.0), (130.0, 190.0)]
    import dataclasses

    from online_id.bench.scenario import BenchScenario, OperatingPoint
    from online_id.bench.simulate import simulate_bench
    from online_id.io.mdf_header import write_recording

    sc = dataclasses.replace(BenchScenario(), seed=5, operating_points=tuple(
        OperatingPoint(s, 12.0) for s in (1200.0, 2000.0, 1500.0, 2400.0)))  # 4 points, 57 s
    cols = simulate_bench(sc).columns()
    path = str(tmp_path / "long.mf4")
    write_recording(path, cols["time_s"], {k: (cols[k], u) for k, u in (("dyno_speed_rpm", "rpm"), (
        "engine_speed_rpm", "rpm"), ("dyno_torque_nm", "Nm"))}, start_time=dt.datetime.now(dt.timezone.utc))
    p = rec.probe(rec.ProbeJob(path, MetaRules(), settings(archive), segment_s=25.0))
    assert p.error is None and len(p.sha256) == 64 and p.span_s[1] > 50.0
    windows = rec.segments(p.span_s, 25.0)
    assert len(windows) == 2
    rows = rec.process(rec.Job(p, "identify", settings(archive), 1, 2, windows[1]))
    assert {(r["segment"], r["segments"], r["segment_t0_s"]) for r in rows} == {(1, 2, windows[1][0])}
    assert all(windows[1][0] <= r["t_start_s"] < r["t_end_s"] <= windows[1][1] + 1e-3 for r in rows)
    assert {r["status"] for r in rows} == {"ok"} and len(rows) == 2, rows[0]["error"]


@pytest.mark.slow
def test_archive_diagnose_adds_the_effects_of_online_id_diagnose(archive, reference, tmp_path, capsys):
    from online_id.archive.table import effects_text
    from online_id.diagnose.bench_diagnosis import diagnose_bench
    from online_id.ingest.bench_series import bench_series

    path = recordings(archive)[0]
    rc = main(["archive", "diagnose", path, "--out", str(tmp_path / "d"), "--workers", "1", "--quiet",
               "--config", str(archive / "config.yaml")])
    assert rc == 0 and "1 tasks run (1 identified, 0 failed, 0 lost)" in capsys.readouterr().out
    rows = read_rows(tmp_path / "d")
    ident = [r for r in read_rows(reference[0]) if r["path"] == path]
    assert [r["f0_hz"] for r in rows] == [r["f0_hz"] for r in ident]  # the same identification
    doc = diagnose_bench(bench_series(Path(path), settings(archive)), na=6, nb=6, max_effects=3).as_dict()
    assert {r["diagnosis"] for r in rows} == {doc["result"]}
    kinds = [e["kind"] for e in doc["effects"]]
    assert all(r["mode"] == "diagnose" for r in rows)
    assert rows[0]["effects"] == effects_text(doc["effects"])  # every effect, as diagnose --json names it
    assert all(k in (rows[0]["effects"] or "") for k in kinds)
