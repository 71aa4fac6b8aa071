"""Slow work off the receive path: the window refits, multi-start checks and physical fits.

The pipeline hands a job (a module-level function and its arguments) to a
*worker* and is called back with the result.  Two workers, one contract:

* :class:`InlineWorker` runs the job at once, inside :meth:`submit`, and
  calls back before returning.  Replay, the offline commands and the tests
  use it: results depend only on the samples, never on the machine's speed.
* :class:`ProcessWorker` runs jobs in one child process at a lower CPU
  priority (``nice +5``), so a refit never holds the receive loop: the
  receive loop sleeps until a frame comes, and the kernel lets a task that
  wakes from sleep preempt a busy lower-priority one.  Not the lowest
  priority (``SCHED_IDLE``, ``nice 19``): on a bench PC busy with other work
  such a worker starves, and the estimate never becomes valid; at ``+5``
  it still gets about a quarter of a core against one busy process.  The
  pipeline calls :meth:`poll` between frames; results are applied then. The
  live service uses it.

The receive loop never waits on the child.  A job is pickled in
:meth:`ProcessWorker.submit` (the arguments as they are then) and written
to the child's socket as far as the socket takes it; the rest goes at the
next :meth:`~ProcessWorker.poll`, and a reply is taken only once it is
complete.  Jobs are larger than a pipe holds (a window of samples 80 KB,
the state 100-160 KB, the backlash test's rows 380 KB), and the child reads
the next job only when it has finished the one it runs: a blocking write
held the loop until then, on a loaded machine 5 s (a backlash test
submitted behind a refit at nice +5), and the kernel dropped 5,000 frames.

Bounds.  At most one job per *lane* is in flight (lanes: ``"window"`` for
the refits and multi-start checks of the sliding window, ``"physical"`` for
the physical-parameter fit, ``"linearity"`` for the backlash test,
``"state"`` for the service's state saves).  While a lane is busy the
pipeline does not submit: a refit that falls due meanwhile waits and is then
run on the newest window; nothing queues up.  A job that raises calls back with its error; a
child that dies (killed, out of memory) is restarted, its job calls back
with an error, and :attr:`restarts` counts it.
"""

from __future__ import annotations

import multiprocessing as mp
import os
import pickle
import select
import socket
import struct
import time
import traceback
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

from online_id.service.scheduling import default_slice

Callback = Callable[[Any, "str | None"], None]
"""``callback(result, error)``: ``error`` is None on success, else a one-line description."""


@dataclass
class WorkerStats:
    """What a worker did (reported in the service's counters)."""

    submitted: dict[str, int] = field(default_factory=dict)
    failed: dict[str, int] = field(default_factory=dict)
    restarts: int = 0

    def count(self, table: dict[str, int], lane: str) -> None:
        table[lane] = table.get(lane, 0) + 1


class InlineWorker:
    """Runs every job at once (see module notes)."""

    asynchronous = False

    def __init__(self) -> None:
        self.stats = WorkerStats()

    def busy(self, lane: str) -> bool:
        return False

    def submit(self, lane: str, fn: Callable[..., Any], args: tuple, callback: Callback) -> None:
        self.stats.count(self.stats.submitted, lane)
        try:
            result = fn(*args)
        except Exception as err:  # noqa: BLE001 - reported to the caller, as the process worker does
            self.stats.count(self.stats.failed, lane)
            callback(None, f"{type(err).__name__}: {err}")
            return
        callback(result, None)

    def poll(self) -> int:
        return 0

    def wait(self, timeout_s: float) -> bool:
        return True

    def close(self) -> None:
        pass


WORKER_NICE = 5  # see module notes


def _lower_priority() -> None:
    """This process yields to the receive loop (see module notes).

    A receive loop run at a real-time priority (the unit's
    ``CPUSchedulingPolicy=fifo``) passes it to this child; a refit at that
    priority would hold the loop off its core, so the child goes back to the
    normal policy first.
    """
    try:
        if os.sched_getscheduler(0) in (os.SCHED_FIFO, os.SCHED_RR):
            os.sched_setscheduler(0, os.SCHED_OTHER, os.sched_param(0))
        os.nice(WORKER_NICE)
    except OSError:
        pass
    default_slice()  # a child started after the loop asked for a short slice would inherit it


