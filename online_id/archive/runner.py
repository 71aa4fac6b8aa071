"""Map a function over many items on a Dask cluster: a local one, or a scheduler's address.

This is the one place that talks to ``dask.distributed``; the archive, the
archive simulator and ``online-id evaluate`` use it, and any other batch of
independent cases can::

    from online_id.archive.runner import cluster, map_tasks

    with cluster(scheduler=None, workers=2) as client:       # LocalCluster, 2 worker processes
        outcomes = map_tasks(client, run_case, cases, label="evaluate",
                             on_done=lambda o: print(o.index, o.error or o.value))

* ``func`` must be picklable (a module-level function) and so must the items
  and what it returns: Dask ships them to the worker processes.
* Every item gives one :class:`Outcome`, returned in submission order
  whatever order they complete in.  A task that raises is an outcome with
  its one-line ``error`` (the batch goes on); a task whose worker died more
  often than the scheduler allows (``KilledWorker``), or that was cancelled,
  is ``lost``: no result and no verdict on the item, so a re-run should try
  it again.
* ``on_done`` is called in the caller's process as each task completes (to
  write its result at once: an interrupted run keeps what finished).
* Progress: a progress line on a terminal (:class:`~online_id.progress.Progress`)
  and, where the cluster serves one, the dashboard's address on stderr.

Dask is an optional dependency (the ``archive`` extra): :func:`require_dask`
raises a one-line :class:`~online_id.errors.ConfigError` naming the extra
when it is missing, and nothing here imports it before it is needed.
"""

from __future__ import annotations

import contextlib
import os
import sys
import time
import traceback
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from typing import Any

from online_id.errors import ConfigError, printable
from online_id.progress import Progress

EXTRA = "pip install 'online-id[archive]'"


@dataclass(frozen=True)
class Outcome:
    """What one item's task gave.

    Attributes
    ----------
    index
        The item's position in the submitted sequence.
    value
        The function's return value (None on an error or a lost task).
    error
        One line: the exception's type and message, when the function raised.
    lost
        True when the task never completed (its worker died too often, the run
        was cancelled): no verdict on the item.
    worker
        Address of the worker that ran it (None when lost).
    cpu_s, wall_s
        CPU and wall time of the function inside the worker.
    started_s, arrived_s
        When the function started in the worker and when its result arrived
        in the caller (``time.time()``): the overhead of scheduling, transfer
        and pickling is what a batch's wall time holds beyond ``wall_s``.
    """

    index: int
    value: Any = None
    error: str | None = None
    lost: bool = False
    worker: str | None = None
    cpu_s: float = 0.0
    wall_s: float = 0.0
    started_s: float = 0.0
    arrived_s: float = 0.0

    @property
    def ok(self) -> bool:
        return self.error is None and not self.lost


def require_dask() -> None:
    """Raise a one-line :class:`ConfigError` when ``dask.distributed`` cannot be imported."""
    try:
        import distributed  # noqa: F401
    except ImportError as err:
        raise ConfigError(f"this command runs on Dask, which is not installed ({err.msg}): {EXTRA}") from None


def one_line(err: BaseException) -> str:
    """An exception as one printable line: ``Type: message`` (the message alone for online-id's own errors)."""
    from online_id.errors import OnlineIdError

    text = " ".join(str(err).split())
    if isinstance(err, OnlineIdError) and text:
        return printable(text)
    return printable(f"{type(err).__name__}: {text}" if text else type(err).__name__)


def _call(func: Callable[[Any], Any], item: Any) -> tuple[Any, str | None, str, float, float, float]:
    """Run ``func(item)`` in the worker: (value, one-line error, worker, CPU s, wall s, start time)."""
    try:
        from distributed import get_worker

        where = get_worker().address
    except (ImportError, ValueError):
        where = f"pid {os.getpid()}"
    t0, c0 = time.time(), time.process_time()
    try:
        value, error = func(item), None
    except Exception as err:  # noqa: BLE001 - a failing item is an outcome, never a lost batch
        value, error = None, one_line(err)
        if os.environ.get("ONLINE_ID_DEBUG"):
            traceback.print_exc()
    return value, error, where, time.process_time() - c0, time.time() - t0, t0


