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
MAX_DRIFT_PPM = 500.0
"""A clock fit drifting more than this is a failed alignment, not a result (quartz: tens of ppm)."""
MAX_MISFIT = 0.5
"""Relative RMS misfit of the aligned shared signals above which the alignment failed."""
WARN_DRIFT_PPM = 200.0
"""An estimated drift beyond this is reported with a warning (two quartz clocks of +-100 ppm)."""
SAME_CLOCK_LAG_S = 0.05
"""With overlapping times, a shared rotation signal lagging by more than this means the clocks differ."""
MIN_LAG_CORRELATION = 0.3
"""Normalised correlation at the coarse lag below which the lag says nothing about the clocks."""


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

    def to_clock1(self, t2: np.ndarray) -> np.ndarray:
        return (np.asarray(t2, dtype=float) - self.offset_s) / (1.0 + 1e-6 * self.drift_ppm)

    def as_dict(self) -> dict:
        return {"offset_s": self.offset_s, "drift_ppm": self.drift_ppm, "misfit": self.misfit,
                "points": self.n_points}


def resample_uniform(time_s: np.ndarray, columns: dict[str, np.ndarray], source: str,
                     time_name: str = "time", lines: np.ndarray | None = None) -> Resampled:
    """Put non-uniformly sampled columns on the uniform grid of their mean interval.

    Jitter is the deviation of each timestamp from the nearest uniform grid
    point fitted through the timestamps (``t0 + k dt``).  A record that is
    uniform within 1e-6 of an interval is returned unchanged.

    Raises
    ------
    InputDataError
        Times not strictly increasing, or a gap over ``MAX_GAP_FACTOR``
        intervals (data missing, not jitter); the message names the file line
        (``lines``: the file line of each sample) or else the sample.
    """
    t = np.asarray(time_s, dtype=float)
    if t.size < 3 or not np.all(np.isfinite(t)):
        raise InputDataError(f"{source}: {time_name}: needs at least 3 finite times")
    dt = np.diff(t)

    def where(i: int) -> str:
        return f"{source}:{int(lines[i])}: column {time_name!r}" if lines is not None else \
            f"{source}: {time_name}: sample {i}"

    bad = np.flatnonzero(dt <= 0)
    if bad.size:
        raise InputDataError(f"{where(bad[0] + 1)}: times not strictly increasing "
                             f"({t[bad[0]]:.6g} then {t[bad[0] + 1]:.6g})")
    k = np.arange(t.size)
    slope, icpt = np.polyfit(k, t, 1)
    step = float(slope)  # the mean interval: robust to jitter, unlike one interval
    gap = np.flatnonzero(dt > MAX_GAP_FACTOR * step)
    if gap.size:
        raise InputDataError(f"{where(gap[0] + 1)}: a gap of {dt[gap[0]]:.4g} s before it "
                             f"(mean interval {step:.4g} s): data missing, not jitter")
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


@dataclass(frozen=True)
class _Shared:
    """The shared signal of both records, low-passed on uniform grids of their own clocks."""

    g1: np.ndarray
    a: np.ndarray
    g2: np.ndarray
    b: np.ndarray


def _shared(t1: np.ndarray, x1: np.ndarray, t2: np.ndarray, x2: np.ndarray, fs_hz: float,
            source: str) -> _Shared:
    g1 = np.arange(t1[0], t1[-1], 1.0 / fs_hz)
    g2 = np.arange(t2[0], t2[-1], 1.0 / fs_hz)
    if g1.size < 10 * fs_hz / LOWPASS_HZ or g2.size < 10 * fs_hz / LOWPASS_HZ:
        raise InputDataError(f"{source}: records too short to align their clocks ({g1.size}, {g2.size} samples)")
    a = _lowpass(np.interp(g1, t1, x1), fs_hz)
    b = _lowpass(np.interp(g2, t2, x2), fs_hz)
    if not (np.all(np.isfinite(a)) and np.all(np.isfinite(b))) or np.ptp(a) == 0 or np.ptp(b) == 0:
        raise InputDataError(f"{source}: the alignment signals do not change; nothing to align the clocks on")
    return _Shared(g1, a, g2, b)


