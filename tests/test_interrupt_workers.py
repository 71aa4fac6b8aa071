"""The stop handlers of :func:`online_id.interrupt.interruptible` and what runs beside them: a caller's own alarm
(pytest-timeout's) and the worker processes forked within (``online-id evaluate``'s pool).

A forked worker inherits its parent's Python signal handlers and their state. ``Pool.terminate`` ends its
workers with SIGTERM; a worker whose handler took that SIGTERM for "a second stop, ignored while the first
one's clean-up runs" never ended, and the pool's exit waited for it (a test run hung for 80 minutes on it).
"""

import multiprocessing
import os
import signal
import time

import pytest

from online_id import interrupt
from online_id.interrupt import interruptible


class CallersAlarm(Exception):
    pass


def _callers_alarm(_signum, _frame):
    raise CallersAlarm


@pytest.fixture
def callers_handler():
    previous = signal.signal(signal.SIGALRM, _callers_alarm)
    yield
    signal.setitimer(signal.ITIMER_REAL, 0.0)
    signal.signal(signal.SIGALRM, previous)


@pytest.mark.parametrize("delay_s", [0.05, 0.3])
def test_a_callers_alarm_reaches_its_handler_inside(callers_handler, delay_s):
    signal.setitimer(signal.ITIMER_REAL, delay_s)
    t0 = time.monotonic()
    with pytest.raises(CallersAlarm):
        with interruptible():
            time.sleep(5.0)
    assert time.monotonic() - t0 < delay_s + 1.0
    assert signal.getsignal(signal.SIGALRM) is _callers_alarm
    assert signal.getsignal(signal.SIGTERM) is not interrupt._raise


def test_a_callers_timer_runs_on_after_a_nested_interruptible(callers_handler):
    signal.setitimer(signal.ITIMER_REAL, 0.4)
    with interruptible():
        with interruptible():
            pass
    assert signal.getitimer(signal.ITIMER_REAL)[0] > 0
    with pytest.raises(CallersAlarm):
        time.sleep(5.0)


def _stays_alive(pid: int, seconds: float) -> bool:
    deadline = time.monotonic() + seconds
    while time.monotonic() < deadline:
        done, _ = os.waitpid(pid, os.WNOHANG)
        if done:
            return False
        time.sleep(0.02)
    return True


def _fork_waiting() -> int:
    """A child that waits (as a pool's worker waits for work); its pid."""
    pid = os.fork()
    if pid == 0:
        try:
            time.sleep(30.0)
        finally:
            os._exit(0)
    time.sleep(0.3)
    return pid


def _ends_on(pid: int, sig: int) -> bool:
    try:
        os.kill(pid, sig)
        return not _stays_alive(pid, 1.5)
    finally:
        try:
            os.kill(pid, signal.SIGKILL)
            os.waitpid(pid, 0)
        except (ProcessLookupError, ChildProcessError):
            pass


@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGINT])
def test_a_child_forked_within_with_a_stop_taken_ends_on_a_stop(sig):
    """Forked while the parent's handler had taken a stop (the state the hung worker may have held)."""
    with interruptible():
        interrupt._received.append(signal.SIGTERM)
        try:
            pid = _fork_waiting()
        finally:
            interrupt._received.clear()
    assert _ends_on(pid, sig)


def test_a_child_forked_outside_keeps_its_parents_own_handler():
    """Only interruptible's own handling is dropped in a child: a handler the caller set stays (here one that
    ignores SIGTERM, so the child lives on)."""
    previous = signal.signal(signal.SIGTERM, lambda *_: None)
    try:
        pid = _fork_waiting()
    finally:
        signal.signal(signal.SIGTERM, previous)
    assert not _ends_on(pid, signal.SIGTERM)


def _square(x: int) -> int:
    return x * x


def test_a_pool_made_within_ends_at_its_exit():
    """``with Pool(...)`` ends in ``terminate``: every worker is stopped by SIGTERM, whatever its parent held."""
    t0 = time.monotonic()
    with interruptible():
        interrupt._received.append(signal.SIGTERM)
        try:
            with multiprocessing.get_context("fork").Pool(2) as pool:
                assert pool.map(_square, range(6)) == [0, 1, 4, 9, 16, 25]
                workers = [p.pid for p in pool._pool]
        finally:
            interrupt._received.clear()
    assert time.monotonic() - t0 < 20.0
    for pid in workers:
        with pytest.raises(ProcessLookupError):
            os.kill(pid, 0)
