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
**Held out by default.**  Of every operating point, ``holdout`` (a
quarter by default) in one piece before or after the fit window is never
fitted: the chosen model is judged on it as MATLAB's ``compare`` does (NRMSE
fit of the simulated and of the one-step predicted output,
:class:`HeldOutFit`) and its one-step residual is tested as MATLAB's
``resid`` does (:func:`~online_id.estimation.validation.residual_correlation`).
A plateau of 37 s is fitted on 27.75 s and validated on 9.25 s; where a
plateau leaves less than a second, the fit window is compared instead and
``HeldOutFit.held_out`` says so.

**Cost bounded by information, not by length.**  The information about the
driveline in a steady, excited plateau grows with its length, but the order
search does not need all of it: the model orders are compared, and started,
on the best-excited ``fit_s`` seconds of each plateau (the window of that
length with the largest torque variance, on a one-second grid, among those
that leave the held-out piece), so their cost does not grow with the
recording.  Everything outside the window is held out: the chosen model's
one-step prediction loss on it is reported next to the fit loss
(``validation_V``), and a model that predicts it much worse than its own
window (a plateau that is not steady) gets a warning.  With ``refine_s``
the chosen order is then refitted, from the window's optimum, on up to
``refine_s`` seconds around the window but off the held-out piece (a few
Gauss-Newton steps), so a long plateau still sharpens the estimate;
``refine_s=0`` keeps the window fit.  Fits use the Levenberg-Marquardt solver of
:func:`~online_id.estimation.pem.fit_armax` (``solver="lm"``).
"""

from __future__ import annotations

import dataclasses
import itertools
from dataclasses import dataclass, field
from typing import Callable

import numpy as np

from online_id.estimation.settings import HOLDOUT, IdentificationSettings, InertiaSettings
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
from online_id.analysis.poles import DRIVELINE, SPEED_DEPENDENT, Pole, PoleSorting, poles_of, sort_poles
from online_id.estimation.preprocess import decimate, decimation_factor
from online_id.estimation.export import point_model
from online_id.estimation.uncertainty import ParameterStd, from_points
from online_id.estimation.validation import Comparison, ResidualCorrelation, compare, residual_correlation
from online_id.errors import EstimationError, InputDataError
from online_id.records import BenchData

Progress = Callable[[float, str], None]
GUARD = 20
"""Decimated samples between a fit and the held-out stretch: the reach of the zero-phase anti-alias filter
(:func:`~online_id.estimation.preprocess.decimate`: 10 output samples per stage, under 20 for a cascade)."""
MIN_HELD_OUT_S = 1.0
"""A held-out stretch shorter than this is not used (the fit window is compared instead, saying so)."""


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
    held_out: tuple[int, int] | None = None
    """Decimated samples ``start:stop`` of the plateau no fit has seen (None: nothing left to hold out)."""
    offsets: tuple[float, float] = (0.0, 0.0)
    """Means of (dyno speed [rad/s], dyno torque [Nm]) over the plateau: the model's signals are deviations."""
    split_at: int | None = None
    """Decimated sample between the fitted and the held-out side: the two were decimated apart."""
    check: "HeldOutFit | None" = None
    """The chosen model against the held-out samples (or, without them, its fit window)."""
    resid: ResidualCorrelation | None = None
    """Residual tests on the same samples (see :func:`check_point`)."""

    @property
    def speed_rpm(self) -> float:
        return self.plateau.speed_rpm


@dataclass(frozen=True)
class HeldOutFit:
    """MATLAB ``compare`` of a model on one stretch of data: NRMSE fits [%] of simulation and one-step prediction.

    ``held_out`` says whether the stretch lies outside every fit (validation
    data) or is the fit window itself (where the plateau left nothing over).
    """

    fit_sim_pct: float
    fit_pred_pct: float
    span: tuple[int, int]  # decimated samples of the plateau
    held_out: bool
    n_cancelled: int
    n_reflected: int
    skip: int  # samples at the start of the span left out of the fits (the filters start there)

    def as_dict(self, point: "PointResult") -> dict:
        t = point.plateau.t_start_s
        return {"fit_simulation_pct": self.fit_sim_pct, "fit_one_step_pct": self.fit_pred_pct,
                "window_s": [t + self.span[0] * point.dt, t + self.span[1] * point.dt], "held_out": self.held_out,
                "n_samples": self.span[1] - self.span[0] - self.skip}