def _coarse(s: _Shared, fs_hz: float, max_offset_s: float, source: str) -> tuple[float, float]:
    """Lag ``t2 - t1`` of the peak of the cross-correlation of the derivatives, and its normalised height."""
    # c[k] = sum_n a'[n] b'[n + k - (n_a - 1)], peak -> t2 - t1
    da, db = np.diff(s.a), np.diff(s.b)
    c = fftconvolve(db, da[::-1], mode="full")
    lags_s = (np.arange(c.size) - (da.size - 1)) / fs_hz + (s.g2[0] - s.g1[0])
    ok = np.abs(lags_s) <= max_offset_s
    if not np.any(ok):
        raise InputDataError(f"{source}: the records do not overlap within +-{max_offset_s:g} s")
    k = int(np.argmax(np.where(ok, np.abs(c), -np.inf)))
    # normalised by the energy of the overlapping stretches at that lag: 1 = the same signal
    n_a, shift = da.size, k - (da.size - 1)
    lo, hi = max(0, -shift), min(n_a, db.size - shift)
    energy = np.sqrt(np.sum(da[lo:hi] ** 2) * np.sum(db[lo + shift:hi + shift] ** 2)) if hi > lo else 0.0
    return float(lags_s[k]), float(abs(c[k]) / energy) if energy > 0 else 0.0


def coarse_offset(t1: np.ndarray, x1: np.ndarray, t2: np.ndarray, x2: np.ndarray, fs_hz: float, *,
                  max_offset_s: float = 10.0, source: str = "") -> tuple[float, float]:
    """Coarse ``t2 - t1`` from a shared signal (the first step of :func:`estimate_clock`) and the
    normalised correlation at that lag (near 1: the same motion; near 0: the lag means nothing)."""
    return _coarse(_shared(t1, x1, t2, x2, fs_hz, source), fs_hz, max_offset_s, source)


def estimate_clock(t1: np.ndarray, x1: np.ndarray, t2: np.ndarray, x2: np.ndarray,
                   fs_hz: float, *, max_offset_s: float = 10.0, source: str = "") -> ClockFit:
    """Offset and drift of clock 2 against clock 1 from a shared signal (see module notes).

    ``x1`` and ``x2`` are the same motion up to scale (a gear ratio), e.g. the
    speeds of two geared shafts; both are interpolated onto uniform grids at
    ``fs_hz`` on their own clocks.  The fit is returned as found: judge it with
    :func:`check_clock`.
    """
    s = _shared(t1, x1, t2, x2, fs_hz, source)
    g1, a, g2, b = s.g1, s.a, s.g2, s.b
    tau0, _ = _coarse(s, fs_hz, max_offset_s, source)
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


def check_clock(fit: ClockFit, source: str, how: str = "") -> ClockFit:
    """``fit`` if it is what two clocks can do, else an error saying why it failed.

    A quartz clock drifts tens of ppm: beyond :data:`MAX_DRIFT_PPM` the fit
    has matched signals that are not the same motion, or the records share one
    clock and the estimate is noise.  A relative misfit over
    :data:`MAX_MISFIT` means the aligned signals do not agree.
    """
    why = []
    if not abs(fit.drift_ppm) <= MAX_DRIFT_PPM:
        why.append(f"drift {fit.drift_ppm:+.6g} ppm (a clock drifts tens of ppm; bound {MAX_DRIFT_PPM:g})")
    if not fit.misfit <= MAX_MISFIT:
        why.append(f"misfit {fit.misfit:.3f} of the aligned signals (bound {MAX_MISFIT:g})")
    if why:
        raise InputDataError(f"{source}: clock alignment failed{how}: {' and '.join(why)}; offset "
                             f"{fit.offset_s:+.4f} s not used. If the loggers share one clock give --same-clock "
                             "[--clock-offset-s X]; else --align COL1:COL2 with a rotation column of each file "
                             "that follows the same motion")
    return fit


def on_grid(base: Resampled, other: Resampled, other_time: np.ndarray, source: str,
            min_samples: int = 100) -> tuple[np.ndarray, dict[str, np.ndarray], dict[str, np.ndarray]]:
    """Both records on ``base``'s instants, cut to their overlap.

    ``other_time`` is ``base.time_s`` read on ``other``'s clock.  Returns the
    kept base times, the base columns cut and the other record's columns
    interpolated there.
    """
    idx = np.flatnonzero((other_time >= other.time_s[0]) & (other_time <= other.time_s[-1]))
    if idx.size < min_samples:
        raise InputDataError(f"{source}: the records overlap in only {idx.size} samples on one time base "
                             f"(first {base.time_s[0]:.6g}-{base.time_s[-1]:.6g} s, second "
                             f"{other.time_s[0]:.6g}-{other.time_s[-1]:.6g} s on its clock)")
    sl = slice(idx[0], idx[-1] + 1)
    cut = {n: c[sl] for n, c in base.columns.items()}
    moved = {n: np.interp(other_time[sl], other.time_s, c) for n, c in other.columns.items()}
    return base.time_s[sl], cut, moved


