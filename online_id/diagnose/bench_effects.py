"""Effects of the bench diagnosis: model terms, residual screening and candidate fits.

Notes
-----
Screening reads the residuals on every plateau.  Each plateau's Welch
spectrum is divided by its median and averaged: the inertia equations' on
an order axis ``f / rev_hz`` (an order line adds up, a line fixed in Hz is
smeared), the torque balance's on a frequency axis.  Peaks give the
rotation-order and the fixed-frequency candidates.

Candidates are fitted as real model extensions (:mod:`bench_model`):

======================  ==================================================
rotation order          sin/cos(k theta) of the entering shaft in the
                        equation of that shaft (and the torque balance)
fixed frequency         sin/cos(2 pi f t) and the residual band-passed at
                        f at two lags (a narrow-band noise model), in the
                        torque balance
additional mode         one more pole pair (na, nb + 2) in the engine
                        equation (found in the speed transfer,
                        :mod:`bench_transfer`)
backlash                clip(twist - centre, +-gap/2) at lags 1..nb in both
                        inertia equations, judged against the linear twist
coulomb friction        sign(y1 - y2) at lags 1..nb in both inertia equations
sensor delay            one speed advanced by a fraction of a sample (the
                        delay is fitted to the speed transfer)
======================  ==================================================

Terms acting inside the coupling (twist, Coulomb friction) add nothing to
the torque balance: the shaft torque cancels there.  A line fixed in Hz is
told a mode or a disturbance by its coherence with the reference (the
recorded demand, else the measured torque; :func:`coherence_contrast`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from functools import lru_cache

import numpy as np
from scipy.ndimage import median_filter, uniform_filter1d
from scipy.signal import bilinear, butter, csd, find_peaks, lfilter, sosfilt, welch

from online_id.diagnose.bench_model import (BALANCE, BALANCE_LAGS, EQS, BenchFit, PlateauSignals, Spec, design,
                                            order_columns, output, plateau_signals)
from online_id.diagnose.bench_data import BenchSeries
from online_id.diagnose.effects import BAND_Q, band_past
from online_id.diagnose.residual_tests import angle_periodogram, line_ratio

ORDER_GRID_STEP = 0.5
MAX_ORDER = 16.0
WELCH_S = 2.0
PEAK_MIN = 4.0      # average normalised PSD a line must reach to be screened
N_LINES = 3         # lines of each type screened per equation
BALANCE_BP_LAG = 5  # first lag of the band-passed torque-balance residual (past its speed-noise window)
COH_SMOOTH_BINS = 5  # +-2 Hz at 1 Hz resolution
LOCAL_BINS = {"hz": 121, "order": 41}  # running median over +-15 Hz, or +-0.2 orders


@dataclass(frozen=True)
class OrderTerm:
    """Disturbance at ``order`` times the rotation of ``shaft``, entering the equation of ``shaft``."""

    shaft: str
    order: float
    kind: str = "rotation_order_disturbance"

    def columns(self, p: PlateauSignals, eq: str) -> np.ndarray | None:
        # an external torque: in the equation of its shaft and in the torque balance
        if eq not in (self.shaft, BALANCE) or self.order * p.rev_hz >= 0.5 * p.fs_hz:
            return None
        theta = (p.theta1 if self.shaft == "dyno" else p.theta2)[p.rows]
        return np.column_stack((np.sin(self.order * theta), np.cos(self.order * theta)))

    def params(self) -> dict:
        return {"shaft": self.shaft, "order": float(self.order)}


@dataclass(frozen=True)
class OrderFamilyTerm:
    """Disturbances at several ``orders`` of the rotation of ``shaft`` (a family: one cause, several
    lines), entering the equation of ``shaft`` and the torque balance; orders above the Nyquist frequency
    of a plateau are left out there."""

    shaft: str
    orders: tuple[float, ...]
    kind: str = "rotation_order_disturbance"

    def columns(self, p: PlateauSignals, eq: str) -> np.ndarray | None:
        if eq not in (self.shaft, BALANCE):
            return None
        ks = [k for k in self.orders if k * p.rev_hz < 0.5 * p.fs_hz]
        if not ks:
            return None
        theta = (p.theta1 if self.shaft == "dyno" else p.theta2)[p.rows]
        return order_columns(theta, ks)

    def params(self) -> dict:
        return {"shaft": self.shaft, "family_orders": [float(k) for k in self.orders]}


def fundamental(orders: list[float] | tuple[float, ...], step: float = ORDER_GRID_STEP) -> float:
    """The greatest common divisor of ``orders`` on the grid of ``step`` (half orders): the fundamental of
    a family (0.5, 1.5, 2.5 -> 0.5; 3, 6 -> 3; a single order -> itself)."""
    n = 0
    for k in orders:
        n = math.gcd(n, int(round(k / step)))
    return n * step


def family_reading(shaft: str, orders: list[float], pulses_per_rev: float, named: float | None = None) -> str:
    """What a family of rotation orders on ``shaft``, named by ``named`` (default its fundamental), points to
    (a physical reading for an engineer)."""
    f0 = fundamental(orders) if named is None else named
    listed = ", ".join(f"{k:g}" for k in sorted(orders))
    if shaft == "engine":
        if f0 % 1.0:
            return (f"half orders of the engine ({listed}): cam-synchronous, once per working cycle of a "
                    "four-stroke; one cylinder differs from the others (compression, injection or firing "
                    "imbalance, a misfire)" if len(orders) > 1 or f0 == 0.5 else
                    f"order {f0:g} of the engine alone ({listed}): a half order, cam-synchronous (a cylinder "
                    "that differs, or an auxiliary driven by the camshaft)")
        if pulses_per_rev and (f0 / pulses_per_rev) % 1.0 == 0.0:
            return f"order {f0:g} of the engine ({listed}): a harmonic of the declared compression pulses"
        if f0 == 1.0:
            return (f"once per engine revolution ({listed}): an imbalance or a misalignment of the crank "
                    "train, the flywheel or the coupling")
        return f"order {f0:g} of the engine ({listed}): a torque locked to the crankshaft"
    if shaft == "dyno":
        if f0 in (1.0, 2.0):
            return (f"order {f0:g} of the dyno ({listed}): an imbalance or a misalignment of the dyno's rotor "
                    "or of the coupling (order 2: a cardan joint bent)")
        return (f"order {f0:g} of the dyno ({listed}): locked to the dyno's rotor: a torque ripple of its "
                "drive (pole pairs, slots, the inverter)")
    return f"order {f0:g} of {shaft} ({listed})"


@dataclass(frozen=True)
class FixedTerm:
    """Line at ``freq_hz`` in equation ``eq``: a sinusoid and a narrow-band noise model.

    ``residuals`` holds, per plateau, the residual of the model the line was
    found in (on the plateau's rows); its causal band-pass at ``freq_hz`` at
    two lags a quarter period apart predicts a narrow-band torque from its
    own past.  In the torque balance the lags start at ``BALANCE_BP_LAG``:
    its residual at ``n`` holds the speed noise up to ``n + 2``.
    """

    freq_hz: float
    eq: str
    residuals: tuple = field(default=(), compare=False, repr=False)
    kind: str = "fixed_frequency_disturbance"
    q: float = BAND_Q  # quality factor of the band-pass (a broadband resonance: 1 / (2 zeta))

    def columns(self, p: PlateauSignals, eq: str) -> np.ndarray | None:
        if eq != self.eq:
            return None
        w = 2.0 * np.pi * self.freq_hz * p.time_s[p.rows]
        cols = [np.sin(w), np.cos(w)]
        # the band-passed residual belongs to the record the line was found in (not to the same record at
        # another rate: there the line is the sinusoid alone)
        if self.residuals and len(self.residuals[p.index]) == p.rows.size:
            cols += band_past(self.residuals[p.index], self.freq_hz, p.fs_hz,
                              BALANCE_BP_LAG if eq == BALANCE else 1, self.q)
        return np.column_stack(cols)

    def params(self) -> dict:
        return {"freq_hz": float(self.freq_hz)}


@dataclass(frozen=True)
class TwistTerm:
    """The high-passed twist (linear), or its dead-zone part ``clip(twist - c_p, +-gap/2)``."""

    gap: float = 0.0
    centers: tuple[float, ...] = ()
    nb: int = 4
    kind: str = "backlash"

    def columns(self, p: PlateauSignals, eq: str) -> np.ndarray | None:
        if eq == BALANCE:
            return None  # the shaft torque cancels in the torque balance
        x = p.twist
        if self.gap > 0:
            x = np.clip(x - self.centers[p.index], -0.5 * self.gap, 0.5 * self.gap)
        return p.lagged(x, np.arange(1, self.nb + 1))

    def params(self) -> dict:
        return {"gap_rad": float(self.gap)}


@dataclass(frozen=True)
class CoulombTerm:
    """Coulomb friction in the coupling: ``sign(y1 - y2)`` at the input lags."""

    nb: int = 4
    kind: str = "coulomb_friction"

    def columns(self, p: PlateauSignals, eq: str) -> np.ndarray | None:
        if eq == BALANCE:
            return None  # a torque inside the coupling cancels in the torque balance
        return p.lagged(np.sign(p.y1 - p.y2), np.arange(1, self.nb + 1))

    def params(self) -> dict:
        return {}


@lru_cache(maxsize=1024)
def _branch_filter(freq_hz: float, zeta: float, fs_hz: float) -> tuple[np.ndarray, np.ndarray]:
    """Read-only ``(b, a)`` of ``H = (w^2 + 2 zeta w s) / (s^2 + 2 zeta w s + w^2)`` (``w = 2 pi freq_hz``),
    bilinear at ``fs_hz``; cached, as a branch search filters every plateau at the same grid points."""
    w = 2 * np.pi * freq_hz
    b, a = bilinear([2 * zeta * w, w * w], [1.0, 2 * zeta * w, w * w], fs=fs_hz)
    b.setflags(write=False)
    a.setflags(write=False)
    return b, a


@dataclass(frozen=True)
class BranchTerm:
    """A further inertia hung off the dyno by its own spring and damper, in the torque balance.

    The torque it takes from the dyno is ``J3 s H(s) y1`` with ``H = (w^2 + 2 zeta w s) / (s^2 + 2 zeta
    w s + w^2)`` (``w``, ``zeta``: the inertia on its spring with the dyno held): the balance
    ``u = -J1 y1' - J2 y2' - J3 (H y1)' - w`` gets ``H y1`` (bilinear, causal) at the balance's speed
    lags, whose derivative weights give ``J3``.  Nothing else in the balance predicts it: the speed
    transfer, engine over dyno, does not see what hangs off the dyno.
    """

    freq_hz: float
    zeta: float
    kind: str = "additional_mode"
    eq: str = BALANCE
    speeds: tuple[str, ...] = ("y1",)

    def filtered(self, p: PlateauSignals, speed: str = "y1") -> np.ndarray:
        key = ("branch", speed, self.freq_hz, self.zeta)
        if key not in p.cache:
            b, a = _branch_filter(float(self.freq_hz), float(self.zeta), float(p.fs_hz))
            y = getattr(p, speed)
            p.cache[key] = lfilter(b, a, y - y[p.rows[0]]) + y[p.rows[0]]
        return p.cache[key]

    def columns(self, p: PlateauSignals, eq: str) -> np.ndarray | None:
        if eq != self.eq:
            return None
        lags = BALANCE_LAGS if eq == BALANCE else np.arange(1, 7)
        return np.hstack([p.lagged(self.filtered(p, v), lags) for v in self.speeds])

    def params(self) -> dict:
        return {"branch_freq_hz": float(self.freq_hz), "branch_zeta": float(self.zeta)}


def smooth_reference(fs_hz: float) -> BranchTerm:
    """Both speeds low-passed at the top of the branch band, at the balance's lags: the reference a
    branch is judged against.  The balance's accelerations are noisy differences; a low-passed speed
    gives a better one, whatever hangs off the dyno, and that is no inertia."""
    return BranchTerm(BRANCH_BAND_HZ[1] * fs_hz, BRANCH_ZETAS[-1], speeds=("y1", "y2"), kind="smooth_reference")

    def params(self) -> dict:
        return {"branch_freq_hz": float(self.freq_hz), "branch_zeta": float(self.zeta)}


def chain_modes(masses: tuple[float, ...], springs: list[tuple[int, int, float, float]]) -> list[tuple[float, float]]:
    """Natural frequency [Hz] and damping ratio of each oscillating mode of inertias ``masses`` joined by
    ``springs`` ``(i, j, c, d)``: the eigenvalues of ``M s^2 + D s + K`` with ``Im > 0``."""
    n = len(masses)
    K, D = np.zeros((n, n)), np.zeros((n, n))
    for i, j, c, d in springs:
        g = np.zeros(n)
        g[i], g[j] = 1.0, -1.0
        K += c * np.outer(g, g)
        D += d * np.outer(g, g)
    minv = np.diag(1.0 / np.asarray(masses, dtype=float))
    a = np.block([[np.zeros((n, n)), np.eye(n)], [-minv @ K, -minv @ D]])
    eig = np.linalg.eigvals(a)
    return sorted((float(abs(x) / (2 * np.pi)), float(-x.real / abs(x))) for x in eig
                  if x.imag > 1e-6 * max(np.abs(eig).max(), 1.0))


def branch_inertias(fit: BenchFit) -> tuple[float, float, float]:
    """``(J1, J2, J3)`` of a balance fitted with :func:`smooth_reference` and a :class:`BranchTerm` (its
    last terms), medians over the plateaus.  Every filtered speed has unit gain at low frequency, so its
    lag weights add to its inertia as the raw speed's do (:func:`balance_inertias`); the branch's give
    ``J3``."""
    lags, k = BALANCE_LAGS, BALANCE_LAGS.size
    out = []
    for (j1, j2), p, coef in zip(balance_inertias(fit), fit.plateaus, fit.eqs[BALANCE].coefs):
        js = [float(np.sum(lags * coef[i:i + k or None]) / p.fs_hz) for i in (-3 * k, -2 * k, -k)]
        out.append((j1 + js[0], j2 + js[1], js[2]))
    return tuple(float(np.median(x)) for x in zip(*out))


BRANCH_ZETAS = (0.04, 0.1, 0.2, 0.35)
BRANCH_GRID = 30  # branch frequencies searched, geometric over BRANCH_BAND_HZ
# 15 Hz to 0.3 fs: above it the balance's accelerations are noise, and any low-pass of the dyno speed
# "explains" the torque better than their noisy difference (a heavily damped branch near 0.4 fs removed
# 30-45 % of a clean balance's held-out error)
BRANCH_BAND_HZ = (15.0, 0.3)


def search_branch(series: BenchSeries, spec: Spec, ps: list[PlateauSignals], eq: str = BALANCE) -> BranchTerm:
    """The branch of :class:`BranchTerm` that removes the largest share of the estimation residual of
    equation ``eq`` of ``spec`` (projection, as :func:`search_backlash`): a geometric grid of
    frequencies over the damping ratios, refined once around the best."""
    proj = {p.index: Projector(design(p, spec, eq)[p.est], output(p, eq)[p.est]) for p in ps}

    def score(f: float, z: float) -> float:
        term = BranchTerm(float(f), float(z), eq=eq)
        total = 0.0
        for p in ps:
            x = term.columns(p, eq)[p.est]
            total += proj[p.index].share_of(x)
        return total

    fs = ps[0].fs_hz
    grid = np.geomspace(BRANCH_BAND_HZ[0], BRANCH_BAND_HZ[1] * fs, BRANCH_GRID)
    best = max(((score(f, z), f, z) for f in grid for z in BRANCH_ZETAS))
    step = grid[1] / grid[0]
    fine = np.clip(best[1] * step ** np.linspace(-1, 1, 9), grid[0], grid[-1])
    zs = np.clip(best[2] * np.array([0.7, 1.0, 1.4]), BRANCH_ZETAS[0], BRANCH_ZETAS[-1])
    best = max(((score(f, z), f, z) for f in fine for z in zs))
    return BranchTerm(float(best[1]), float(best[2]), eq=eq)


# -- screening ------------------------------------------------------------------

@dataclass(frozen=True)
class Line:
    """A residual line found by screening: ``value`` is the averaged normalised PSD."""

    eq: str
    axis: str  # "hz" or "order"
    at: float
    value: float


def screen_lines(fit: BenchFit, eqs: tuple[str, ...] | None = None,
                 axes: tuple[str, ...] = ("hz", "order")) -> list[Line]:
    """Peaks of the plateau-averaged residual spectra of ``eqs`` (default all), on the Hz and order axes."""
    return screen_signals(fit.plateaus, {eq: fit.eqs[eq].residuals for eq in (fit.eqs if eqs is None else eqs)},
                          axes)


def speed_lines(ps: list[PlateauSignals]) -> list[Line]:
    """Peaks of the plateau-averaged spectra of the measured speeds on the order axis (``eq`` names the
    speed), the declared orders left out: a strong order line stands out there even where a speed
    equation predicts it from its lags."""
    sig = {eq: [(p.y1 if eq == "dyno" else p.y2)[p.rows] - np.mean((p.y1 if eq == "dyno" else p.y2)[p.rows])
                for p in ps] for eq in EQS}
    return screen_signals(ps, sig, ("order",), exclude=set().union(*(p.declared for p in ps)))


def screen_signals(ps: list[PlateauSignals], signals: dict[str, list[np.ndarray]],
                   axes: tuple[str, ...] = ("hz", "order"), exclude: set | frozenset = frozenset()) -> list[Line]:
    """Peaks of the plateau-averaged spectra of ``signals`` (per name, one array per plateau on its rows),
    each plateau's spectrum over its median, on the Hz and order axes, over their running medians;
    orders within 0.1 of ``exclude`` are left out."""
    out = []
    fs = ps[0].fs_hz
    f_axis = np.arange(0.5, 0.45 * fs, 0.25)
    k_axis = np.arange(0.25, MAX_ORDER + 1e-9, 0.01)
    k_axis = k_axis[k_axis * min(p.rev_hz for p in ps) < 0.45 * fs]
    for eq, sigs in signals.items():
        hz, order = [], []
        for p, r in zip(ps, sigs):
            f, pxx = welch(r, fs=fs, nperseg=int(WELCH_S * fs))
            pxx = pxx / np.median(pxx)
            hz.append(np.interp(f_axis, f, pxx))
            kf = k_axis * p.rev_hz
            order.append(np.where(kf < 0.45 * fs, np.interp(kf, f, pxx), np.nan))
        for axis, grid, spec in (("hz", f_axis, np.mean(hz, axis=0)),
                                 ("order", k_axis, np.nanmean(np.array(order), axis=0))):
            if axis not in axes:
                continue
            spec = np.nan_to_num(spec)
            local = median_filter(spec, size=LOCAL_BINS[axis], mode="nearest")
            spec = spec / np.maximum(local, 1e-12)  # a line stands out of its neighbourhood
            if axis == "order" and exclude:
                spec[np.min(np.abs(grid[:, None] - np.array(sorted(exclude))[None, :]), axis=1) <= 0.1] = 0.0
            idx, _ = find_peaks(spec, height=PEAK_MIN, distance=4)
            idx = idx[np.argsort(spec[idx])[::-1]][:N_LINES]
            out += [Line(eq, axis, float(grid[i]), float(spec[i])) for i in idx]
    return out


SCAN_MIN = 16.0  # line ratio (averaged over plateaus) a grid order must reach: the generic path's whole-record one


def order_scan(ps: list[PlateauSignals], signals: dict[str, list[np.ndarray]],
               exclude: set | frozenset = frozenset(), above: float = 0.0) -> list[Line]:
    """Order lines of ``signals`` (per name, one array per plateau on its rows) found by order tracking,
    as the generic path does (:func:`~online_id.diagnose.residual_tests.angle_periodogram`): each
    plateau's signal resampled on the uniform angle of its shaft (``dyno``: the dyno's, else the
    engine's) and its periodogram taken over the whole plateau.

    A line locked to a shaft stays in one order bin whatever the speed does within the plateau, and its
    height over the floor grows with the number of revolutions, where the Welch screen keeps it at that
    of one 2 s segment.  At each half order (the grid above ``above``, ``exclude`` left out) the line ratio
    (:func:`~online_id.diagnose.residual_tests.line_ratio`) is averaged over the plateaus where the
    order lies below 0.45 fs; the :data:`N_LINES` highest at :data:`SCAN_MIN` or more are returned per
    signal (``value``: that average)."""
    grid = np.arange(ORDER_GRID_STEP, MAX_ORDER + 1e-9, ORDER_GRID_STEP)
    grid = grid[[k > above and all(abs(k - x) > 0.1 for x in exclude) for k in grid]]
    out = []
    for name, sigs in signals.items():
        ratio, count = np.zeros(grid.size), np.zeros(grid.size)
        for p, r in zip(ps, sigs):
            pg = angle_periodogram(r, (p.y1 if name == "dyno" else p.y2)[p.rows], p.fs_hz)
            if pg is None:
                continue
            for i in np.flatnonzero(grid * p.rev_hz < 0.45 * p.fs_hz):
                ratio[i] += line_ratio(*pg, float(grid[i]))
                count[i] += 1
        value = np.divide(ratio, count, out=np.zeros_like(ratio), where=count > 0)
        idx = [i for i in np.argsort(value)[::-1][:N_LINES] if value[i] >= SCAN_MIN]
        out += [Line(name, "order", float(grid[i]), float(value[i])) for i in idx]
    return out


HUMP_BAND = (8.0, 0.4)  # Hz, fraction of fs: where the torque balance's residual is searched for a hump
HUMP_WELCH_S = 1.0


@dataclass(frozen=True)
class Hump:
    """A broad resonance hump in the torque balance's residual spectrum: natural frequency, damping,
    the peak's height over the floor (pooled) and per plateau (the band's mean ratio around it)."""

    freq_hz: float
    zeta: float
    peak: float
    per_plateau: tuple[float, ...]


def balance_hump(fit: BenchFit) -> Hump | None:
    """The broad hump a heavily damped resonance driven by its own noise leaves in the torque balance's
    residual (nothing in the balance predicts it from the speeds).

    Each plateau's residual spectrum (Welch, 1 s) over a smooth floor (a quadratic in log frequency fitted
    robustly: twice, leaving out the bins more than twice above it), the ratios averaged over the
    plateaus, and a resonance ``1 + A / ((1 - (f/f0)^2)^2 + (2 zeta f/f0)^2)`` fitted to them from the
    best of a grid of starts.  A narrow line stands out of a running median and is screened as a line;
    a hump as wide as that neighbourhood does not.
    """
    from scipy.optimize import least_squares as lsq

    ps = fit.plateaus
    fs = ps[0].fs_hz
    ratios = []
    for p, r in zip(ps, fit.eqs[BALANCE].residuals):
        f, pxx = welch(r, fs=fs, nperseg=int(HUMP_WELCH_S * fs))
        band = (f >= HUMP_BAND[0]) & (f <= HUMP_BAND[1] * fs)
        x, y = np.log(f[band]), np.log(np.maximum(pxx[band], 1e-300))
        keep = np.ones(x.size, bool)
        for _ in range(3):
            c = np.polyfit(x[keep], y[keep], 2)
            keep = y - np.polyval(c, x) < np.log(2.0)
        ratios.append(np.exp(y - np.polyval(c, x)))
    fb = f[band]
    R = np.mean(ratios, axis=0)

    def model(v: np.ndarray) -> np.ndarray:
        a, f0, z = np.exp(v)
        q = fb / f0
        return 1.0 + a / ((1 - q * q) ** 2 + (2 * z * q) ** 2)

    best = None
    for f0 in np.geomspace(15.0, HUMP_BAND[1] * 0.75 * fs, 24):
        for z in (0.1, 0.2, 0.3):
            v0 = np.log([max(float(np.interp(f0, fb, R)) - 1.0, 0.05) * (2 * z) ** 2, f0, z])
            cost = float(np.sum((model(v0) - R) ** 2))
            if best is None or cost < best[0]:
                best = (cost, v0)
    fitv = lsq(lambda v: model(v) - R, best[1], method="lm", max_nfev=400).x
    a, f0, z = (float(x) for x in np.exp(fitv))
    if not (HUMP_BAND[0] < f0 < HUMP_BAND[1] * fs and 0.0 < z < 1.0):
        return None
    near = np.abs(fb - f0) <= max(z * f0, 2.0)
    return Hump(f0, z, 1.0 + a / (2 * z) ** 2, tuple(float(np.mean(r[near])) for r in ratios))


def line_strength(fit: BenchFit, eq: str, freq_hz: float) -> list[float]:
    """Per plateau, the residual PSD of ``eq`` at ``freq_hz`` over its median within +-15 Hz.

    A line fixed in Hz stands out on every plateau; an order line that passes
    ``freq_hz`` at one speed stands out on that plateau only.
    """
    out = []
    for p, r in zip(fit.plateaus, fit.eqs[eq].residuals):
        f, pxx = welch(r, fs=p.fs_hz, nperseg=int(WELCH_S * p.fs_hz))
        near = np.abs(f - freq_hz) <= 15.0
        i = int(np.argmin(np.abs(f - freq_hz)))
        peak = float(np.max(pxx[max(i - 1, 0):i + 2]))
        out.append(peak / max(float(np.median(pxx[near])), 1e-300))
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
        out += [t for t in order_terms(k) if t not in out]
    return out


def order_terms(order: float) -> list[OrderTerm]:
    """The order terms tried for a screened ``order``: on the engine, and on the dyno where it is a whole
    order (an electric machine's lines are whole orders of its rotation)."""
    return [OrderTerm(shaft, float(order)) for shaft in EQS if shaft != "dyno" or order % 1 == 0]


def excitation_coherence(fit: BenchFit, eq: str) -> tuple[np.ndarray, np.ndarray]:
    """Coherence between the residual of ``eq`` and the external excitation, pooled over plateaus.

    The excitation is the recorded torque demand (the PRBS) when the series
    has one, else the measured dyno torque.  Cross and auto spectra (Welch,
    1 s segments) are summed over the plateaus, weighted by their length,
    and smoothed over +-2 Hz before the ratio is formed.
    """
    sxy = sxx = syy = 0.0
    for p, r in zip(fit.plateaus, fit.eqs[eq].residuals):
        x = (p.demand if p.demand is not None else p.u)[p.rows]
        nper = int(p.fs_hz)
        f, pxy = csd(x, r, fs=p.fs_hz, nperseg=nper)
        _, pxx = welch(x, fs=p.fs_hz, nperseg=nper)
        _, pyy = welch(r, fs=p.fs_hz, nperseg=nper)
        sxy, sxx, syy = sxy + pxy * r.size, sxx + pxx * r.size, syy + pyy * r.size
    sm = lambda a: uniform_filter1d(a, COH_SMOOTH_BINS)  # noqa: E731
    return f, np.abs(sm(sxy.real) + 1j * sm(sxy.imag)) ** 2 / np.maximum(sm(sxx) * sm(syy), 1e-300)


def coherence_contrast(f: np.ndarray, coh: np.ndarray, freq_hz: float) -> float:
    """Coherence at ``freq_hz`` over the median coherence of its neighbourhood.

    A mode's line is driven by the excitation through the measured motion:
    the residual there stays as coherent with the excitation as around it
    (contrast near or above 1).  An unmeasured narrow-band torque adds power
    that the excitation does not explain: the coherence dips at the line
    (contrast well below 1).  The neighbourhood is +-15 Hz without +-3 Hz.
    """
    i = int(np.argmin(np.abs(f - freq_hz)))
    d = np.abs(f - freq_hz)
    ring = (d > 3.0) & (d <= 15.0) & (f > 1.0)
    ref = float(np.median(coh[ring])) if ring.any() else 0.0
    return float(coh[i] / ref) if ref > 0 else 0.0


# -- the shaft torque ------------------------------------------------------------------

SHAFT_TORQUE_LOWPASS_HZ = 60.0


def balance_inertias(fit: BenchFit) -> list[tuple[float, float]]:
    """``(J1, J2)`` per plateau from the torque balance's speed coefficients.

    The balance ``u[n] = sum_k a_k y1[n - k] + sum_k b_k y2[n - k] + ...``
    stands for ``u = -J1 y1' - J2 y2' - w``: on a ramp ``y = c n / fs`` its
    speed terms give ``-J c``, so ``J1 = sum_k k a_k / fs`` (and ``J2`` from
    ``b``).  Speed noise biases them low by a few per cent.
    """
    lags = BALANCE_LAGS
    out = []
    for p, coef in zip(fit.plateaus, fit.eqs[BALANCE].coefs):
        a, b = coef[:lags.size], coef[lags.size:2 * lags.size]
        out.append((float(np.sum(lags * a) / p.fs_hz), float(np.sum(lags * b) / p.fs_hz)))
    return out


def shaft_torque_reversed(fit: BenchFit) -> list[float]:
    """Per plateau, the share of time [%] the shaft torque has the sign opposite to its median.

    The shaft torque is read from the dyno equation, ``T_s = -u - J1 y1'``
    with ``J1`` from the torque balance, low-passed at 60 Hz (causal).  A
    backlash shows only where the shaft torque reverses and the twist
    crosses the gap; where it never reverses the dead zone cannot be seen.
    Speed noise makes the share a little larger than the truth.
    """
    sos = butter(2, SHAFT_TORQUE_LOWPASS_HZ, fs=fit.plateaus[0].fs_hz, output="sos")
    out = []
    for p, (j1, _) in zip(fit.plateaus, balance_inertias(fit)):
        y1 = p.y1[p.rows[0] - 1:p.rows[-1] + 2]
        acc = 0.5 * (y1[2:] - y1[:-2]) * p.fs_hz
        ts = sosfilt(sos, -p.u[p.rows] - j1 * acc)[int(p.fs_hz):]  # 1 s for the filter to settle
        out.append(float(100.0 * np.mean(np.sign(ts) != np.sign(np.median(ts)))) if ts.size else 0.0)
    return out


# -- searches ---------------------------------------------------------------------

GAP_GRID = np.geomspace(0.04, 1.5, 12)  # gaps searched, times the twist's 5-95 % span
N_CENTRES = 17  # dead-zone centres searched per plateau, between the twist's 1st and 99th percentiles
SEARCH_LAG = 1


class Projector:
    """Least-squares residual maker of one equation's regressors on one plateau's estimation rows."""

    def __init__(self, phi: np.ndarray, y: np.ndarray) -> None:
        scale = np.maximum(np.sqrt(np.mean(phi**2, axis=0)), 1e-300)
        self.q, _ = np.linalg.qr(phi / scale)
        self.r = self.off(y)
        self.ssr = float(self.r @ self.r)

    def off(self, x: np.ndarray) -> np.ndarray:
        return x - self.q @ (self.q.T @ x)

    def shares(self, X: np.ndarray) -> np.ndarray:
        """Share of the residual sum of squares that each column of ``X`` removes alone (one product for all)."""
        xo = self.off(X)
        den = np.einsum("ij,ij->j", xo, xo)
        if self.ssr <= 0:
            return np.zeros(X.shape[1])
        num = (self.r @ xo) ** 2
        return np.divide(num, den * self.ssr, out=np.zeros_like(num), where=den > 0)

    def share_of(self, x: np.ndarray) -> float:
        """Share of the residual sum of squares that the columns ``x`` (2-D) remove together."""
        xo = self.off(x)
        q, rr = np.linalg.qr(xo / np.maximum(np.sqrt(np.mean(xo**2, axis=0)), 1e-300))
        keep = np.abs(np.diag(rr)) > 1e-8 * max(np.abs(np.diag(rr)).max(), 1e-300)
        c = q[:, keep].T @ self.r
        return float(c @ c) / self.ssr if self.ssr > 0 else 0.0


def search_backlash(series: BenchSeries, spec: Spec) -> TwistTerm:
    """Gap (shared) and dead-zone centre (per plateau) of ``clip(twist - c_p, +-gap/2)``.

    ``spec`` is the reference model with the linear twist.  The share of each
    equation's estimation-block residual sum of squares that the dead-zone
    column (at lag 1) removes is computed by projection (Frisch-Waugh: the
    reference regressors are factored once per plateau and equation), summed
    over both equations, maximised over the centre per plateau and summed
    over the plateaus for each gap.  A coarse grid (gaps 0.04-1.5 x the
    twist's 5-95 % span on a geometric grid, 17 centres across the twist's
    range) is refined once around its best point.
    """
    ps = plateau_signals(series, spec)
    span = float(np.median([np.subtract(*np.percentile(p.twist[p.rows], [95, 5])) for p in ps]))
    proj = {}
    for p in ps:
        for eq in EQS:
            phi = design(p, spec, eq)[p.est]
            proj[p.index, eq] = Projector(phi, output(p, eq)[p.est])

    def scores(p: PlateauSignals, gap: float, cs: np.ndarray) -> np.ndarray:
        """The summed share of each centre of ``cs`` at ``gap``."""
        twist = p.twist[p.rows - SEARCH_LAG][p.est]
        X = np.clip(twist[:, None] - np.asarray(cs)[None, :], -0.5 * gap, 0.5 * gap)
        return sum(proj[p.index, eq].shares(X) for eq in EQS)

    def best_centres(gaps: np.ndarray, centres: list[np.ndarray]) -> tuple[float, tuple[float, ...], float]:
        best = (-np.inf, 0.0, ())
        for g in gaps:
            total, picks = 0.0, []
            for p, cs in zip(ps, centres):
                vals = scores(p, g, cs)
                i = int(np.argmax(vals))
                total += vals[i]
                picks.append(float(cs[i]))
            if total > best[0]:
                best = (total, float(g), tuple(picks))
        return best[1], best[2], best[0]

    coarse = [np.percentile(p.twist[p.rows], np.linspace(1, 99, N_CENTRES)) for p in ps]
    gap, centres, _ = best_centres(span * GAP_GRID, coarse)
    step_g = GAP_GRID[1] / GAP_GRID[0]
    fine = [c + np.linspace(-1, 1, 9) * float(np.mean(np.diff(cs))) for c, cs in zip(centres, coarse)]
    gap, centres, _ = best_centres(gap * step_g ** np.linspace(-1, 1, 7), fine)
    return TwistTerm(gap, centres, spec.nb)
