"""What a worker process of a pool starts with: the signals' default actions.

A worker forked by ``multiprocessing`` (``Pool``, ``ProcessPoolExecutor``) inherits its parent's Python
signal handlers and their state. The command line's (:mod:`online_id.interrupt`) turn SIGTERM and SIGINT
into a stop that is raised, repeated, or ignored while a first one's clean-up runs; ``Pool.terminate``
ends its workers with SIGTERM and then waits for them, and a worker that took that SIGTERM as a stop to
ignore never ended (docs/history/ci-hang.md).
"""

from __future__ import annotations

import signal


def worker_signals() -> None:
    """Pool initializer: SIGTERM ends the worker at once (as ``Pool.terminate`` expects), so does SIGINT
    (Ctrl-C reaches the whole process group: the parent stops and ends its pool, the programs a worker runs
    get it as any program does), and no timer or handler of the parent's goes on in it."""
    signal.setitimer(signal.ITIMER_REAL, 0.0)
    for sig in (signal.SIGALRM, signal.SIGTERM, signal.SIGINT):
        signal.signal(sig, signal.SIG_DFL)
