"""The workers that take slow work off the receive path: same contract inline and in a process."""

from __future__ import annotations

import dataclasses
import hashlib
import os
import signal
import time

import numpy as np
import pytest

from online_id.bench.scenario import BenchScenario, OperatingPoint
from online_id.bench.simulate import simulate_bench
from online_id.config import InertiaSettings, ModelSettings, Settings
from online_id.service.offload import InlineWorker, ProcessWorker
from online_id.service.pipeline import Pipeline, run_bench_data


def _square(x: float) -> float:
    return x * x


def _fail(x: float) -> float:
    raise ValueError(f"no square for {x}")


def _sleep(s: float) -> float:
    time.sleep(s)
    return s


def _wait(worker, results: list, n: int, timeout_s: float = 60.0) -> None:
    deadline = time.monotonic() + timeout_s
    while len(results) < n and time.monotonic() < deadline:
        worker.poll()
        time.sleep(0.005)
    assert len(results) == n, results


@pytest.fixture(params=["inline", "process"])
def worker(request):
    w = InlineWorker() if request.param == "inline" else ProcessWorker()
    yield w
    w.close()


def test_results_and_errors_come_back_through_the_callback(worker) -> None:
    results: list = []
    for x in (2.0, 3.0):
        worker.submit("a", _square, (x,), lambda r, e: results.append((r, e)))
        _wait(worker, results, len(results) + 1 if worker.asynchronous else len(results))
    worker.submit("a", _fail, (7.0,), lambda r, e: results.append((r, e)))
    _wait(worker, results, 3)
    assert results[:2] == [(4.0, None), (9.0, None)]
    assert results[2][0] is None and "ValueError: no square for 7.0" in results[2][1] and "\n" not in results[2][1]
    assert worker.stats.submitted["a"] == 3 and worker.stats.failed["a"] == 1


def test_one_job_per_lane_and_lanes_are_independent() -> None:
    worker = ProcessWorker()
    try:
        results: list = []
        worker.submit("slow", _sleep, (0.3,), lambda r, e: results.append(("slow", r)))
        assert worker.busy("slow") and not worker.busy("fast")
        with pytest.raises(RuntimeError, match="busy"):
            worker.submit("slow", _sleep, (0.0,), lambda r, e: None)
        worker.submit("fast", _square, (4.0,), lambda r, e: results.append(("fast", r)))
        _wait(worker, results, 2)
        assert results == [("slow", 0.3), ("fast", 16.0)]  # one child: first in, first out
        assert not worker.busy("slow") and not worker.busy("fast")
    finally:
        worker.close()


def _digest(data: np.ndarray) -> str:
    return hashlib.sha256(data.tobytes()).hexdigest()


def test_a_large_job_is_handed_over_without_waiting_for_the_child() -> None:
    """submit returns at once while the child runs another lane's job, however large the job: a job larger
    than the socket holds (the backlash test's rows are 380 KB) once held the receive loop in a blocking write
    until the child had finished its refit (5 s on a loaded machine, 5,000 frames dropped). The job's bytes
    arrive whole, and its arguments are those of the moment of submit."""
    worker = ProcessWorker()
    try:
        results: list = []
        worker.submit("slow", _sleep, (3.0,), lambda r, e: results.append(("slow", r, e)))
        data = np.random.default_rng(7).integers(0, 256, 24 << 20, dtype=np.uint8)  # 24 MiB: more than any buffer
        expected = _digest(data)
        t0 = time.perf_counter()
        worker.submit("big", _digest, (data,), lambda r, e: results.append(("big", r, e)))
        took = time.perf_counter() - t0
        data[:] = 0  # changed after submit: the job has the data as they were
        assert took < 1.0, f"submit of a 24 MiB job took {took:.2f} s behind a 3 s job"
        _wait(worker, results, 2)
        assert results == [("slow", 3.0, None), ("big", expected, None)]
        # and with nobody polling: wait() hands the rest over itself
        worker.submit("big", _digest, (data,), lambda r, e: results.append(("big", r, e)))
        assert worker.wait(60.0)
        assert results[2] == ("big", _digest(data), None)
    finally:
        worker.close()


def test_a_killed_worker_is_restarted_and_its_job_reported() -> None:
    worker = ProcessWorker()
    try:
        results: list = []
        worker.submit("a", _sleep, (30.0,), lambda r, e: results.append((r, e)))
        time.sleep(0.5)
        os.kill(worker._proc.pid, signal.SIGKILL)
        _wait(worker, results, 1)
        assert results[0][0] is None and "died" in results[0][1] or "ended" in results[0][1]
        assert worker.stats.restarts == 1
        worker.submit("a", _square, (5.0,), lambda r, e: results.append((r, e)))
        _wait(worker, results, 2)
        assert results[1] == (25.0, None)
    finally:
        worker.close()


