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
    dt = float(np.median(np.diff(time_s[:100_001])))  # uniform times: the first 100,000 intervals tell it
    win = max(1, int(round(smooth_s / dt)))
    smooth = uniform_filter1d(np.asarray(speed_rpm, dtype=float), size=win, mode="nearest")
    trim = int(round(trim_s / dt))
    min_len = int(round(min_duration_s / dt))
    # the slope (np.gradient's differences) is taken inside: an hour at 1 kHz holds no array of it
    starts, stops = _steady_runs(smooth, dt, float(max_rate_rpm_s), float(tol_rpm), max(1, win))
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
def _slow(smooth: np.ndarray, j: int, dt: float, max_rate: float) -> bool:
    """``|slope| < max_rate`` at ``j``, the slope as :func:`numpy.gradient` takes it (one-sided at the ends)."""
    n = smooth.shape[0]
    if j == 0:
        rate = (smooth[1] - smooth[0]) / dt
    elif j == n - 1:
        rate = (smooth[n - 1] - smooth[n - 2]) / dt
    else:
        rate = (smooth[j + 1] - smooth[j - 1]) / (2.0 * dt)
    return abs(rate) < max_rate


@njit(cache=True)
def _steady_runs(smooth: np.ndarray, dt: float, max_rate: float, tol: float,
                 win: int) -> tuple[np.ndarray, np.ndarray]:
    """Runs ``i:j`` of slow samples (slope below ``max_rate``) whose smoothed speed stays within ``tol`` of the
    run's median.

    The median is of ``smooth[i:j]``, updated every ``win`` samples; it is
    kept in two heaps (the lower half in a max-heap, stored negated, the
    upper half in a min-heap), so a run of ``m`` samples costs
    :math:`O(m \\log m)` instead of a partition of the run at every update.
    The runs' bounds and the heaps are kept in arrays that grow as needed.
    """
    n = smooth.shape[0]
    starts = np.empty(64, dtype=np.int64)
    stops = np.empty(64, dtype=np.int64)
    low = np.empty(1024)  # negated: a min-heap of -x is a max-heap of x
    high = np.empty(1024)
    m = 0
    i = 0
    while i < n:
        if not _slow(smooth, i, dt, max_rate):
            i += 1
            continue
        # grow a run while the smoothed speed stays near the running median
        j = i
        level = smooth[i]
        n_low = 0
        n_high = 0
        while j < n and _slow(smooth, j, dt, max_rate) and abs(smooth[j] - level) <= tol:
            x = smooth[j]
            if max(n_low, n_high) + 2 > low.shape[0]:  # the heaps grow with the run
                low = np.concatenate((low, np.empty_like(low)))
                high = np.concatenate((high, np.empty_like(high)))
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
        if m == starts.shape[0]:
            starts = np.concatenate((starts, np.empty_like(starts)))
            stops = np.concatenate((stops, np.empty_like(stops)))
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
