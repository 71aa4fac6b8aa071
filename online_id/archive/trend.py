"""Wear trends: a bench's resonance and damping at each operating point against the date (no I/O).

Notes
-----
For each bench and operating point (the recordings' engine speeds grouped
where they lie within ``band_rpm`` of each other) and each quantity
(the resonance :math:`f_0` and the damping ratio :math:`\\zeta` of the
archive table, one value per recording):

1. **Baseline** -- the median of the values of the first ``baseline_days``
   (at least ``min_baseline`` recordings): the healthy weeks.  Every value
   becomes a relative change :math:`r_i = 100 (y_i / \\bar y - 1)` [%].
2. **Three models** of :math:`r(t)` (:math:`t` in days) fitted by least
   squares:

   * *no change*: :math:`r = a`;
   * *wear*: a hinge, :math:`r = a + s \\max(0, t - t_0)`, the onset
     :math:`t_0` searched on a half-day grid (at least ``min_after``
     recordings after it);
   * *sudden change*: a step, :math:`r = a + d\\,[t \\ge t_0]`, :math:`t_0`
     between two recordings.

   The model with the least BIC, :math:`n \\ln(RSS/n) + k \\ln n` (k = 1, 3,
   3: the onset counts as a parameter), is kept; a change model is kept only
   where the fitted change at the last recording is also beyond the dead band
   (the live service's ``detection.min_freq_change_pct`` and
   ``min_damping_change_pct``): a healthy bench's day-to-day scatter is no
   trend.
3. **Drift per month** -- the hinge's slope :math:`30.4\\,s` with its 95 %
   interval (Student's t with :math:`n - 3` degrees of freedom, given
   :math:`t_0`); for *no change* the slope of a straight line over all
   recordings, with its interval, is reported (it should hold zero).
4. **Alerts** -- where the fitted change at the last recording passes
   the warning (fault) level, an alert with the date the fitted curve first
   passed it and the onset, in the live service's words
   (:func:`~online_id.monitoring.detection.alarm_message`: "warning: driveline
   frequency 3.1 % lower (stiffness about 6 % lower) since 2025-03-04 ... at
   1500 rpm").
"""

from __future__ import annotations

import datetime as dt
import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from scipy import stats

from online_id.monitoring.detection import DAMPING, FREQUENCY, alarm_message

NONE, WEAR, STEP = "no change", "wear", "sudden change"
DAY_S = 86400.0
MONTH_DAYS = 30.4


@dataclass(frozen=True)
class TrendSettings:
    """How trends are fitted and when they alert (percent of the baseline)."""

    baseline_days: float = 28.0
    min_baseline: int = 4
    min_points: int = 8
    min_after: int = 3
    band_rpm: float = 100.0
    dead_band_freq_pct: float = 0.5  # the live detector's detection.min_freq_change_pct
    dead_band_damping_pct: float = 20.0  # ... and detection.min_damping_change_pct
    warn_freq_pct: float = 1.0  # about 2 % of stiffness
    fault_freq_pct: float = 2.5  # about 5 % of stiffness
    warn_damping_pct: float = 20.0
    fault_damping_pct: float = 40.0

    def __post_init__(self) -> None:
        for name in ("baseline_days", "band_rpm", "warn_freq_pct", "fault_freq_pct", "warn_damping_pct",
                     "fault_damping_pct"):
            if not getattr(self, name) > 0:
                raise ValueError(f"{name}: expected a number > 0, got {getattr(self, name)!r}")
        if self.fault_freq_pct < self.warn_freq_pct or self.fault_damping_pct < self.warn_damping_pct:
            raise ValueError("the fault levels must be at least the warning levels")

    def levels(self, kind: str) -> tuple[float, float, float]:
        """(dead band, warning, fault) of ``kind`` [%]."""
        if kind == FREQUENCY:
            return self.dead_band_freq_pct, self.warn_freq_pct, self.fault_freq_pct
        return self.dead_band_damping_pct, self.warn_damping_pct, self.fault_damping_pct


