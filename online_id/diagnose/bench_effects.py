"""Effects of the bench diagnosis: model terms, residual screening and candidate fits.

Notes
-----
Screening reads the residual of both equations on every plateau.  Each
plateau's Welch spectrum is divided by its median and averaged twice: on a
frequency axis (a line fixed in Hz adds up, an order line is smeared) and on
an order axis ``f / rev_hz`` (the reverse).  Peaks of the two averages give
the fixed-frequency and the rotation-order candidates.

Candidates are fitted as real model extensions (:mod:`bench_model`):

======================  ==================================================
rotation order          sin/cos(k theta) of the entering shaft in the
                        equation of that shaft
fixed frequency         sin/cos(2 pi f t) and two lags of the residual
                        band-passed at f (a narrow-band noise model)
additional mode         one more pole pair (na, nb + 2) in one equation
backlash                clip(twist - centre, +-gap/2) at the input lags in
                        both equations, judged against the linear twist
coulomb friction        sign(y1 - y2) at the input lags in both equations
sensor delay            one speed advanced by a fraction of a sample
======================  ==================================================
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
from scipy.ndimage import median_filter
from scipy.optimize import minimize_scalar
from scipy.signal import coherence, find_peaks, iirpeak, lfilter, welch

from online_id.diagnose.bench_model import (EQS, BenchFit, PlateauSignals, Spec, fit_plateau,
                                            fit_spec, plateau_signals)
from online_id.diagnose.bench_data import BenchSeries

ORDER_GRID_STEP = 0.5
MAX_ORDER = 16.0
WELCH_S = 2.0
PEAK_MIN = 4.0      # average normalised PSD a line must reach to be screened
N_LINES = 3         # lines of each type screened per equation
BAND_Q = 8.0
LOCAL_BINS = {"hz": 121, "order": 41}  # running median over +-15 Hz, or +-0.2 orders


@dataclass(frozen=True)
class OrderTerm:
    """Disturbance at ``order`` times the rotation of ``shaft``, entering the equation of ``shaft``."""

    shaft: str
    order: float
    kind: str = "rotation_order_disturbance"

    def columns(self, p: PlateauSignals, eq: str) -> np.ndarray | None:
        if eq != self.shaft or self.order * p.rev_hz >= 0.5 * p.fs_hz:
            return None
        theta = (p.theta1 if self.shaft == "dyno" else p.theta2)[p.rows]
        return np.column_stack((np.sin(self.order * theta), np.cos(self.order * theta)))

    def params(self) -> dict:
        return {"shaft": self.shaft, "order": float(self.order)}


@dataclass(frozen=True)
class FixedTerm:
    """Line at ``freq_hz`` in equation ``eq``: a sinusoid and a narrow-band noise model."""

    freq_hz: float
    eq: str
    kind: str = "fixed_frequency_disturbance"

    def columns(self, p: PlateauSignals, eq: str) -> np.ndarray | None:
        if eq != self.eq:
            return None
        w = 2.0 * np.pi * self.freq_hz * p.time_s[p.rows]
        cols = [np.sin(w), np.cos(w)]
        r = p.residual.get(eq)
        if r is not None:  # baseline residual on the plateau rows, band-passed causally
            b, a = iirpeak(self.freq_hz, BAND_Q, fs=p.fs_hz)
            bp = lfilter(b, a, r)
            cols += [np.concatenate(([0.0] * k, bp[:-k])) for k in (1, 2)]
        return np.column_stack(cols)

    def params(self) -> dict:
        return {"freq_hz": float(self.freq_hz), "shaft": self.eq}


@dataclass(frozen=True)
class TwistTerm:
    """The high-passed twist (linear), or its dead-zone part ``clip(twist - c_p, +-gap/2)``."""

    gap: float = 0.0
    centers: tuple[float, ...] = ()
    nb: int = 4
    kind: str = "backlash"

    def columns(self, p: PlateauSignals, eq: str) -> np.ndarray:
        x = p.twist
        if self.gap > 0:
            x = np.clip(x - self.centers[p.index], -0.5 * self.gap, 0.5 * self.gap)
        return p.lagged(x, np.arange(self.nb))

    def params(self) -> dict:
        return {"gap_rad": float(self.gap)}


@dataclass(frozen=True)
class CoulombTerm:
    """Coulomb friction in the coupling: ``sign(y1 - y2)`` at the input lags."""

    nb: int = 4
    kind: str = "coulomb_friction"

    def columns(self, p: PlateauSignals, eq: str) -> np.ndarray:
        return p.lagged(np.sign(p.y1 - p.y2), np.arange(self.nb))

    def params(self) -> dict:
        return {}


# -- screening ------------------------------------------------------------------

@dataclass(frozen=True)
class Line:
    """A residual line found by screening: ``value`` is the averaged normalised PSD."""

    eq: str
    axis: str  # "hz" or "order"
    at: float
    value: float


def screen_lines(fit: BenchFit) -> list[Line]:
    """Peaks of the plateau-averaged residual spectra, on the Hz and on the order axis."""
    out = []
    ps = fit.plateaus
    fs = ps[0].fs_hz
    f_axis = np.arange(0.5, 0.45 * fs, 0.25)
    k_axis = np.arange(0.25, MAX_ORDER + 1e-9, 0.01)
    k_axis = k_axis[k_axis * min(p.rev_hz for p in ps) < 0.45 * fs]
    for eq in fit.eqs:
        hz, order = [], []
        for p, r in zip(ps, fit.eqs[eq].residuals):
            f, pxx = welch(r, fs=fs, nperseg=int(WELCH_S * fs))
            pxx = pxx / np.median(pxx)
            hz.append(np.interp(f_axis, f, pxx))
            kf = k_axis * p.rev_hz
            order.append(np.where(kf < 0.45 * fs, np.interp(kf, f, pxx), np.nan))
        for axis, grid, spec in (("hz", f_axis, np.mean(hz, axis=0)),
                                 ("order", k_axis, np.nanmean(np.array(order), axis=0))):
            spec = np.nan_to_num(spec)
            local = median_filter(spec, size=LOCAL_BINS[axis], mode="nearest")
            spec = spec / np.maximum(local, 1e-12)  # a line stands out of its neighbourhood
            idx, _ = find_peaks(spec, height=PEAK_MIN, distance=4)
            idx = idx[np.argsort(spec[idx])[::-1]][:N_LINES]
            out += [Line(eq, axis, float(grid[i]), float(spec[i])) for i in idx]
    return out


def order_candidates(lines: list[Line], fit: BenchFit) -> list[OrderTerm]:
    """Order terms at the half-order grid points nearest the order lines (declared orders excluded)."""
    declared = set()
    for p in fit.plateaus:
        declared.update(p.declared)
    out = []
    for line in lines:
        if line.axis != "order":
            continue
        k = round(line.at / ORDER_GRID_STEP) * ORDER_GRID_STEP
        if k <= 0 or k in declared or abs(k - line.at) > 0.05:
            continue
        for shaft in EQS:
            t = OrderTerm(shaft, float(k))
            if t not in out:
                out.append(t)
    return out


def input_coherence(fit: BenchFit, eq: str, freq_hz: float, half_width_hz: float = 2.0) -> float:
    """Largest coherence between the residual of ``eq`` and the dyno torque near ``freq_hz``.

    A mode's line is driven by the measured motion, hence by the test torque;
    an unmeasured narrow-band torque reaches the measured torque only through
    the speed controller, weakly above its bandwidth.
    """
    vals = []
    for p, r in zip(fit.plateaus, fit.eqs[eq].residuals):
        f, c = coherence(r, p.u[p.rows], fs=p.fs_hz, nperseg=int(p.fs_hz))
        band = np.abs(f - freq_hz) <= half_width_hz
        if band.any():
            vals.append(float(np.max(c[band])))
    return float(np.mean(vals)) if vals else 0.0


# -- searches ---------------------------------------------------------------------

def est_loss(series: BenchSeries, spec: Spec, base: BenchFit) -> float:
    """Estimation-block loss of ``spec``: both equations, each relative to ``base``."""
    fit = fit_spec(series, spec)
    total = 0.0
    for eq in EQS:
        e_new = np.concatenate([r[p.est] for r, p in zip(fit.eqs[eq].residuals, fit.plateaus)])
        e_old = np.concatenate([r[p.est] for r, p in zip(base.eqs[eq].residuals, base.plateaus)])
        total += float(np.mean(e_new**2) / np.mean(e_old**2))
    return total


def search_delay(series: BenchSeries, spec: Spec, base: BenchFit, signal: str,
                 max_samples: float) -> Spec:
    """Fractional advance of one speed (``dyno`` or ``engine``) minimising the estimation loss."""
    attr = "shift_dyno" if signal == "dyno" else "shift_engine"
    start = getattr(spec, attr)
    loss = lambda d: est_loss(series, replace(spec, **{attr: start + d}), base)  # noqa: E731
    grid = np.arange(0.5, max_samples + 1e-9, 0.5)
    values = [loss(d) for d in grid]
    i = int(np.argmin(values))
    res = minimize_scalar(loss, bounds=(max(grid[i] - 0.5, 0.05), grid[i] + 0.5), method="bounded",
                          options={"xatol": 0.02})
    d = float(res.x) if res.fun < values[i] else float(grid[i])
    return replace(spec, **{attr: start + d})


def search_backlash(series: BenchSeries, spec: Spec) -> TwistTerm:
    """Gap (shared) and dead-zone centre (per plateau) by grid search on the estimation blocks."""
    ps = plateau_signals(series, spec)
    span = float(np.median([np.subtract(*np.percentile(p.twist[p.rows], [95, 5])) for p in ps]))
    best = (np.inf, None)
    for gap in span * np.geomspace(0.05, 1.0, 5):
        total, centers = 0.0, []
        for p in ps:
            lo, hi = np.percentile(p.twist[p.rows], [10, 90])
            pick = (np.inf, 0.0)
            for c in np.linspace(lo, hi, 4):
                x = np.clip(p.twist - c, -0.5 * gap, 0.5 * gap)
                cols = p.lagged(x, np.arange(spec.nb))
                v = 0.0
                for eq in EQS:
                    r, _, _ = fit_plateau(p, spec, eq, [p.lagged(p.twist, np.arange(spec.nb)), cols])
                    v += float(np.log(np.mean(r[p.est] ** 2)))
                pick = min(pick, (v, float(c)))
            total += pick[0]
            centers.append(pick[1])
        best = min(best, (total, (float(gap), tuple(centers))), key=lambda b: b[0])
    gap, centers = best[1]
    return TwistTerm(gap, centers, spec.nb)
