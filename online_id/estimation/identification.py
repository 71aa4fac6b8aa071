"""Offline identification: operating points -> ARMAX per point -> sorted poles -> driveline.

This is the seed paper's experiment as a function: for every steady
operating point an over-parametrised ARMAX model from dyno torque to dyno
speed is estimated (recursive start, then prediction-error minimisation),
one model order is chosen for all points by the summed log-FPE, the poles are
sorted into the invariant driveline pair and the speed-dependent ones, and
the physical parameters follow from the pole pair, the zeros and the gain (or
from given inertias).

Notes
-----
**Cost bounded by information, not by length.**  The information about the
driveline in a steady, excited plateau grows with its length, but the order
search does not need all of it: the model orders are compared, and started,
on the best-excited ``fit_s`` seconds of each plateau (the window of that
length with the largest torque variance, on a one-second grid), so their
cost does not grow with the recording.  The rest of the plateau is held out:
the chosen model's one-step prediction loss on it is reported next to the
fit loss (``validation_V``), and a model that predicts it much worse than
its own window (a plateau that is not steady) gets a warning.  With
``refine_s`` the chosen order is then refitted, from the window's optimum, on
up to ``refine_s`` seconds around the window (a few Gauss-Newton steps), so
a long plateau still sharpens the estimate; ``refine_s=0`` keeps the window
fit.  Fits use the Levenberg-Marquardt solver of
:func:`~online_id.estimation.pem.fit_armax` (``solver="lm"``).
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass, field
from typing import Callable

import numpy as np

from online_id.estimation.settings import IdentificationSettings, InertiaSettings
from online_id.estimation.model import ArmaxOrders
from online_id.estimation.pem import ArmaxFit, fit_armax, predict_errors
from online_id.estimation.window import fit_two_starts
from online_id.analysis.physical import (
    DrivelineParameters,
    ResponseFit,
    fit_response,
    frequency_response,
    parameters,
    response_grid,
)
from online_id.analysis.plateaus import Plateau, find_plateaus, plateaus_from_times
from online_id.analysis.poles import DRIVELINE, Pole, PoleSorting, poles_of, sort_poles
from online_id.estimation.preprocess import decimate, decimation_factor
from online_id.errors import EstimationError, InputDataError
from online_id.records import BenchData

Progress = Callable[[float, str], None]


@dataclass
class PointResult:
    """Identification at one operating point."""

    plateau: Plateau
    dt: float
    fits: dict[ArmaxOrders, ArmaxFit]
    fit: ArmaxFit | None = None
    poles: list[Pole] = field(default_factory=list)
    response: ResponseFit | None = None
    window: tuple[int, int] = (0, 0)
    """Decimated samples ``start:stop`` of the plateau used in the order search."""
    validation_V: float | None = None
    """One-step prediction loss of the window's fit on the rest of the plateau (None if no rest)."""

    @property
    def speed_rpm(self) -> float:
        return self.plateau.speed_rpm


@dataclass
class IdentificationResult:
    """Everything :func:`identify` found."""

    points: list[PointResult]
    orders: ArmaxOrders
    sorting: PoleSorting
    driveline: DrivelineParameters | None
    fs_hz: float
    warnings: list[str]

    def as_dict(self) -> dict:
        drive = self.driveline.as_dict() if self.driveline else None
        if drive is not None and self.sorting.driveline is not None:
            drive["f0_std_hz"] = self.sorting.driveline.f0_std_hz
            drive["zeta_std"] = self.sorting.driveline.zeta_std
            drive["n_points"] = self.sorting.driveline.n_points
        fpes = [p.fit.fpe for p in self.points if p.fit is not None]
        return {
            "driveline": drive,
            "operating_points": [
                {
                    "engine_speed_rpm": p.speed_rpm,
                    "t_start_s": p.plateau.t_start_s,
                    "t_end_s": p.plateau.t_end_s,
                    "n_samples": p.fit.n if p.fit else 0,
                    "fpe": p.fit.fpe if p.fit else None,
                    "fit_window_s": [p.plateau.t_start_s + p.window[0] * p.dt,
                                     p.plateau.t_start_s + p.window[1] * p.dt],
                    "validation_V": p.validation_V,
                    "poles": [q.as_dict() for q in p.poles],
                }
                for p in self.points
            ],
            "model": {
                "na": self.orders.na,
                "nb": self.orders.nb,
                "nc": self.orders.nc,
                "nk": self.orders.nk,
                "fpe": float(np.mean(fpes)) if fpes else None,
                "sample_rate_hz": self.fs_hz,
            },
            "invariant_modes": [{"f_hz": m.f0_hz, "zeta": m.zeta} for m in self.sorting.invariant_modes],
            "rotation_lines": [{"order": x.order, "f_hz": x.f_hz, "zeta": x.zeta, "n_points": x.n_points,
                                "declared": x.declared} for x in self.sorting.lines],
            "warnings": list(self.warnings),
        }