@dataclass(frozen=True)
class Fit:
    """A model of the relative change r(t) [%]."""

    model: str
    a: float
    slope: float = 0.0  # % per day (wear, or the straight line of no change)
    step: float = 0.0  # % (sudden change)
    t0: float | None = None  # onset [days]
    rss: float = 0.0
    bic: float = 0.0
    slope_ci: tuple[float, float] = (0.0, 0.0)  # 95 % interval of the slope, % per day

    def at(self, t: np.ndarray | float) -> np.ndarray:
        """The fitted change at ``t`` [days]."""
        t = np.asarray(t, dtype=float)
        if self.model == WEAR:
            return self.a + self.slope * np.maximum(0.0, t - self.t0)
        if self.model == STEP:
            return self.a + self.step * (t >= self.t0)
        return self.a + 0.0 * t


def _bic(rss: float, n: int, k: int) -> float:
    return n * math.log(max(rss, 1e-300) / n) + k * math.log(n)


def _line(x: np.ndarray, r: np.ndarray) -> tuple[float, float, float, float]:
    """Least squares ``r = a + b x``: (a, b, rss, standard error of b)."""
    X = np.column_stack([np.ones_like(x), x])
    coef, *_ = np.linalg.lstsq(X, r, rcond=None)
    res = r - X @ coef
    rss = float(res @ res)
    dof = max(r.size - 3, 1)
    sxx = float(np.sum((x - x.mean()) ** 2))
    se = math.sqrt(rss / dof / sxx) if sxx > 0 else math.inf
    return float(coef[0]), float(coef[1]), rss, se


def fit_change(t: np.ndarray, r: np.ndarray, min_after: int = 3) -> tuple[Fit, Fit, Fit, Fit]:
    """(best, no change, wear, sudden change) fits of ``r`` [%] against ``t`` [days] (see module notes)."""
    order = np.argsort(t, kind="stable")
    t, r = np.asarray(t, float)[order], np.asarray(r, float)[order]
    n = r.size
    q = stats.t.ppf(0.975, max(n - 3, 1))
    a0 = float(np.mean(r))
    rss0 = float(np.sum((r - a0) ** 2))
    la, lb, _lrss, lse = _line(t, r)
    none = Fit(NONE, a0, lb, rss=rss0, bic=_bic(rss0, n, 1), slope_ci=(lb - q * lse, lb + q * lse))
    wear = step = None
    last = n - min_after  # the onset leaves at least min_after recordings after it
    if last >= 2:
        # every onset of the grid at once: r = a + s x with x = max(0, t - t0), by the normal equations
        t0s = np.arange(math.floor(t[1]), t[last] + 1e-9, 0.5)
        x = np.maximum(0.0, t[None, :] - t0s[:, None])
        t0s, x = t0s[np.count_nonzero(x > 0, axis=1) >= min_after], x[np.count_nonzero(x > 0, axis=1) >= min_after]
        if t0s.size:
            xc = x - x.mean(axis=1, keepdims=True)
            sxx = np.einsum("ij,ij->i", xc, xc)
            slope = xc @ (r - r.mean()) / sxx
            rss = np.sum((r - r.mean()) ** 2) - slope ** 2 * sxx
            j = int(np.argmin(rss))
            a, s, rss_j, se = _line(x[j], r)  # the best onset's fit again, with its standard error
            wear = Fit(WEAR, a, s, t0=float(t0s[j]), rss=rss_j, bic=_bic(rss_j, n, 3),
                       slope_ci=(s - q * se, s + q * se))
        for k in range(2, last + 1):
            if t[k] == t[k - 1]:
                continue
            a, d = float(np.mean(r[:k])), float(np.mean(r[k:]) - np.mean(r[:k]))
            rss = float(np.sum((r[:k] - a) ** 2) + np.sum((r[k:] - a - d) ** 2))
            if step is None or rss < step.rss:
                step = Fit(STEP, a, 0.0, d, float(0.5 * (t[k - 1] + t[k])), rss, _bic(rss, n, 3))
    wear = wear or none
    step = step or none
    best = min((none, wear, step), key=lambda f: f.bic)
    return best, none, wear, step