@dataclass(frozen=True)
class Clock:
    """How the second record's clock was put on the first's: the fit, whether it was estimated, and why."""

    fit: ClockFit
    mode: str  # "same" (given or assumed) or "estimated"
    text: str
    warnings: tuple[str, ...] = ()

    def as_dict(self, aligned_on: str = "") -> dict:
        fit = self.fit.as_dict()
        if self.mode != "estimated":
            fit["misfit"] = None  # nothing was fitted
        return {**fit, "mode": self.mode, "estimated": self.mode == "estimated",
                "aligned_on": aligned_on, "text": self.text, "warnings": list(self.warnings)}


def _span(t: np.ndarray) -> str:
    return f"{t[0]:.6g}-{t[-1]:.6g} s"


def decide_clock(t1: np.ndarray, x1: np.ndarray | None, t2: np.ndarray, x2: np.ndarray | None, fs_hz: float,
                 *, mode: str = "auto", offset_s: float = 0.0, source: str = "", on: str = "") -> Clock:
    """The second record's clock against the first: given, estimated, or estimated only where needed.

    ``mode``: ``same`` (one clock, ``t2 = t1 + offset_s``, nothing estimated),
    ``estimate`` (offset and drift from the shared rotation signals ``x1``,
    ``x2``, judged by :func:`check_clock`) or ``auto``: estimated when the
    clocks plainly differ (the records' times overlap by less than half the
    shorter record, or the shared rotation signal lags by more than
    :data:`SAME_CLOCK_LAG_S` with a clear correlation), else one clock is
    assumed and the note says so.  ``x1``/``x2`` ``None``: no rotation signal
    in that record.
    """
    if mode == "same":
        return Clock(ClockFit(float(offset_s), 0.0, 0.0, 0), "same",
                     f"one clock (--same-clock): second file's time = first's {offset_s:+.4f} s; nothing estimated")
    overlap = min(t1[-1], t2[-1]) - max(t1[0], t2[0])
    apart = overlap < 0.5 * min(t1[-1] - t1[0], t2[-1] - t2[0])
    why = ""
    if mode == "auto" and not apart:
        if x1 is None or x2 is None:
            return Clock(ClockFit(0.0, 0.0, 0.0, 0), "same",
                         "one clock assumed: the files' times overlap and no rotation column in both files "
                         "could check it (--align COL1:COL2 estimates offset and drift, --same-clock states it)")
        lag, corr = coarse_offset(t1, x1, t2, x2, fs_hz, source=source)
        if not (corr >= MIN_LAG_CORRELATION and abs(lag) > SAME_CLOCK_LAG_S):
            return Clock(ClockFit(0.0, 0.0, 0.0, 0), "same",
                         f"one clock assumed: the files' times overlap and {on} show no lag beyond "
                         f"{1e3 * SAME_CLOCK_LAG_S:g} ms (coarse lag {1e3 * lag:+.1f} ms, correlation {corr:.2f}); "
                         "--align estimates offset and drift, --same-clock states it")
        why = f"{on} lag by {lag:+.3f} s on the files' time columns"
    elif mode == "auto":
        why = (f"the files' times overlap by {max(overlap, 0.0):.4g} s only (first {_span(t1)}, "
               f"second {_span(t2)})")
    if x1 is None or x2 is None:
        raise InputDataError(f"{source}: cannot align the clocks: " + (f"{why}, and " if why else "")
                             + "no rotation column in both files; give --align COL1:COL2, or --same-clock "
                             "[--clock-offset-s X] if the loggers share one clock")
    how = f" ({why})" if why else " (--align)"
    fit = check_clock(estimate_clock(t1, x1, t2, x2, fs_hz, max_offset_s=np.inf if apart else 10.0,
                                     source=source), source, how)
    warn = ()
    if abs(fit.drift_ppm) > WARN_DRIFT_PPM:
        warn = (f"{source}: estimated clock drift {fit.drift_ppm:+.1f} ppm is more than two quartz clocks "
                f"usually differ (up to {WARN_DRIFT_PPM:g} ppm); if the loggers share one clock give --same-clock",)
    return Clock(fit, "estimated", f"clock of the second file estimated{how}: offset {fit.offset_s:+.4f} s, "
                 f"drift {fit.drift_ppm:+.1f} ppm (misfit {fit.misfit:.3f}, on {on})", warn)