_HEADER = struct.Struct("!Q")  # a message on the worker's socket: its length, then the pickle
SEND_BUFFER_BYTES = 1 << 20  # asked for the parent's end: the largest job (380 KB) usually goes in one write


def _pack(obj: Any) -> bytes:
    data = pickle.dumps(obj, protocol=pickle.HIGHEST_PROTOCOL)
    return _HEADER.pack(len(data)) + data


def _read_exactly(sock: socket.socket, n: int) -> bytearray:
    """``n`` bytes from a blocking socket (the child's end); EOFError when the other end closed."""
    buf = bytearray(n)
    view, got = memoryview(buf), 0
    while got < n:
        k = sock.recv_into(view[got:])
        if k == 0:
            raise EOFError("the other end closed")
        got += k
    return buf


def _serve(sock: socket.socket) -> None:
    """The child's loop: receive ``(job_id, fn, args)``, send ``(job_id, result, error)``."""
    _lower_priority()
    while True:
        try:
            (n,) = _HEADER.unpack(_read_exactly(sock, _HEADER.size))
            job = pickle.loads(_read_exactly(sock, n))
        except (EOFError, OSError, KeyboardInterrupt):
            return  # the parent closed its end (close, restart) or went away
        job_id, fn, args = job
        try:
            reply = (job_id, fn(*args), None)
        except Exception as err:  # noqa: BLE001 - every failure goes back to the parent
            last = traceback.extract_tb(err.__traceback__)[-1:]
            where = f" ({last[0].filename.rsplit('/', 1)[-1]}:{last[0].lineno})" if last else ""
            reply = (job_id, None, f"{type(err).__name__}: {err}{where}")
        try:
            message = _pack(reply)
        except Exception as err:  # noqa: BLE001 - a result that cannot be pickled is that job's failure
            message = _pack((job_id, None, f"the result could not be sent back: {type(err).__name__}: {err}"))
        try:
            sock.sendall(message)
        except (OSError, KeyboardInterrupt):
            return


class _Channel:
    """The parent's end of the worker's socket: messages out and in, never waiting (see module notes).

    ``put`` queues a message and writes what the socket takes; ``flush``
    writes more; ``take`` returns the replies received complete, and sets
    ``closed`` once the child's end has closed (OSError: it broke).
    """

    def __init__(self, sock: socket.socket) -> None:
        try:
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, SEND_BUFFER_BYTES)
        except OSError:
            pass
        sock.setblocking(False)
        self.sock = sock
        self._out: deque[memoryview] = deque()
        self._in = bytearray()
        self.closed = False

    @property
    def sending(self) -> bool:
        """Bytes of a message not written yet."""
        return bool(self._out)

    def put(self, message: bytes) -> None:
        self._out.append(memoryview(message))
        self.flush()

    def flush(self) -> None:
        out = self._out
        while out:
            try:
                n = self.sock.send(out[0])
            except (BlockingIOError, InterruptedError):
                return
            if n < len(out[0]):
                out[0] = out[0][n:]
                return
            out.popleft()

    def take(self) -> list:
        while True:
            try:
                chunk = self.sock.recv(1 << 20)
            except (BlockingIOError, InterruptedError):
                break
            if not chunk:
                self.closed = True  # the replies before the end are still taken
                break
            self._in += chunk
        replies = []
        size = _HEADER.size
        while len(self._in) >= size:
            (n,) = _HEADER.unpack_from(self._in)
            if len(self._in) < size + n:
                break
            replies.append(pickle.loads(self._in[size:size + n]))
            del self._in[:size + n]
        return replies

    def close(self) -> None:
        self._out.clear()
        self.sock.close()


