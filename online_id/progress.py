"""One progress bar for every long command: fraction done, rate and time left, on stderr.

A :class:`Progress` is a callable ``progress(fraction, message="")`` (the
signature the numerical code calls, e.g. :func:`~online_id.estimation.
identification.identify`), plus :meth:`Progress.count` for loops that know
how many items they work through (frames of a log, samples of a bench)::

    with Progress("replay", unit="frames", quiet=args.json) as progress:
        for k, frame in enumerate(frames):
            ...
            progress.count(k + 1, total)

On a terminal it redraws one line in place, at most ten times a second::

    replay [##########----------]  48.2%  12.0 s  41,003 frames/s  13 s left  t = 102.0 s

It writes nothing when the stream is not a terminal (a pipe, a log file, a
test), or with ``quiet`` (``--json``, ``--quiet``), so that machine-read
output stays clean.
"""

from __future__ import annotations

import sys
import time
from typing import TextIO

WIDTH = 120
"""Characters of the progress line (it is padded to this, so a shorter line erases a longer one)."""


def _duration(seconds: float) -> str:
    if seconds < 60:
        return f"{seconds:.0f} s"
    if seconds < 3600:
        return f"{seconds // 60:.0f} min {seconds % 60:02.0f} s"
    return f"{seconds // 3600:.0f} h {seconds % 3600 // 60:02.0f} min"


class Progress:
    """A one-line progress bar (see module notes).

    Parameters
    ----------
    label
        What runs (the command's name).
    unit
        What :meth:`count` counts (``frames``, ``samples``); shown with the rate.
    stream
        Where to draw (default ``sys.stderr``).
    enabled
        Draw or not; default: when ``stream`` is a terminal and not ``quiet``.
    quiet
        Never draw (``--json``, ``--quiet``).
    """

    def __init__(self, label: str, stream: TextIO | None = None, enabled: bool | None = None, *,
                 unit: str = "", quiet: bool = False, clock=time.monotonic) -> None:
        self.stream = stream or sys.stderr
        if enabled is None:
            isatty = getattr(self.stream, "isatty", None)
            enabled = bool(isatty and isatty())
        self.enabled = enabled and not quiet
        self.label = label
        self.unit = unit
        self.clock = clock
        self.t0 = clock()
        self._last = -1.0
        self.fraction = 0.0  # the last fraction reported (read by tests)
        self.done = 0  # the last count reported

    def line(self, fraction: float, message: str = "", now: float | None = None) -> str:
        """The progress line for ``fraction`` done (without the leading carriage return)."""
        now = self.clock() if now is None else now
        elapsed = max(now - self.t0, 0.0)
        f = min(max(fraction, 0.0), 1.0)
        filled = int(round(20 * f))
        parts = [f"{self.label} [{'#' * filled}{'-' * (20 - filled)}] {100 * f:5.1f}%", f"{elapsed:5.1f} s"]
        if self.unit and self.done and elapsed > 0:
            parts.append(f"{self.done / elapsed:,.0f} {self.unit}/s")
        if 0.01 <= f < 1.0 and elapsed >= 1.0:
            parts.append(f"{_duration(elapsed * (1.0 - f) / f)} left")
        if message:
            parts.append(message)
        return "  ".join(parts)[:WIDTH]

    def __call__(self, fraction: float, message: str = "") -> None:
        """Report ``fraction`` (0..1) done; redraws at most every 0.1 s (and always at 1.0)."""
        self.fraction = fraction
        if not self.enabled:
            return
        now = self.clock()
        if fraction < 1.0 and now - self._last < 0.1:
            return
        self._last = now
        self.stream.write("\r" + self.line(fraction, message, now).ljust(WIDTH))
        self.stream.flush()

    def count(self, done: int, total: int | None = None, message: str = "") -> None:
        """Report ``done`` items of ``total`` (``None``: unknown, the bar stays empty, the rate shows)."""
        self.done = done
        fraction = min(done / total, 0.999) if total else 0.0
        self(fraction, message)

    def close(self) -> None:
        """Erase the line (the command's own output follows)."""
        if self.enabled:
            self.stream.write("\r" + " " * WIDTH + "\r")
            self.stream.flush()

    def __enter__(self) -> "Progress":
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def add_quiet_option(parser) -> None:
    """``--quiet``: no progress bar (also implied by ``--json``)."""
    parser.add_argument("--quiet", action="store_true", help="no progress bar on stderr (implied by --json)")


def progress_for(args, label: str, unit: str = "") -> Progress:
    """The command's progress bar, quiet with ``--json`` or ``--quiet``."""
    return Progress(label, unit=unit, quiet=bool(getattr(args, "json", False) or getattr(args, "quiet", False)))
