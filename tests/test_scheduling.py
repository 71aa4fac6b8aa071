"""The receive loop's short time slice, and the worker process back on the kernel's default."""

import threading

import pytest

from online_id.service.offload import ProcessWorker
from online_id.service.scheduling import SHORT_SLICE_NS, current_slice_ns, default_slice, request_short_slice


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