@pytest.mark.slow
@pytest.mark.parametrize("seed,f_rpm", [(2, 1600.0), (5, 2200.0)])
def test_pipeline_with_the_process_worker_matches_the_inline_pipeline(seed: int, f_rpm: float) -> None:
    """The same stream through both workers: the same estimate (results arrive later, not different)."""
    rng = np.random.default_rng(seed)
    scenario = dataclasses.replace(BenchScenario(), c_s=float(rng.uniform(3000, 9000)), seed=seed,
                                   operating_points=(OperatingPoint(f_rpm, 30.0),))
    record = simulate_bench(scenario)
    truth = record.truth
    settings = Settings(inertias=InertiaSettings(J1=truth["J1"]),
                        model=dataclasses.replace(ModelSettings(), pulses_per_rev=truth["pulses_per_rev"]))
    finals = {}
    for name, worker in (("inline", InlineWorker()), ("process", ProcessWorker())):
        f0: list[float] = []

        def progress(_frac: float, _text: str) -> None:
            # results come back while the stream runs, later than inline (adopted at the next progress call
            # at the earliest), however slow the machine: the test waits for them, not for a wall-clock pace
            assert worker.wait(60.0), "the worker did not answer within 60 s"
            est = pipe_ref[0].last_estimate if pipe_ref else None
            if est is not None and est.valid:
                f0.append(est.f0_hz)

        pipe_ref: list[Pipeline] = []
        try:
            import online_id.service.pipeline as pl

            original = pl.Pipeline

            class Capture(original):  # keep a handle on the pipeline run_bench_data builds
                def __init__(self, *a, **k):
                    super().__init__(*a, **k)
                    pipe_ref.append(self)

            pl.Pipeline = Capture
            try:
                run_bench_data(record.to_data("sim"), settings, progress=progress, worker=worker)
            finally:
                pl.Pipeline = original
        finally:
            worker.close()
        assert worker.stats.submitted.get("window", 0) > 5
        assert len(f0) > 20, name
        finals[name] = float(np.median(f0[-20:]))
    assert abs(finals["process"] / finals["inline"] - 1) < 0.002
    assert abs(finals["process"] / truth["f0_hz"] - 1) < 0.01


class _CountingWorker(InlineWorker):
    """Runs jobs inline but says it is asynchronous, and counts the polls (where results would be adopted)."""

    asynchronous = True

    def __init__(self) -> None:
        super().__init__()
        self.polls = 0

    def poll(self) -> int:
        self.polls += 1
        return 0

    def wait(self, timeout_s: float) -> bool:
        return True


@pytest.mark.parametrize("rate_hz", [10.0, 1000.0])
def test_the_worker_is_not_polled_on_a_sample_that_publishes(rate_hz: float) -> None:
    """Adopting a result (up to a millisecond) never delays an estimate; but it is never put off twice running,
    even when every sample publishes."""
    from online_id.config import PublishSettings
    from online_id.records import EstimateOut, SignalSample

    record = simulate_bench(dataclasses.replace(BenchScenario(), seed=3,
                                                operating_points=(OperatingPoint(1500.0, 3.0),)))
    worker = _CountingWorker()
    pipe = Pipeline(Settings(publish=PublishSettings(rate_hz=rate_hz)), worker=worker)
    d = record.to_data("sim")
    publishing, plain = [], []
    for k in range(len(d)):
        t = float(d.time_s[k])
        for role, x in (("dyno_speed", d.dyno_speed_rad_s), ("engine_speed", d.engine_speed_rad_s),
                        ("dyno_torque", d.dyno_torque_nm)):
            before = worker.polls
            out = pipe.on_signal(SignalSample(role, float(x[k]), t))
            if role == "dyno_torque":  # the frame that completes the sample
                (publishing if any(isinstance(o, EstimateOut) for o in out) else plain).append(worker.polls - before)
    assert plain and all(n == 1 for n in plain)
    if rate_hz < 100.0:
        assert len(publishing) > 20 and all(n == 0 for n in publishing[1:])  # the first sample starts the schedule
    else:  # every sample publishes: polled on every second one
        assert not plain[1:] and sum(publishing) == len(publishing) // 2
