"""Find steady operating points (engine-speed plateaus) in a record.

Notes
-----
The engine speed is smoothed with a centred moving average over
``smooth_s``; a sample is *steady* when the smoothed speed stays within
``tol_rpm`` of the median of its plateau and the local slope is below
``max_rate_rpm_s``.  Runs of steady samples longer than ``min_duration_s``
become operating points; ``trim_s`` is cut from both ends so that the
transient after a speed ramp does not enter the identification.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numba import njit
from scipy.ndimage import uniform_filter1d


@dataclass(frozen=True)
class Plateau:
    """One operating point: samples ``start:stop`` at about ``speed_rpm``."""

    start: int
    stop: int
    speed_rpm: float
    t_start_s: float
    t_end_s: float

    @property
    def n_samples(self) -> int:
        return self.stop - self.start


def find_plateaus(
    time_s: np.ndarray,
    speed_rpm: np.ndarray,
    *,
    min_duration_s: float = 8.0,
    tol_rpm: float = 25.0,
    max_rate_rpm_s: float = 30.0,
    smooth_s: float = 1.0,
    trim_s: float = 1.0,
) -> list[Plateau]:
    """Steady engine-speed plateaus, in time order.

    Parameters
    ----------
    time_s
        Uniform sample times.
    speed_rpm
        Engine speed.
    min_duration_s
        Shortest plateau kept (after trimming).
    tol_rpm
        Largest deviation of the smoothed speed from the plateau median.
    max_rate_rpm_s
        Largest slope of the smoothed speed inside a plateau.
    """
    n = speed_rpm.shape[0]
    if n < 3:
        return []
    dt = float(np.median(np.diff(time_s)))
    win = max(1, int(round(smooth_s / dt)))
    smooth = uniform_filter1d(speed_rpm.astype(float), size=win, mode="nearest")
    rate = np.gradient(smooth, dt)
    slow = np.abs(rate) < max_rate_rpm_s
    trim = int(round(trim_s / dt))
    min_len = int(round(min_duration_s / dt))
    starts, stops = _steady_runs(smooth, slow, float(tol_rpm), max(1, win))
    plateaus: list[Plateau] = []
    for i, j in zip(starts.tolist(), stops.tolist()):
        start, stop = i + trim, j - trim
        if stop - start >= min_len:
            seg = slice(start, stop)
            plateaus.append(
                Plateau(start, stop, float(np.mean(speed_rpm[seg])), float(time_s[start]), float(time_s[stop - 1]))
            )
    return plateaus


@njit(cache=True)
def _steady_runs(smooth: np.ndarray, slow: np.ndarray, tol: float, win: int) -> tuple[np.ndarray, np.ndarray]:
    """Runs ``i:j`` of slow samples whose smoothed speed stays within ``tol`` of the run's median.

    The median is of ``smooth[i:j]``, updated every ``win`` samples; it is
    kept in two heaps (the lower half in a max-heap, stored negated, the
    upper half in a min-heap), so a run of ``m`` samples costs
    :math:`O(m \\log m)` instead of a partition of the run at every update.
    """
    n = smooth.shape[0]
    starts = np.empty(n, dtype=np.int64)
    stops = np.empty(n, dtype=np.int64)
    low = np.empty(n // 2 + 2)  # negated: a min-heap of -x is a max-heap of x
    high = np.empty(n // 2 + 2)
    m = 0
    i = 0
    while i < n:
        if not slow[i]:
            i += 1
            continue
        # grow a run while the smoothed speed stays near the running median
        j = i
        level = smooth[i]
        n_low = 0
        n_high = 0
        while j < n and slow[j] and abs(smooth[j] - level) <= tol:
            x = smooth[j]
            if n_low == 0 or x <= -low[0]:
                n_low = _heap_push(low, n_low, -x)
            else:
                n_high = _heap_push(high, n_high, x)
            if n_low > n_high + 1:
                n_low, top = _heap_pop(low, n_low)
                n_high = _heap_push(high, n_high, -top)
            elif n_high > n_low:
                n_high, top = _heap_pop(high, n_high)
                n_low = _heap_push(low, n_low, -top)
            j += 1
            if (j - i) % win == 0:
                level = -low[0] if n_low > n_high else (-low[0] + high[0]) / 2.0
        starts[m] = i
        stops[m] = j
        m += 1
        i = max(j, i + 1)
    return starts[:m], stops[:m]


@njit(cache=True)
def _heap_push(heap: np.ndarray, size: int, x: float) -> int:
    """Push ``x`` onto the min-heap ``heap[:size]``; returns the new size."""
    k = size
    heap[k] = x
    while k > 0:
        parent = (k - 1) // 2
        if heap[parent] <= heap[k]:
            break
        heap[parent], heap[k] = heap[k], heap[parent]
        k = parent
    return size + 1


@njit(cache=True)
def _heap_pop(heap: np.ndarray, size: int) -> tuple[int, float]:
    """Pop the smallest of the min-heap ``heap[:size]``; returns the new size and the value."""
    top = heap[0]
    size -= 1
    heap[0] = heap[size]
    k = 0
    while True:
        left = 2 * k + 1
        if left >= size:
            break
        child = left
        if left + 1 < size and heap[left + 1] < heap[left]:
            child = left + 1
        if heap[k] <= heap[child]:
            break
        heap[k], heap[child] = heap[child], heap[k]
        k = child
    return size, top


def plateaus_from_times(
    time_s: np.ndarray, speed_rpm: np.ndarray, windows: list[tuple[float, float]] | tuple[tuple[float, float], ...]
) -> list[Plateau]:
    """Operating points from given ``(t_start, t_end)`` windows (flags or config)."""
    out = []
    for t0, t1 in windows:
        start = int(np.searchsorted(time_s, t0, side="left"))
        stop = int(np.searchsorted(time_s, t1, side="right"))
        if stop - start < 2:
            continue
        seg = slice(start, stop)
        out.append(Plateau(start, stop, float(np.mean(speed_rpm[seg])), float(time_s[start]), float(time_s[stop - 1])))
    return out