def candidate_orders(s: IdentificationSettings) -> list[ArmaxOrders]:
    """The grid of model orders to try (empty ``nb``/``nc`` lists mean "same as na")."""
    out = []
    for na in s.na:
        nbs = s.nb or (na,)
        ncs = s.nc or (na,)
        for nb, nc in itertools.product(nbs, ncs):
            out.append(ArmaxOrders(na, nb, nc, s.nk))
    return out


def _check_excitation(u: np.ndarray, where: str) -> None:
    spread = float(np.std(u))
    if not np.isfinite(spread) or spread <= 1e-9 * max(1.0, float(np.max(np.abs(u)))):
        raise InputDataError(f"{where}: no excitation: the dyno torque is constant (std {spread:.3g} Nm); "
                             "add a test signal (PRBS) to the torque")


def find_operating_points(data: BenchData, s: IdentificationSettings) -> list[Plateau]:
    """Operating points from the configured windows, or found automatically."""
    rpm = data.engine_speed_rpm
    if s.operating_points:
        return plateaus_from_times(data.time_s, rpm, s.operating_points)
    return find_plateaus(data.time_s, rpm, min_duration_s=s.min_plateau_s, tol_rpm=s.plateau_tol_rpm)


def _segment(data: BenchData, p: Plateau, factor: int) -> tuple[np.ndarray, np.ndarray]:
    """Mean-free, anti-alias decimated (y = dyno speed, u = dyno torque) of one plateau.

    The means are removed because constant terms vanish in the identification
    (seed paper, eq. 10 and 18): friction offset and steady speed.
    """
    seg = slice(p.start, p.stop)
    y = data.dyno_speed_rad_s[seg] - np.mean(data.dyno_speed_rad_s[seg])
    u = data.dyno_torque_nm[seg] - np.mean(data.dyno_torque_nm[seg])
    return decimate(y, factor), decimate(u, factor)


def best_window(u: np.ndarray, n: int, step: int) -> tuple[int, int]:
    """``(start, stop)`` of the ``n`` samples of ``u`` with the largest variance, starts on a grid of ``step``.

    The whole signal when it is not longer than ``n``; the first of equally
    good windows (a steady PRBS excites every window alike).
    """
    if n >= u.size:
        return 0, u.size
    starts = np.arange(0, u.size - n + 1, max(1, step))
    c1 = np.concatenate(([0.0], np.cumsum(u)))
    c2 = np.concatenate(([0.0], np.cumsum(u * u)))
    mean = (c1[starts + n] - c1[starts]) / n
    var = (c2[starts + n] - c2[starts]) / n - mean**2
    best = int(starts[int(np.argmax(np.round(var, 12)))])
    return best, best + n