@dataclass
class Series:
    """One quantity of one bench at one operating point: the values, the fits, the verdict."""

    bench: str
    kind: str  # FREQUENCY or DAMPING
    speed_rpm: float
    time_s: np.ndarray  # Unix times of the recordings
    values: np.ndarray
    baseline: float | None = None
    baseline_n: int = 0
    fit: Fit | None = None
    change_pct: float | None = None  # fitted change at the last recording
    drift_pct_per_month: float | None = None
    drift_ci: tuple[float, float] | None = None
    onset_s: float | None = None
    level: int = 0  # 0 none, 1 warning, 2 fault
    alert_s: float | None = None  # when the fitted curve first passed the level
    message: str | None = None
    note: str | None = None

    @property
    def t0_s(self) -> float:
        return float(self.time_s.min())

    def relative(self) -> np.ndarray:
        """The values as % of the baseline."""
        return 100.0 * (self.values / self.baseline - 1.0)

    def days(self) -> np.ndarray:
        return (self.time_s - self.t0_s) / DAY_S

    def as_row(self) -> dict[str, Any]:
        """A row of the fleet table."""
        def iso(t: float | None) -> str | None:
            return None if t is None else dt.datetime.fromtimestamp(t, dt.timezone.utc).strftime("%Y-%m-%d")

        return {
            "bench": self.bench, "quantity": "resonance" if self.kind == FREQUENCY else "damping",
            "speed_rpm": round(self.speed_rpm), "recordings": int(self.values.size), "baseline": self.baseline,
            "model": self.fit.model if self.fit else None, "change_pct": self.change_pct,
            "drift_pct_per_month": self.drift_pct_per_month,
            "drift_ci_low": self.drift_ci[0] if self.drift_ci else None,
            "drift_ci_high": self.drift_ci[1] if self.drift_ci else None,
            "onset": iso(self.onset_s), "level": ("fault", "warning", "")[2 - self.level] if self.level else "",
            "alert_date": iso(self.alert_s), "message": self.message or self.note or "",
        }


def analyse(s: Series, settings: TrendSettings) -> Series:
    """Baseline, fits, drift and alert of ``s`` (filled in place and returned)."""
    order = np.argsort(s.time_s, kind="stable")
    s.time_s, s.values = s.time_s[order], s.values[order]
    if s.values.size < settings.min_points:
        s.note = f"{s.values.size} recordings: too few for a trend (at least {settings.min_points})"
        return s
    days = s.days()
    in_base = days < settings.baseline_days
    if np.count_nonzero(in_base) < settings.min_baseline:
        in_base = np.arange(s.values.size) < settings.min_baseline
    s.baseline = float(np.median(s.values[in_base]))
    s.baseline_n = int(np.count_nonzero(in_base))
    r = s.relative()
    best, none, _wear, _step = fit_change(days, r, settings.min_after)
    dead, warn, fault = settings.levels(s.kind)
    end = float(best.at(days[-1]) - best.a)
    if best.model != NONE and abs(end) < dead:
        best = none  # a change within the dead band is no trend
    s.fit = best
    s.change_pct = float(best.at(days[-1])) if best.model != NONE else 0.0
    if best.model == NONE:
        lo, hi = none.slope_ci
        s.drift_pct_per_month, s.drift_ci = MONTH_DAYS * none.slope, (MONTH_DAYS * lo, MONTH_DAYS * hi)
        return s
    s.onset_s = s.t0_s + best.t0 * DAY_S
    if best.model == WEAR:
        lo, hi = best.slope_ci
        s.drift_pct_per_month, s.drift_ci = MONTH_DAYS * best.slope, (MONTH_DAYS * lo, MONTH_DAYS * hi)
    else:
        s.drift_pct_per_month, s.drift_ci = 0.0, (0.0, 0.0)
    size = abs(s.change_pct)
    s.level = 2 if size >= fault else 1 if size >= warn else 0
    if s.level:
        level_pct = fault if s.level == 2 else warn
        if best.model == WEAR and best.slope != 0:
            cross = best.t0 + (math.copysign(level_pct, best.slope) - (best.a)) / best.slope
            cross = min(max(cross, best.t0), days[-1])
        else:
            cross = best.t0
        s.alert_s = s.t0_s + cross * DAY_S
        stiff = 100.0 * ((1.0 + s.change_pct / 100.0) ** 2 - 1.0) if s.kind == FREQUENCY else None
        s.message = alarm_message(s.kind, s.level, s.change_pct, stiff, s.onset_s, s.speed_rpm)
    return s