@contextlib.contextmanager
def cluster(scheduler: str | None = None, workers: int = 2, *, quiet: bool = False,
            memory_limit: str | None = "auto") -> Iterator[Any]:
    """A ``distributed.Client``: on the scheduler at ``scheduler`` (``tcp://HOST:8786``), else on a
    ``LocalCluster`` of ``workers`` processes with one thread each (numpy kept single-threaded in them).

    Raises
    ------
    ConfigError
        Dask is not installed, ``workers`` < 1, or the scheduler cannot be reached (one line).
    """
    require_dask()
    import logging

    import dask
    from distributed import Client, LocalCluster

    # the cluster's own log lines (worker start, a lost worker) go to stderr at WARNING; not our output
    for name in ("distributed", "distributed.worker", "distributed.nanny", "distributed.scheduler"):
        logging.getLogger(name).setLevel(logging.ERROR)
    if scheduler:
        try:
            client = Client(scheduler, timeout="10s", set_as_default=False)
        except (OSError, TimeoutError) as err:
            raise ConfigError(f"--scheduler {scheduler}: cannot reach the Dask scheduler ({one_line(err)})") from None
        try:
            yield client
        finally:
            client.close()
        return
    if workers < 1:
        raise ConfigError(f"--workers: expected a number >= 1, got {workers!r}")
    # a free port: another cluster on the machine may hold the default 8787 (without bokeh the scheduler
    # still serves its HTTP endpoints there, without the dashboard's pages)
    dashboard = "127.0.0.1:0"
    env = {k: "1" for k in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS")}
    # Dask's nannies set MALLOC_TRIM_THRESHOLD_=65536 in their workers (and in this process): glibc then gives
    # freed memory back to the system so eagerly that the fits' linear algebra pays for fresh pages again and
    # again (measured: 1.5-2x the CPU of the same cases); the default threshold of glibc is kept instead.
    # The nannies also write their workers' pre-spawn variables (PYTHONHASHSEED ...) into this process's
    # environment: it is put back when the cluster closes, so no process started later inherits them
    environ = dict(os.environ)
    with dask.config.set({"distributed.nanny.pre-spawn-environ.MALLOC_TRIM_THRESHOLD_": None}):
        local = LocalCluster(n_workers=workers, threads_per_worker=1, processes=True, host="127.0.0.1",
                             dashboard_address=dashboard, memory_limit=memory_limit, env=env,
                             silence_logs=logging.ERROR)
    client = Client(local, set_as_default=False)
    try:
        yield client
    finally:
        client.close()
        local.close()
        if os.environ != environ:
            os.environ.clear()
            os.environ.update(environ)


def dashboard_note(client: Any) -> str | None:
    """"dashboard: http://..." when the cluster serves one, else None."""
    try:
        import bokeh  # noqa: F401  (the dashboard's pages need it)
    except ImportError:
        return None
    try:
        link = client.dashboard_link
    except Exception:  # noqa: BLE001 - no dashboard (bokeh missing, or the scheduler runs without)
        return None
    info = client.scheduler_info() if hasattr(client, "scheduler_info") else {}
    if not info.get("services", {}).get("dashboard"):
        return None
    return f"dashboard: {link}"


def workers_of(client: Any) -> int:
    """How many workers the client's cluster has now."""
    return len(client.scheduler_info(n_workers=-1).get("workers", {}))


def map_tasks(client: Any, func: Callable[[Any], Any], items: Sequence[Any], *, label: str = "tasks",
              on_done: Callable[[Outcome], None] | None = None, quiet: bool = False,
              weights: Sequence[float] | None = None, stream=None) -> list[Outcome]:
    """Run ``func(item)`` for every item on ``client``'s cluster (see module notes).

    ``weights`` (one per item, e.g. seconds of data) make the progress bar's
    fraction; default one per item.  Returns one :class:`Outcome` per item, in
    the order of ``items``.  On KeyboardInterrupt the pending tasks are
    cancelled and the interrupt goes on (what ``on_done`` saw is kept).
    """
    from distributed import as_completed
    from distributed.client import FutureCancelledError

    try:
        from distributed.scheduler import KilledWorker
    except ImportError:  # pragma: no cover - moved in some versions
        from distributed import KilledWorker

    items = list(items)
    out: list[Outcome | None] = [None] * len(items)
    if not items:
        return []
    w = [1.0] * len(items) if weights is None else [max(float(x), 0.0) for x in weights]
    total = sum(w) or 1.0
    note = dashboard_note(client)
    if note and not quiet:
        print(f"{label}: {note}", file=stream or sys.stderr)
    futures = client.map(_call, [func] * len(items), items, pure=False)
    index = {f.key: i for i, f in enumerate(futures)}
    done_w = 0.0
    n_done = 0
    with Progress(label, quiet=quiet, unit="tasks", stream=stream) as progress:
        try:
            for fut in as_completed(futures, loop=client.loop):
                i = index[fut.key]
                try:
                    value, error, where, cpu, wall, t0 = fut.result()
                    outcome = Outcome(i, value, error, False, where, cpu, wall, t0, time.time())
                except (KilledWorker, FutureCancelledError) as err:
                    outcome = Outcome(i, error=one_line(err), lost=True)
                except Exception as err:  # noqa: BLE001 - the task could not be run or its result not read
                    outcome = Outcome(i, error=one_line(err), lost=True)
                fut.release()
                out[i] = outcome
                n_done += 1
                done_w += w[i]
                if on_done is not None:
                    on_done(outcome)
                progress.done = n_done
                progress(min(done_w / total, 0.999 if n_done < len(items) else 1.0),
                         f"{n_done}/{len(items)}" + (f"  {outcome.error[:60]}" if outcome.error else ""))
        except BaseException:
            client.cancel([f for f in futures if not f.done()])
            raise
    return [o if o is not None else Outcome(k, error="no result", lost=True) for k, o in enumerate(out)]