def _refine_span(size: int, window: tuple[int, int], n: int) -> tuple[int, int]:
    """``n`` samples (at most ``size``) centred on ``window``, shifted to stay inside ``0:size``."""
    if n >= size:
        return 0, size
    n = max(n, window[1] - window[0])
    start = max(0, (window[0] + window[1]) // 2 - n // 2)
    start = min(start, size - n)
    return start, start + n


def _centred(x: np.ndarray) -> np.ndarray:
    """``x`` minus its mean (the slice's own operating point, see :func:`_segment`)."""
    return x - np.mean(x)


def _validate(p: PointResult, y: np.ndarray, u: np.ndarray, warnings: list[str],
              max_ratio: float = 2.0) -> None:
    """Held-out check: the window fit's one-step loss on the rest of the plateau (see module notes).

    The prediction errors run over the whole plateau, so the held-out
    samples continue from the window (and the window from what precedes it);
    the first second of the plateau, where the predictor starts from rest, is
    left out.  The held-out loss is compared with the loss inside the window
    in the same run.
    """
    a, b = p.window
    fit = p.fit
    start = fit.orders.max_lag + int(round(1.0 / p.dt))
    held = np.ones(y.size, dtype=bool)
    held[a:b] = False
    held[:start] = False
    inside = np.zeros(y.size, dtype=bool)
    inside[max(a, start):b] = True
    if np.count_nonzero(held) < 2 * fit.d or np.count_nonzero(inside) < 2 * fit.d:
        return
    eps = predict_errors(y, u, fit.orders, fit.theta)
    p.validation_V = float(np.mean(eps[held] ** 2))
    ratio = p.validation_V / float(np.mean(eps[inside] ** 2))
    if not ratio <= max_ratio:
        warnings.append(f"{p.speed_rpm:.0f} rpm: the model of the {(b - a) * p.dt:.0f} s fit window predicts the "
                        f"other {np.count_nonzero(held) * p.dt:.0f} s of the plateau with {ratio:.2g} times "
                        "its loss in the window: the operating point may not be steady")


def _response_band(point: PointResult, f0_hz: float, nyquist_hz: float) -> np.ndarray:
    return response_grid(f0_hz, nyquist_hz, [q for q in point.poles if q.cls != DRIVELINE], 300)


def identify(
    data: BenchData,
    settings: IdentificationSettings | None = None,
    inertias: InertiaSettings | None = None,
    progress: Progress | None = None,
    *,
    fit_s: float | None = 40.0,
    refine_s: float | None = None,
    solver: str = "lm",
) -> IdentificationResult:
    """Identify the driveline from bench data (see module docstring).

    Parameters
    ----------
    data, settings, inertias
        The record, how to identify, and known inertias.
    progress
        Called as ``progress(fraction, message)``.
    fit_s
        Seconds of each plateau (its best-excited window) on which the order
        grid is fitted; None fits the whole plateau (the cost then grows
        with the recording).
    refine_s
        Seconds of each plateau, around the window, on which the chosen
        order is refitted from the window's optimum; None (default) or 0
        keeps the window fit.
    solver
        :func:`~online_id.estimation.pem.fit_armax` solver, ``"lm"`` or ``"trf"``.
    """
    s = settings or IdentificationSettings()
    inertias = inertias or InertiaSettings()
    report = progress or (lambda frac, msg: None)
    dt_raw = float(np.median(np.diff(data.time_s)))
    fs_raw = 1.0 / dt_raw
    warnings: list[str] = []

    _check_excitation(data.dyno_torque_nm, data.source)
    report(0.0, "finding the operating points")
    plateaus = find_operating_points(data, s)
    target_fs = min(s.sample_rate_hz, fs_raw)
    if s.pulses_per_rev is not None and plateaus:
        # keep the highest compression line well inside the band (below 0.3 fs),
        # where the anti-alias filter leaves it untouched and the model can place its pole
        top_hz = s.pulses_per_rev * max(p.speed_rpm for p in plateaus) / 60.0
        if top_hz > 0.3 * target_fs:
            target_fs = min(fs_raw, top_hz / 0.3)
            if top_hz > 0.3 * target_fs:
                warnings.append(f"the compression line reaches {top_hz:.0f} Hz, close to the Nyquist "
                                f"frequency {fs_raw / 2:.0f} Hz of the data")
    factor = decimation_factor(fs_raw, target_fs)
    dt = dt_raw * factor
    if len(plateaus) < s.min_operating_points:
        found = ", ".join(f"{p.speed_rpm:.0f} rpm" for p in plateaus) or "none"
        raise InputDataError(
            f"{data.source}: found {len(plateaus)} steady operating point(s) ({found}); "
            f"at least {s.min_operating_points} are needed to sort the driveline poles from the "
            f"speed-dependent ones (steady = engine speed within {s.plateau_tol_rpm:g} rpm for "
            f"{s.min_plateau_s:g} s; set identification.operating_points or min_operating_points)"
        )
    candidates = candidate_orders(s)
    points = [PointResult(p, dt, {}) for p in plateaus]
    n_fit = np.iinfo(np.int64).max if fit_s is None else max(int(round(fit_s / dt)), 1)
    step = max(1, int(round(1.0 / dt)))
    total = len(points) * (len(candidates) + (1 if refine_s else 0))
    done = 0
    signals = []
    for point in points:
        y, u = _segment(data, point.plateau, factor)
        _check_excitation(u, f"{data.source}: operating point at {point.speed_rpm:.0f} rpm")
        point.window = best_window(u, n_fit, step)
        a, b = point.window
        signals.append((y, u))
        for orders in candidates:
            report(done / total, f"{point.speed_rpm:.0f} rpm, na={orders.na} nb={orders.nb} nc={orders.nc}")
            try:
                point.fits[orders] = fit_two_starts(_centred(y[a:b]), _centred(u[a:b]), orders, s.recursive_start, solver=solver)
            except EstimationError as err:
                warnings.append(f"{point.speed_rpm:.0f} rpm, {orders}: {err}")
            done += 1
    report(1.0, "sorting poles")

    # one structure for all points: the one with the least summed log-FPE (or AIC)
    def score(o: ArmaxOrders) -> float:
        vals = []
        for p in points:
            fit = p.fits.get(o)
            if fit is None:
                return np.inf
            vals.append(np.log(fit.fpe) if s.criterion == "fpe" else fit.aic)
        return float(np.sum(vals))

    scored = sorted(candidates, key=score)
    if not np.isfinite(score(scored[0])):
        raise EstimationError(f"{data.source}: no model order could be fitted at every operating point")
    orders = scored[0]
    n_refine = int(round(refine_s / dt)) if refine_s else 0
    for p, (y, u) in zip(points, signals):
        p.fit = p.fits[orders]
        a, b = p.window
        _validate(p, y, u, warnings)
        lo, hi = _refine_span(y.size, p.window, n_refine)
        if n_refine and (lo, hi) != (a, b):
            report(done / total, f"{p.speed_rpm:.0f} rpm, refining na={orders.na} on {(hi - lo) * dt:.0f} s")
            try:
                p.fit = fit_armax(_centred(y[lo:hi]), _centred(u[lo:hi]), orders, theta0=p.fit.theta, solver=solver,
                                  start_radius=0.999)
            except EstimationError as err:
                warnings.append(f"{p.speed_rpm:.0f} rpm: refining on {(hi - lo) * dt:.0f} s failed, "
                                f"the fit of the {(b - a) * dt:.0f} s window is kept: {err}")
        done += 1
        p.poles = poles_of(p.fit.A, dt)

    sorting = sort_poles(
        [p.poles for p in points],
        [p.speed_rpm for p in points],
        band_hz=(s.band_hz[0], min(s.band_hz[1], 0.45 / dt)),
        pulses_per_rev=s.pulses_per_rev,
        tol_pct=s.invariant_tol_pct,
        max_freq_hz=0.4 / dt,
    )
    for p, row in zip(points, sorting.poles):
        p.poles = row
    warnings += [line.text() for line in sorting.lines if not line.declared]

    driveline = None
    if sorting.driveline is None:
        warnings.append("no invariant lightly damped pole pair was found at the operating points")
    else:
        mode = sorting.driveline
        fas, gains = [], []
        for p in points:
            f = _response_band(p, mode.f0_hz, 0.5 / dt)
            try:
                p.response = fit_response(f, frequency_response(p.fit.B, p.fit.A, f, dt), mode.f0_hz, mode.zeta)
            except EstimationError as err:
                warnings.append(f"{p.speed_rpm:.0f} rpm: {err}")
                continue
            fas.append(p.response.fa_hz)
            gains.append(p.response.gain)
        fa = float(np.median(fas)) if fas else None
        gain = float(np.median(gains)) if gains else None
        driveline = parameters(
            mode.f0_hz, mode.zeta, fa, gain, J1=inertias.J1, J2=inertias.J2, J_total=inertias.J_total
        )
        for name in ("J1", "J2", "c_s"):
            value = getattr(driveline, name)
            if value is not None and not value > 0:
                warnings.append(f"{name} comes out {value:.3g} from {driveline.source}: not physical; the pole "
                                "pair taken for the driveline may not be its resonance, or the anti-resonance "
                                "and gain read from the model are off (give known inertias with --J1/--J2)")
    return IdentificationResult(points, orders, sorting, driveline, 1.0 / dt, warnings)
