"""The receive loop's short time slice, and the worker process back on the kernel's default."""

import gc
import threading

import pytest

from online_id.service.offload import ProcessWorker
from online_id.service.scheduling import SHORT_SLICE_NS, Collector, current_slice_ns, default_slice, request_short_slice


def test_the_loop_gets_a_short_slice_and_the_worker_goes_back_to_the_default() -> None:
    said: list[str] = []
    t = threading.Thread(target=lambda: said.append(request_short_slice()))  # a thread of its own, as the loop
    t.start()
    t.join()
    assert len(said) == 1 and said[0].startswith("scheduling: ") and "\n" not in said[0]
    if "keeps its default" in said[0]:
        pytest.skip(f"this kernel has no per-task slice: {said[0]}")
    assert "100 us" in said[0]
    try:
        # here too, then a worker spawned from this thread, which would inherit the short slice
        assert request_short_slice() == said[0] and current_slice_ns() == SHORT_SLICE_NS
        worker = ProcessWorker()
        try:
            got: list = []
            worker.submit("s", current_slice_ns, (), lambda r, e: got.append((r, e)))
            assert worker.wait(60.0)
        finally:
            worker.close()
        (slice_ns, error), = got
        assert error is None and slice_ns and slice_ns > SHORT_SLICE_NS
    finally:
        default_slice()
    assert current_slice_ns() > SHORT_SLICE_NS


class _Cycle:
    def __init__(self) -> None:
        self.me = self


def test_the_collector_runs_only_where_the_loop_calls_it_and_the_same_generations() -> None:
    """While open, allocation never triggers a collection; collect() runs the one due (by CPython's counts and
    thresholds), none when none is due; close() gives the automatic collection back as it was."""
    runs: list[int] = []

    def seen(phase: str, info: dict) -> None:
        if phase == "start":
            runs.append(info["generation"])

    gc.collect()
    old = gc.get_threshold()
    gc.set_threshold(100, 3, 2)
    gc.callbacks.append(seen)
    try:
        collector = Collector()
        assert not gc.isenabled()
        keep = [_Cycle() for _ in range(5000)]  # far past threshold 0: nothing runs by itself
        assert runs == [] and gc.get_count()[0] > 100
        got = []
        for _ in range(18):
            for _ in range(150):
                _Cycle()  # garbage that only the collector frees
            got.append(collector.collect())
        assert runs == got  # each call ran exactly the collection it reports
        # generation 1 after more than 3 of generation 0, 2 after more than 2 of generation 1, as CPython counts
        assert got == [0, 0, 0, 0, 1] * 3 + [2, 0, 0]
        gc.collect()
        assert collector.collect() == -1 and runs == got + [2]
        collector.close()
        assert gc.isenabled() and len(keep) == 5000
    finally:
        gc.callbacks.remove(seen)
        gc.set_threshold(*old)
        gc.enable()