@dataclass
class IdentificationResult:
    """Everything :func:`identify` found."""

    points: list[PointResult]
    orders: ArmaxOrders
    sorting: PoleSorting
    driveline: DrivelineParameters | None
    fs_hz: float
    warnings: list[str]
    uncertainty: ParameterStd | None = None
    """Standard deviations of the driveline parameters from the fits' covariances."""

    def as_dict(self) -> dict:
        drive = self.driveline.as_dict() if self.driveline else None
        if drive is not None and self.sorting.driveline is not None:
            drive["f0_std_hz"] = self.sorting.driveline.f0_std_hz
            drive["zeta_std"] = self.sorting.driveline.zeta_std
            drive["n_points"] = self.sorting.driveline.n_points
        if drive is not None and self.uncertainty is not None:
            drive["std"] = self.uncertainty.as_dict()
            drive["ci95"] = self.uncertainty.interval(self.driveline)
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
                    "held_out_s": (None if p.held_out is None else
                                   [p.plateau.t_start_s + p.held_out[0] * p.dt,
                                    p.plateau.t_start_s + p.held_out[1] * p.dt]),
                    "validation": p.check.as_dict(p) if p.check is not None else None,
                    "model": point_model(p) if p.fit is not None else None,
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


def _segment(data: BenchData, p: Plateau, factor: int, split_at: int | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Mean-free, anti-alias decimated (y = dyno speed, u = dyno torque) of one plateau.

    The means are removed because constant terms vanish in the identification
    (seed paper, eq. 10 and 18): friction offset and steady speed.  With
    ``split_at`` (a decimated sample) the two sides are made mean-free and
    decimated apart, so that neither side's samples reach the other through
    the mean, the filter or its edge extension (a line through a signal's
    first and last samples).
    """
    if split_at is not None:
        cut = p.start + split_at * factor
        parts = [_segment(data, dataclasses.replace(p, start=a, stop=b), factor) for a, b in
                 ((p.start, cut), (cut, p.stop))]
        return np.concatenate([y for y, _ in parts]), np.concatenate([u for _, u in parts])
    seg = slice(p.start, p.stop)
    y = data.dyno_speed_rad_s[seg] - np.mean(data.dyno_speed_rad_s[seg])
    u = data.dyno_torque_nm[seg] - np.mean(data.dyno_torque_nm[seg])
    return decimate(y, factor), decimate(u, factor)


def best_window(u: np.ndarray, n: int, step: int, keep: int = 0) -> tuple[int, int]:
    """``(start, stop)`` of the ``n`` samples of ``u`` with the largest variance, starts on a grid of ``step``.

    The whole signal when it is not longer than ``n``; the first of equally
    good windows (a steady PRBS excites every window alike).  With ``keep``,
    only windows that leave ``keep`` consecutive samples before or after
    them are considered (held out for validation); ``n`` must leave room.
    """
    if n >= u.size:
        return 0, u.size
    starts = np.arange(0, u.size - n + 1, max(1, step))
    if keep:
        starts = starts[(starts >= keep) | (starts + n <= u.size - keep)]
        starts = np.union1d(starts, [0, u.size - n]).astype(int)  # the two ends always qualify
        starts = starts[(starts >= keep) | (starts + n <= u.size - keep)]
    c1 = np.concatenate(([0.0], np.cumsum(u)))
    c2 = np.concatenate(([0.0], np.cumsum(u * u)))
    mean = (c1[starts + n] - c1[starts]) / n
    var = (c2[starts + n] - c2[starts]) / n - mean**2
    best = int(starts[int(np.argmax(np.round(var, 12)))])
    return best, best + n


def split_plateau(u: np.ndarray, n_fit: int | None, holdout: float, dt: float,
                  min_held_s: float = MIN_HELD_OUT_S) -> tuple[tuple[int, int], tuple[int, int] | None]:
    """The fit window and the held-out stretch of one plateau (decimated samples, see :func:`identify`).

    ``holdout`` of the plateau (rounded up), in one piece before or after
    the window, is kept from the fit; the window is the best-excited
    ``n_fit`` samples (None: all) of the rest.  The held-out stretch is the
    longer piece outside the window, less :data:`GUARD` samples next to it
    (the anti-alias filter's reach, so that no held-out sample leaks into a
    fitted one), when it spans ``min_held_s`` seconds, else None.  With
    ``holdout = 0`` the window may lie anywhere and what is left over (if
    anything) is held out.
    """
    size = u.size
    n_hold = int(np.ceil(holdout * size)) if holdout > 0 else 0
    n = size - n_hold if n_fit is None else min(n_fit, size - n_hold)
    a, b = best_window(u, max(n, 1), max(1, int(round(1.0 / dt))), keep=n_hold)
    before, after = (0, max(a - GUARD, 0)), (min(b + GUARD, size), size)
    rest = max(before, after, key=lambda r: r[1] - r[0])
    held = rest if (rest[1] - rest[0]) * dt >= min_held_s else None
    return (a, b), held


def _refine_span(size: int, window: tuple[int, int], n: int,
                 held: tuple[int, int] | None = None) -> tuple[int, int]:
    """``n`` samples centred on ``window``, shifted to stay inside ``0:size`` and off the ``held`` stretch."""
    lo, hi = 0, size
    if held is not None:
        lo, hi = (held[1] + GUARD, size) if held[0] < window[0] else (0, held[0] - GUARD)
    if n >= hi - lo:
        return lo, hi
    n = max(n, window[1] - window[0])
    start = max(lo, (window[0] + window[1]) // 2 - n // 2)
    start = min(start, hi - n)
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


def compare_point(p: PointResult, y: np.ndarray, u: np.ndarray, span: tuple[int, int]) -> Comparison:
    """MATLAB ``compare`` of the point's model on ``y[a:b]``, ``u[a:b]`` (each made mean-free).

    The simulation (infinite horizon) starts from the initial state that
    fits the span best, without the order-line pole-zero pairs (which the
    torque does not drive) and with unstable poles reflected; the one-step
    prediction starts at the span too, so no sample outside it enters.
    """
    a, b = span
    return compare(p.fit, _centred(y[a:b]), _centred(u[a:b]),
                   cancel=[q.z for q in p.poles if q.cls == SPEED_DEPENDENT], initial="estimate")


def check_point(p: PointResult, y: np.ndarray, u: np.ndarray, span: tuple[int, int] | None = None,
                held_out: bool | None = None) -> None:
    """``p.check`` and ``p.resid``: the chosen model against the plateau's held-out samples.

    ``span`` defaults to ``p.held_out`` or, where the plateau left nothing,
    the fit window (then ``check.held_out`` is False); see
    :func:`compare_point`.  The residual tests take the one-step prediction
    errors on the span after the predictor's start-up.  A span too short
    for the model leaves both None.
    """
    if span is None:
        span = p.held_out if p.held_out is not None else p.window
        held_out = p.held_out is not None
    try:
        c = compare_point(p, y, u, span)
    except EstimationError:
        return
    p.check = HeldOutFit(c.fit_sim_pct, c.fit_pred_pct, span, bool(held_out), c.n_cancelled, c.n_reflected, c.skip)
    skip = max(c.skip, int(round(0.2 / p.dt)))  # the predictor's start-up from rest
    a, b = span
    eps = (c.y - c.y_pred)[skip:]
    try:
        p.resid = residual_correlation(eps, _centred(u[a:b])[skip:])
    except EstimationError:
        p.resid = None


def point_signals(data: BenchData, point: PointResult) -> tuple[np.ndarray, np.ndarray]:
    """The decimated, mean-free (dyno speed [rad/s], dyno torque [Nm]) of one operating point, as identified."""
    dt_raw = float(np.median(np.diff(data.time_s)))
    return _segment(data, point.plateau, max(1, int(round(point.dt / dt_raw))), point.split_at)


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
    holdout: float = HOLDOUT,
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
    holdout
        Fraction of each plateau (in one piece, before or after the fit
        window) that no fit sees: the chosen model is validated on it
        (``PointResult.check``, ``.resid``).  0 lets the window lie anywhere
        and validates on what it leaves (if anything), else on the window.
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
    if not 0.0 <= holdout < 1.0:
        raise EstimationError(f"holdout: expected a fraction 0 <= holdout < 1, got {holdout!r}")
    n_fit = None if fit_s is None else max(int(round(fit_s / dt)), 1)
    total = len(points) * (len(candidates) + (1 if refine_s else 0))
    done = 0
    signals = []
    for point in points:
        y, u = _segment(data, point.plateau, factor)
        seg = slice(point.plateau.start, point.plateau.stop)
        point.offsets = (float(np.mean(data.dyno_speed_rad_s[seg])), float(np.mean(data.dyno_torque_nm[seg])))
        _check_excitation(u, f"{data.source}: operating point at {point.speed_rpm:.0f} rpm")
        point.window, point.held_out = split_plateau(u, n_fit, holdout, dt)
        if point.held_out is not None and holdout > 0:
            h0, h1 = point.held_out
            point.split_at = h1 + GUARD // 2 if h0 == 0 else h0 - GUARD // 2
            y, u = _segment(data, point.plateau, factor, point.split_at)
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
        lo, hi = _refine_span(y.size, p.window, n_refine, p.held_out if holdout > 0 else None)
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
    for p, row, (y, u) in zip(points, sorting.poles, signals):
        p.poles = row
        check_point(p, y, u)
    warnings += [line.text() for line in sorting.lines if not line.declared]

    driveline = None
    uncertainty = None
    if sorting.driveline is None:
        warnings.append("no invariant lightly damped pole pair was found at the operating points")
    else:
        mode = sorting.driveline
        fas, gains = [], []
        bands: dict[int, np.ndarray] = {}
        for k, p in enumerate(points):
            f = bands[k] = _response_band(p, mode.f0_hz, 0.5 / dt)
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
        given = [k for k in ("J1", "J2", "J_total") if getattr(inertias, k) is not None]
        uncertainty = from_points(points, driveline, bands, given)
    return IdentificationResult(points, orders, sorting, driveline, 1.0 / dt, warnings, uncertainty)


def validate_on(result: IdentificationResult, data: BenchData, settings: IdentificationSettings | None = None,
                max_speed_gap: float = 0.1) -> list[dict]:
    """MATLAB ``compare`` of the identified models on another recording, per operating point of it.

    Each steady operating point of ``data`` (found as :func:`identify` finds
    them) is compared with the model of the nearest identified engine speed,
    when that lies within ``max_speed_gap`` (relative); the whole plateau is
    used (no sample of it was fitted).
    """
    s = settings or IdentificationSettings()
    models = [p for p in result.points if p.fit is not None]
    if not models:
        return []
    dt_raw = float(np.median(np.diff(data.time_s)))
    factor = max(1, int(round(models[0].dt / dt_raw)))
    if abs(factor * dt_raw - models[0].dt) > 0.01 * models[0].dt:
        raise InputDataError(f"{data.source}: sampled every {1e3 * dt_raw:.3g} ms, which does not divide the models' "
                             f"{1e3 * models[0].dt:.3g} ms: validate on a recording at the identified one's rate")
    rows = []
    for plateau in find_operating_points(data, dataclasses.replace(s, operating_points=())):
        row = {"engine_speed_rpm": plateau.speed_rpm, "t_start_s": plateau.t_start_s, "t_end_s": plateau.t_end_s,
               "model_speed_rpm": None, "fit_simulation_pct": None, "fit_one_step_pct": None}
        best = min(models, key=lambda p: abs(p.speed_rpm - plateau.speed_rpm))
        if abs(best.speed_rpm - plateau.speed_rpm) > max_speed_gap * best.speed_rpm:
            row["note"] = (f"no model within {100 * max_speed_gap:.0f} % of this speed (nearest "
                           f"{best.speed_rpm:.0f} rpm)")
            rows.append(row)
            continue
        y, u = _segment(data, plateau, factor)
        try:
            c = compare_point(best, y, u, (0, y.size))
        except EstimationError as err:
            row["note"] = f"not compared: {err}"
            rows.append(row)
            continue
        row |= {"model_speed_rpm": best.speed_rpm, "fit_simulation_pct": c.fit_sim_pct,
                "fit_one_step_pct": c.fit_pred_pct}
        rows.append(row)
    return rows
