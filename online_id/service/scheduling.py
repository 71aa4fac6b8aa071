"""The receive loop's CPU scheduling: a short time slice, so that a frame's arrival preempts other work.

Linux's fair scheduler (EEVDF, kernels 6.6 and later) lets the task that
runs finish its time slice (about 3 ms on a small machine) before a task
that just woke up takes the CPU, unless the woken task asked for a shorter
slice than the running one (kernels 6.12 and later: ``sched_setattr`` with
``sched_runtime`` for a ``SCHED_OTHER`` task).  The receive loop sleeps
until a frame comes and then works for well under a millisecond, so it asks
for the shortest slice (0.1 ms): on its arrival it preempts the worker
process's refits and the PC's other work at once instead of waiting up to a
slice for them.  It does not get more CPU than its fair share by this, only
sooner.  On older kernels the request is accepted and has no effect, which
:func:`request_short_slice` reports; under ``SCHED_FIFO`` (the unit's
real-time drop-in) it is not needed and not made.

The worker process, which inherits the slice, goes back to the kernel's
default (:func:`default_slice`): its refits are throughput work.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import os
import platform

SHORT_SLICE_NS = 100_000  # the shortest the kernel accepts (0.1 ms)
_NR_SCHED_SETATTR = {"x86_64": 314, "aarch64": 274, "i686": 351, "armv7l": 380, "ppc64le": 355, "riscv64": 274,
                     "s390x": 345}
_NR_SCHED_GETATTR = {"x86_64": 315, "aarch64": 275, "i686": 352, "armv7l": 381, "ppc64le": 356, "riscv64": 275,
                     "s390x": 346}


class _SchedAttr(ctypes.Structure):
    """``struct sched_attr`` of ``sched_setattr(2)``, first version (48 bytes)."""

    _fields_ = [("size", ctypes.c_uint32), ("sched_policy", ctypes.c_uint32), ("sched_flags", ctypes.c_uint64),
                ("sched_nice", ctypes.c_int32), ("sched_priority", ctypes.c_uint32),
                ("sched_runtime", ctypes.c_uint64), ("sched_deadline", ctypes.c_uint64),
                ("sched_period", ctypes.c_uint64)]


def _libc():
    return ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6", use_errno=True)


def current_slice_ns() -> int | None:
    """This thread's fair-scheduler slice as the kernel reports it (0 before Linux 6.12; None: no such call)."""
    machine = platform.machine()
    if os.name != "posix" or machine not in _NR_SCHED_GETATTR:
        return None
    back = _SchedAttr()
    if _libc().syscall(_NR_SCHED_GETATTR[machine], 0, ctypes.byref(back), ctypes.sizeof(back), 0) != 0:
        return None
    return int(back.sched_runtime)


def _set_slice(slice_ns: int) -> int | None:
    """Set this thread's fair-scheduler slice; the slice read back (None where the call does not exist)."""
    machine = platform.machine()
    if os.name != "posix" or machine not in _NR_SCHED_SETATTR:
        return None
    attr = _SchedAttr(size=ctypes.sizeof(_SchedAttr), sched_policy=os.SCHED_OTHER,
                      sched_nice=os.getpriority(os.PRIO_PROCESS, 0), sched_runtime=slice_ns)
    if _libc().syscall(_NR_SCHED_SETATTR[machine], 0, ctypes.byref(attr), 0) != 0:
        return None
    return current_slice_ns()


def request_short_slice() -> str:
    """Ask for the shortest fair-scheduler slice for this thread; says what came of it (for the log)."""
    try:
        if os.sched_getscheduler(0) != os.SCHED_OTHER:
            return "scheduling: real-time policy, no slice needed"
        got = _set_slice(SHORT_SLICE_NS)
    except (OSError, AttributeError) as err:
        return f"scheduling: could not ask for a short time slice ({err})"
    if got == SHORT_SLICE_NS:
        return f"scheduling: time slice {SHORT_SLICE_NS / 1e3:.0f} us (a frame's arrival preempts other work)"
    return "scheduling: this kernel keeps its default time slice (a short one needs Linux 6.12 or later)"


def default_slice() -> None:
    """Back to the kernel's default slice (the worker process; nothing happens where it is not supported)."""
    try:
        if os.sched_getscheduler(0) == os.SCHED_OTHER:
            _set_slice(0)
    except (OSError, AttributeError):
        pass
