r"""Two records on their own clocks: offset and drift, and resampling onto one uniform grid.

Notes
-----
The second recorder's clock reads :math:`t_2 = a + (1 + \\delta) t_1` at the
instant the first reads :math:`t_1`.  Both records carry a signal of the
same motion (e.g. the speed of a shaft on one side and the speed of a shaft
geared to it on the other; a gear only scales it).  The signals (e.g. the speeds of two geared shafts) are put on uniform grids
of their own clocks, low-passed below ``LOWPASS_HZ`` (zero phase, both alike:
there the geared shafts move as one, so the compliance between them adds no
lag) and normalised.  The global cross-correlation of their derivatives
(FFT) gives the coarse offset; then :math:`a, \delta`, a gain and a bias are
fitted by least squares, :math:`x_2(a + (1+\delta) t_1) = g x_1(t_1) + k`.
``misfit`` is the RMS of that fit's residual relative to the normalised
signal (0 = the records agree exactly).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.optimize import least_squares
from scipy.signal import butter, fftconvolve, sosfiltfilt

from online_id.errors import InputDataError

LOWPASS_HZ = 3.0
EDGE_PERIODS = 6.0
MAX_GAP_FACTOR = 20.0


@dataclass(frozen=True)
class Resampled:
    """A record put on a uniform grid, with its sampling jitter."""

    time_s: np.ndarray
    columns: dict[str, np.ndarray]
    fs_hz: float
    jitter_rms_s: float
    jitter_max_s: float
    resampled: bool

    def as_dict(self) -> dict:
        return {"fs_hz": self.fs_hz, "jitter_rms_s": self.jitter_rms_s,
                "jitter_max_s": self.jitter_max_s, "resampled": self.resampled}


@dataclass(frozen=True)
class ClockFit:
    """``t_2 = offset_s + (1 + drift_ppm 1e-6) t_1``."""

    offset_s: float
    drift_ppm: float
    misfit: float
    n_points: int

    def to_clock2(self, t1: np.ndarray) -> np.ndarray:
        return self.offset_s + (1.0 + 1e-6 * self.drift_ppm) * np.asarray(t1, dtype=float)

    def as_dict(self) -> dict:
        return {"offset_s": self.offset_s, "drift_ppm": self.drift_ppm, "misfit": self.misfit,
                "points": self.n_points}


def resample_uniform(time_s: np.ndarray, columns: dict[str, np.ndarray], source: str,
                     time_name: str = "time") -> Resampled:
    """Put non-uniformly sampled columns on the uniform grid of their mean interval.

    Jitter is the deviation of each timestamp from the nearest uniform grid
    point fitted through the timestamps (``t0 + k dt``).  A record that is
    uniform within 1e-6 of an interval is returned unchanged.

    Raises
    ------
    InputDataError
        Times not strictly increasing, or a gap over ``MAX_GAP_FACTOR``
        intervals (data missing, not jitter); the message names the sample.
    """
    t = np.asarray(time_s, dtype=float)
    if t.size < 3 or not np.all(np.isfinite(t)):
        raise InputDataError(f"{source}: {time_name}: needs at least 3 finite times")
    dt = np.diff(t)
    bad = np.flatnonzero(dt <= 0)
    if bad.size:
        raise InputDataError(f"{source}: {time_name}: times not strictly increasing at sample {bad[0] + 1} "
                             f"({t[bad[0]]:.6g} then {t[bad[0] + 1]:.6g})")
    k = np.arange(t.size)
    slope, icpt = np.polyfit(k, t, 1)
    step = float(slope)  # the mean interval: robust to jitter, unlike one interval
    gap = np.flatnonzero(dt > MAX_GAP_FACTOR * step)
    if gap.size:
        raise InputDataError(f"{source}: {time_name}: a gap of {dt[gap[0]]:.4g} s after sample {gap[0]} "
                             f"(median interval {step:.4g} s): data missing, not jitter")
    dev = t - (icpt + slope * k)
    jit_rms, jit_max = float(np.sqrt(np.mean(dev**2))), float(np.max(np.abs(dev)))
    if np.max(np.abs(dt - step)) <= 1e-6 * step:
        return Resampled(t, {n: np.asarray(c, dtype=float) for n, c in columns.items()}, 1.0 / step,
                         jit_rms, jit_max, False)
    grid = t[0] + step * np.arange(int(np.floor((t[-1] - t[0]) / step)) + 1)
    out = {n: np.interp(grid, t, np.asarray(c, dtype=float)) for n, c in columns.items()}
    return Resampled(grid, out, 1.0 / step, jit_rms, jit_max, True)


def _lowpass(x: np.ndarray, fs_hz: float) -> np.ndarray:
    sos = butter(4, min(LOWPASS_HZ, 0.2 * fs_hz), fs=fs_hz, output="sos")
    y = sosfiltfilt(sos, np.asarray(x, dtype=float) - np.mean(x))
    return y / (y.std() + 1e-300)


def estimate_clock(t1: np.ndarray, x1: np.ndarray, t2: np.ndarray, x2: np.ndarray,
                   fs_hz: float, *, max_offset_s: float = 10.0, source: str = "") -> ClockFit:
    """Offset and drift of clock 2 against clock 1 from a shared signal (see module notes).

    ``x1`` and ``x2`` are the same motion up to scale (a gear ratio), e.g. the
    speeds of two geared shafts; both are interpolated onto uniform grids at
    ``fs_hz`` on their own clocks.
    """
    g1 = np.arange(t1[0], t1[-1], 1.0 / fs_hz)
    g2 = np.arange(t2[0], t2[-1], 1.0 / fs_hz)
    if g1.size < 10 * fs_hz / LOWPASS_HZ or g2.size < 10 * fs_hz / LOWPASS_HZ:
        raise InputDataError(f"{source}: records too short to align their clocks ({g1.size}, {g2.size} samples)")
    a = _lowpass(np.interp(g1, t1, x1), fs_hz)
    b = _lowpass(np.interp(g2, t2, x2), fs_hz)
    if not (np.all(np.isfinite(a)) and np.all(np.isfinite(b))) or np.ptp(a) == 0 or np.ptp(b) == 0:
        raise InputDataError(f"{source}: the alignment signals do not change; nothing to align the clocks on")
    # coarse: c[k] = sum_n a'[n] b'[n + k - (n_a - 1)], peak -> t2 - t1
    da, db = np.diff(a), np.diff(b)
    c = fftconvolve(db, da[::-1], mode="full")
    lags_s = (np.arange(c.size) - (da.size - 1)) / fs_hz + (g2[0] - g1[0])
    ok = np.abs(lags_s) <= max_offset_s
    if not np.any(ok):
        raise InputDataError(f"{source}: the records do not overlap within +-{max_offset_s:g} s")
    tau0 = float(lags_s[int(np.argmax(np.where(ok, np.abs(c), -np.inf)))])
    # fine: least squares on b(offset + (1 + delta) t1) = gain a(t1) + bias
    step = max(1, int(fs_hz / (20.0 * LOWPASS_HZ)))
    edge = EDGE_PERIODS / LOWPASS_HZ  # the filters' start and end transients differ between the records
    keep = slice(int(edge * fs_hz), g1.size - int(edge * fs_hz), step)
    ts, av = g1[keep], a[keep]

    def resid(p: np.ndarray) -> np.ndarray:
        t2p = p[0] + (1.0 + 1e-6 * p[1]) * ts
        inside = (t2p >= g2[0] + edge) & (t2p <= g2[-1] - edge)
        return np.where(inside, np.interp(t2p, g2, b) - p[2] * av - p[3], 0.0)

    sign = float(np.sign(np.dot(np.interp(tau0 + ts, g2, b), av)) or 1.0)
    fit = least_squares(resid, [tau0, 0.0, sign, 0.0], x_scale=[1e-3, 10.0, 1.0, 0.1], method="lm")
    r = resid(fit.x)
    used = int(np.count_nonzero(r))
    if used < 0.2 * ts.size:
        raise InputDataError(f"{source}: too little overlap between the records to align their clocks "
                             f"(coarse offset {tau0:+.3f} s)")
    rel = float(np.sqrt(np.sum(r**2) / used))
    return ClockFit(float(fit.x[0]), float(fit.x[1]), rel, used)
