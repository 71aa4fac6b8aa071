"""The service's reaction time: from an input frame's arrival to the first output it triggered, sent.

The receive loop measures, for every frame whose processing publishes
something, ``time.time()`` after the first of its output frames is sent (at
a publication, normally the OidEstimate: the pipeline puts it first) minus
the frame's timestamp.  On a kernel socket (SocketCAN, ``udp_multicast``) that
timestamp is the kernel's arrival stamp (CLOCK_REALTIME, as ``time.time()``),
so the figure holds the wait in the socket buffer, the scheduler's delay in
waking the loop, decoding, assembly, the recursive update and the sends.  A
frame stamped in another time base (a replayed log, a clock step) gives a
difference outside 0-10 s and is counted as not measurable.

The service keeps a second histogram of the same outputs from the moment
its loop got the frame from the socket (``processing``): the loop's own
work; the rest of the reaction is the wait for the loop (the scheduler,
frames ahead of it, housekeeping).

A fixed histogram: 10 us bins up to 100 ms, then 1 ms bins up to the 10 s
of the measurable range, so a loop that falls seconds behind still gives
distinct p50, p99 and maximum; constant memory and cost whatever the run's
length.
"""

from __future__ import annotations

import re

import numpy as np

BIN_S = 10e-6
N_FINE = 10_000  # 10 us bins up to FINE_END_S
FINE_END_S = N_FINE * BIN_S
COARSE_S = 1e-3  # then 1 ms bins up to MAX_MEASURABLE_S
MAX_MEASURABLE_S = 10.0
N_BINS = N_FINE + round((MAX_MEASURABLE_S - FINE_END_S) / COARSE_S)
_SUMMARY = re.compile(r"(?:^|[:;] )(?P<what>[a-z][A-Za-z ]*?) p50 (?P<p50>[\d.]+) ms, p99 (?P<p99>[\d.]+) ms, "
                      r"max (?P<max>[\d.]+) ms over (?P<n>\d+) outputs", re.MULTILINE)


class ReactionTimes:
    """Histogram of reaction times (seconds) with their count, maximum and the unmeasurable ones."""

    __slots__ = ("counts", "n", "max_s", "unmeasurable")

    def __init__(self) -> None:
        self.counts = np.zeros(N_BINS + 1, dtype=np.int64)
        self.n = 0
        self.max_s = 0.0
        self.unmeasurable = 0

    def add(self, dt_s: float) -> None:
        if not 0.0 <= dt_s < MAX_MEASURABLE_S:  # also false for NaN
            self.unmeasurable += 1
            return
        k = int(dt_s / BIN_S) if dt_s < FINE_END_S else N_FINE + int((dt_s - FINE_END_S) / COARSE_S)
        self.counts[min(k, N_BINS)] += 1
        self.n += 1
        if dt_s > self.max_s:
            self.max_s = dt_s

    def percentile_s(self, q: float) -> float:
        """The ``q``-th percentile (upper edge of its bin), NaN with nothing measured."""
        if self.n == 0:
            return float("nan")
        k = int(np.searchsorted(np.cumsum(self.counts), q / 100.0 * self.n))
        if k >= N_BINS:
            return self.max_s
        edge = (k + 1) * BIN_S if k < N_FINE else FINE_END_S + (k + 1 - N_FINE) * COARSE_S
        return min(edge, self.max_s)

    def summary(self, what: str = "reaction") -> str:
        """``reaction p50 0.12 ms, p99 0.40 ms, max 1.30 ms over N outputs`` (or why there is none)."""
        if self.n == 0:
            return f"{what} time not measured (no output, or frames stamped in another time base)"
        return (f"{what} p50 {1e3 * self.percentile_s(50):.2f} ms, p99 {1e3 * self.percentile_s(99):.2f} ms, "
                f"max {1e3 * self.max_s:.2f} ms over {self.n} outputs")

    def as_dict(self) -> dict:
        return {"n": self.n, "unmeasurable": self.unmeasurable,
                "p50_ms": 1e3 * self.percentile_s(50), "p99_ms": 1e3 * self.percentile_s(99),
                "max_ms": 1e3 * self.max_s}


def read_summaries(text: str) -> dict[str, dict[str, float]]:
    """The figures of every :meth:`ReactionTimes.summary` in ``text`` (a service's log), by what each measured:
    ``{"reaction": {"p50": ms, "p99": ms, "max": ms, "n": count}, "processing CPU": {...}, ...}``; a summary
    saying its time was not measured is left out.  The first of each name counts."""
    out: dict[str, dict[str, float]] = {}
    for m in _SUMMARY.finditer(text):
        out.setdefault(m["what"], {k: float(m[k]) for k in ("p50", "p99", "max", "n")})
    return out