def operating_points(speeds_rpm: np.ndarray, band_rpm: float) -> np.ndarray:
    """The operating point of each speed: the median of its group, speeds grouped where consecutive sorted
    speeds lie within ``band_rpm`` of each other."""
    speeds = np.asarray(speeds_rpm, dtype=float)
    order = np.argsort(speeds, kind="stable")
    groups = np.zeros(speeds.size, dtype=int)
    g = 0
    for j in range(1, speeds.size):
        if speeds[order[j]] - speeds[order[j - 1]] > band_rpm:
            g += 1
        groups[order[j]] = g
    out = np.empty(speeds.size)
    for k in range(g + 1):
        out[groups == k] = float(np.median(speeds[groups == k]))
    return out


@dataclass
class BenchTrend:
    """Every series of one bench, and its verdict."""

    bench: str
    series: list[Series] = field(default_factory=list)

    @property
    def level(self) -> int:
        return max((s.level for s in self.series), default=0)

    def onset_s(self, kind: str = FREQUENCY) -> float | None:
        """The median onset of the series of ``kind`` with a change (None: none)."""
        onsets = [s.onset_s for s in self.series if s.kind == kind and s.onset_s is not None]
        return float(np.median(onsets)) if onsets else None

    def verdict(self) -> str:
        """One line: the worst alert, or the trend found, or none."""
        alerts = sorted((s for s in self.series if s.level), key=lambda s: (-s.level, s.alert_s or 0.0))
        if alerts:
            return alerts[0].message
        changes = [s for s in self.series if s.fit is not None and s.fit.model != NONE]
        if changes:
            c = changes[0]
            return f"{c.fit.model} of the {'resonance' if c.kind == FREQUENCY else 'damping'} below the warning level"
        return "no trend"


def trends(rows: list[dict[str, Any]], settings: TrendSettings | None = None,
           bench: str | None = None) -> list[BenchTrend]:
    """Per bench (only ``bench`` if given) and operating point, the trend of the resonance and the damping
    from the table rows with status ok and a start time."""
    settings = settings or TrendSettings()
    use = [r for r in rows if r.get("status") == "ok" and r.get("start_time") is not None
           and r.get("f0_hz") is not None and (bench is None or r.get("bench") == bench)]
    out = []
    for name in sorted({r["bench"] for r in use}):
        mine = [r for r in use if r["bench"] == name]
        ops = operating_points(np.array([r["speed_rpm"] for r in mine]), settings.band_rpm)
        bt = BenchTrend(name)
        for op in sorted(set(ops.tolist())):
            sel = [r for r, o in zip(mine, ops) if o == op]
            times = np.array([r["start_time"].timestamp() for r in sel])
            for kind, key in ((FREQUENCY, "f0_hz"), (DAMPING, "zeta")):
                vals = np.array([r[key] if r[key] is not None else np.nan for r in sel], dtype=float)
                keep = np.isfinite(vals)
                bt.series.append(analyse(Series(name, kind, float(op), times[keep], vals[keep]), settings))
        out.append(bt)
    return out