class ProcessWorker:
    """Runs jobs in one low-priority child process (see module notes).

    The child is started with the ``spawn`` method (no copy of the parent's
    threads or sockets) when the worker is built; it imports what the jobs
    need on first use.
    """

    asynchronous = True

    def __init__(self) -> None:
        self.stats = WorkerStats()
        self._ctx = mp.get_context("spawn")
        self._next_id = 0
        self._pending: dict[int, tuple[str, Callback]] = {}
        self._lanes: set[str] = set()
        self._start()

    def _start(self) -> None:
        parent, child = socket.socketpair(socket.AF_UNIX, socket.SOCK_STREAM)
        self._proc = self._ctx.Process(target=_serve, args=(child,), name="online-id-worker", daemon=True)
        self._proc.start()
        child.close()
        self._channel = _Channel(parent)

    def busy(self, lane: str) -> bool:
        return lane in self._lanes

    def submit(self, lane: str, fn: Callable[..., Any], args: tuple, callback: Callback) -> None:
        """Hand a job to the child; returns at once, whatever the job's size and whatever the child is doing."""
        if lane in self._lanes:
            raise RuntimeError(f"ProcessWorker: lane {lane!r} is busy (check busy() before submit)")
        job_id = self._next_id + 1
        message = _pack((job_id, fn, args))  # the arguments as they are now (a job that cannot be pickled raises)
        self._next_id = job_id
        self.stats.count(self.stats.submitted, lane)
        self._pending[job_id] = (lane, callback)
        self._lanes.add(lane)
        try:
            self._channel.put(message)
        except OSError:
            self._restart("the worker process is gone")

    def poll(self) -> int:
        """Write more of a job not yet handed over, and call back every finished job; returns how many finished."""
        if not self._pending:
            return 0
        done = 0
        try:
            self._channel.flush()
            for job_id, result, error in self._channel.take():
                done += self._finish(job_id, result, error)
            if self._channel.closed:
                raise EOFError("the worker's end of the socket closed")
        except (OSError, EOFError):
            # the child's end of the socket closes when it exits, however it ends (killed, out of memory):
            # it reads as end of file (or a write fails), so no per-call liveness check is needed
            self._proc.join(0.1)
            self._restart(f"the worker process ended (exit code {self._proc.exitcode})")
        return done

    def wait(self, timeout_s: float) -> bool:
        """Block until every job in flight has called back (or ``timeout_s`` passed); True if none is left.

        Not for the receive loop (it polls); for offline callers that want the results before going on.
        """
        deadline = time.monotonic() + timeout_s
        while self._pending:
            left = deadline - time.monotonic()
            if left <= 0:
                break
            sock = self._channel.sock
            try:
                select.select([sock], [sock] if self._channel.sending else [], [], left)
            except (OSError, ValueError):
                pass  # a broken socket: poll() restarts the child and calls the job back with the error
            self.poll()
        return not self._pending

    def _finish(self, job_id: int, result: Any, error: str | None) -> int:
        entry = self._pending.pop(job_id, None)
        if entry is None:
            return 0
        lane, callback = entry
        self._lanes.discard(lane)
        if error is not None:
            self.stats.count(self.stats.failed, lane)
        callback(result, error)
        return 1

    def _restart(self, why: str) -> None:
        self.stats.restarts += 1
        pending, self._pending = self._pending, {}
        self._lanes.clear()
        self._close_child(wait_s=0.1)
        self._start()
        for lane, callback in pending.values():
            self.stats.count(self.stats.failed, lane)
            callback(None, f"{why}; restarted it")

    def _close_child(self, wait_s: float) -> None:
        """The child's socket closed (it ends when it reads the end of file, after a job it runs), then ended."""
        self._channel.close()
        self._proc.join(wait_s)
        if self._proc.is_alive():
            self._proc.kill()
            self._proc.join(1.0)

    def close(self) -> None:
        """Stop the child (a job in flight is abandoned)."""
        self._pending.clear()
        self._lanes.clear()
        self._close_child(wait_s=2.0)
