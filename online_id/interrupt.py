"""SIGINT and SIGTERM on the command line: one way to stop, at any moment, leaving nothing behind.

Python's defaults differ: SIGINT raises ``KeyboardInterrupt`` (a traceback when
nothing catches it), SIGTERM ends the process on the spot, so that no
``finally`` runs and the temporary files of :mod:`online_id.io.outfile`
stay.  :func:`interruptible` (entered by :func:`online_id.cli.main` before
anything else) makes both raise :class:`Interrupted`, a ``KeyboardInterrupt``:
every ``finally`` and context manager on the way out runs (partial outputs
are removed, worker pools and processes ended), and ``main`` prints one line
and returns the shell's status for the signal: 130 for SIGINT, 143 for
SIGTERM.  A second signal while the first one's clean-up runs is ignored, so
that the clean-up finishes.

The service (``online-id run``) sets its own handlers once it is built
(:func:`online_id.service.live.run_service`: stop the loop, save, exit 0); a
signal during its start-up ends it with status 0 too (nothing was changed yet).

Before ``main`` runs, in the first ~0.1 s while the interpreter itself starts,
the signals are Python's: SIGTERM ends the process at once (there is nothing
to leave behind yet), SIGINT raises ``KeyboardInterrupt`` in Python's own
start-up code.
"""

from __future__ import annotations

import os
import signal
import sys
import threading
from collections.abc import Iterator
from contextlib import contextmanager

from online_id.io import outfile

SIGNALS = (signal.SIGINT, signal.SIGTERM)


class Interrupted(KeyboardInterrupt):
    """SIGINT or SIGTERM arrived; ``exit_status`` is the shell's status for it (128 + the signal's number)."""

    def __init__(self, signum: int) -> None:
        self.signum = int(signum)
        self.name = signal.Signals(self.signum).name
        super().__init__(self.name)

    @property
    def exit_status(self) -> int:
        return 128 + self.signum


AGAIN_S = 0.5
"""How often a stop that was swallowed is raised again (see :func:`_again`)."""

_received: list[int] = []

_stopped_by: list[int] = []
"""The signal that stopped the last :func:`interruptible` block, if one did (see :func:`stopped_by`)."""


def stopped_by() -> int | None:
    """The signal (SIGINT or SIGTERM) that arrived within the last :func:`interruptible` block, else None.

    Set whatever became of its :class:`Interrupted`: an extension module whose import the signal cut
    short may raise its own error instead (numpy's ``ImportError`` when ``datetime`` did not load), and
    that error is then the signal's doing, not a fault to report.
    """
    return _stopped_by[-1] if _stopped_by else None


def end_process(status: int) -> None:
    """End the console process after a stop, with ``status``, without the interpreter's finalisation.

    The ``finally`` blocks and context managers have run (partial outputs removed, pools ended); what is
    left is the finalisation of modules and objects the signal may have cut short half-made (an
    extension module's import, an llvmlite pass builder while numba compiled), which can crash the
    interpreter on its way out (SIGSEGV instead of the status). So: the ``atexit`` functions run (they
    remove temporary directories, among others), the standard streams are flushed, and the process ends.
    """
    import atexit

    try:
        atexit._run_exitfuncs()
    finally:
        for stream in (sys.stdout, sys.stderr):
            try:
                stream.flush()
            except (OSError, ValueError):  # a reader gone, a stream closed: nothing more to say
                pass
        os._exit(status)


def _raise(signum: int, _frame) -> None:
    if _received:  # a second signal while the first one's clean-up runs: the clean-up finishes
        return
    _received.append(signum)
    signal.setitimer(signal.ITIMER_REAL, AGAIN_S, AGAIN_S)  # see _again
    _deliver(signum)


def _deliver(signum: int) -> None:
    if outfile.holding():  # a temporary file is being made: raised once its removal guards it
        outfile.hold(Interrupted(signum))
        return
    raise Interrupted(signum)


def _again(_signum: int, _frame) -> None:
    """Every ``AGAIN_S`` after a stop: raise it again unless it is on its way out.

    Some code swallows any exception: a callback from C (numba's compiler calls back into Python, and
    ctypes reports and drops what the callback raised), an ``except BaseException`` in a library's
    import.  The stop is on its way out while :class:`Interrupted` is the exception being handled (the
    ``finally`` blocks and ``__exit__`` methods that clean up run with it): then nothing is raised, so
    that the clean-up is never cut.
    """
    if _received:
        if not isinstance(sys.exc_info()[1], Interrupted):
            _deliver(_received[0])
    elif callable(_outer_alarm[-1] if _outer_alarm else None):
        _outer_alarm[-1](_signum, _frame)  # no stop pending: the alarm is the caller's own (see interruptible)


_outer_alarm: list = []
"""The SIGALRM handlers of the callers of :func:`interruptible` (innermost last)."""


def _forked_child() -> None:
    """In a process forked within :func:`interruptible` (a pool's worker): the signals' default actions.

    The child would otherwise inherit the stop handlers and their state: ``Pool.terminate`` ends its workers
    with SIGTERM and waits for them, and a worker that took that SIGTERM as a second stop, ignored while the
    first one's clean-up runs, never ended (docs/history/ci-hang.md). SIGINT ends it too: Ctrl-C reaches the
    whole process group, the parent stops and ends its pool, and the programs a worker runs get it as any
    program does. (A fork's child has no timer of its parent's.)
    """
    if signal.getsignal(signal.SIGTERM) is not _raise:
        return
    _received.clear()
    _outer_alarm.clear()
    for s in (*SIGNALS, signal.SIGALRM):
        signal.signal(s, signal.SIG_DFL)


os.register_at_fork(after_in_child=_forked_child)


@contextmanager
def interruptible(process_ends: bool = False) -> Iterator[None]:
    """Within: SIGINT and SIGTERM raise :class:`Interrupted` (see module notes), and again if some code
    swallows it (:func:`_again`).

    On the way out the previous handlers come back, unless a signal arrived or ``process_ends`` (the
    console script, whose work is done: its exit status stands): then further signals are ignored.
    Outside the main thread (where Python runs no handler) it does nothing.
    """
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    previous = {s: signal.getsignal(s) for s in (*SIGNALS, signal.SIGALRM)}
    # a caller's own alarm (pytest-timeout's, for one) still reaches its handler while no stop is pending,
    # and its timer runs on: the timer is this function's only once a stop has set it (_raise)
    outer = previous[signal.SIGALRM]
    _outer_alarm.append((_outer_alarm[-1] if _outer_alarm else None) if outer is _again else outer)
    hook = sys.unraisablehook

    def unraisable(info) -> None:
        if not isinstance(info.exc_value, Interrupted):  # swallowed, not reported: _again raises it again
            hook(info)

    _received.clear()
    _stopped_by.clear()
    sys.unraisablehook = unraisable
    signal.signal(signal.SIGALRM, _again)
    for s in SIGNALS:
        signal.signal(s, _raise)
    try:
        yield
    finally:
        if _received:
            signal.setitimer(signal.ITIMER_REAL, 0.0)
            _stopped_by.append(_received[0])
        _outer_alarm.pop()
        for s, handler in previous.items():
            stays = s != signal.SIGALRM and (_received or process_ends)
            signal.signal(s, signal.SIG_IGN if stays else handler)
        # after a signal the console process only ends: the finalisers of what the signal cut short (an
        # llvmlite pass builder half made while numba compiled) have nothing to report to the user
        sys.unraisablehook = (lambda info: None) if _received and process_ends else hook
        _received.clear()
