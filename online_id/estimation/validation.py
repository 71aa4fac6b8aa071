"""Model validation against the data: measured frequency response and MATLAB ``compare``-style fits.

Numerical only (numpy, scipy); the plots are in :mod:`online_id.plots`.

Notes
-----
**Measured frequency response (H1).**  With Welch averages of the input
auto-spectrum :math:`S_{uu}` and the cross-spectrum :math:`S_{uy}`,
:math:`\\hat H_1(f) = S_{uy}(f) / S_{uu}(f)` and the magnitude-squared
coherence :math:`\\gamma^2 = |S_{uy}|^2 / (S_{uu} S_{yy})`
(``scipy.signal.csd``, ``welch``, ``coherence``).  H1 is unbiased for noise
on the output only; where :math:`\\gamma^2` is low (little excitation, or
noise fed back through the dyno's speed controller), it is not to be read.

**Fit percent** (MATLAB ``compare``): :math:`100 (1 - \\|y - \\hat y\\| /
\\|y - \\bar y\\|)`, for the simulated output :math:`\\hat y = B/A\\,u`
(infinite horizon) and for the one-step prediction
:math:`\\hat y = y - \\varepsilon` (horizon 1).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from scipy.signal import coherence, csd, welch

from online_id.analysis.physical import frequency_response
from online_id.errors import EstimationError
from online_id.estimation.model import ArmaxOrders
from online_id.estimation.identification import PointResult, _segment
from online_id.estimation.pem import (
    ArmaxFit,
    fit_percent,
    predict_errors,
    reflect_unstable_roots,
    simulate_model,
)
from online_id.records import BenchData


@dataclass(frozen=True)
class MeasuredResponse:
    """H1 estimate of the frequency response from ``u`` to ``y`` and its coherence, per frequency [Hz]."""

    f_hz: np.ndarray
    h: np.ndarray  # complex, units of y per unit of u
    coherence: np.ndarray  # [0, 1]
    segment_s: float
    n_segments: int


def measured_response(u: np.ndarray, y: np.ndarray, fs_hz: float, segment_s: float = 2.0) -> MeasuredResponse:
    """H1 frequency response estimate from ``u`` to ``y`` (Welch, Hann window, 50 % overlap).

    ``segment_s`` sets the resolution (``1/segment_s`` Hz); it is shortened
    to a quarter of the record when the record is short, so that at least
    about seven segments are averaged.
    """
    u = np.asarray(u, dtype=float).ravel()
    y = np.asarray(y, dtype=float).ravel()
    if u.size != y.size:
        raise EstimationError(f"measured_response: u has {u.size} samples but y has {y.size}")
    nper = int(min(round(segment_s * fs_hz), u.size // 4))
    if nper < 16:
        raise EstimationError(f"measured_response: {u.size} samples are too few for a spectral estimate")
    f, suy = csd(u, y, fs=fs_hz, nperseg=nper)
    _, suu = welch(u, fs=fs_hz, nperseg=nper)
    _, coh = coherence(u, y, fs=fs_hz, nperseg=nper)
    with np.errstate(divide="ignore", invalid="ignore"):
        h = np.where(suu > 0, suy / suu, np.nan)
    n_seg = 1 + (u.size - nper) // (nper // 2)
    return MeasuredResponse(f, h, coh, nper / fs_hz, n_seg)


def model_response(fit: ArmaxFit, f_hz: np.ndarray, dt: float) -> np.ndarray:
    """Frequency response ``B/A`` of the fitted model at ``f_hz``."""
    return frequency_response(fit.B, fit.A, f_hz, dt)


@dataclass(frozen=True)
class Comparison:
    """Measured, simulated and one-step predicted output of a model on one record, with the fits [%]."""

    y: np.ndarray
    y_sim: np.ndarray
    y_pred: np.ndarray
    fit_sim_pct: float
    fit_pred_pct: float
    skip: int  # samples at the start left out of the fits (the filters start from rest)
    n_reflected: int  # unstable poles of A reflected into the unit circle for the simulation
    n_cancelled: int  # disturbance pole-zero pairs removed for the simulation (see cancel_pairs)


def cancel_pairs(fit: ArmaxFit, poles: Sequence[complex], tol: float = 0.02) -> tuple[np.ndarray, int]:
    """The model's parameters with each pole of ``poles`` removed together with the zero of ``B`` next to it.

    A periodic disturbance (the compression pulses on an engine-order line)
    shows in an ARMAX fit as a pole of ``A`` that a zero of ``B`` nearly
    cancels: the torque does not drive it.  Simulated from the torque, the
    imperfect cancellation rings at the order frequency; removing the pair
    (when a zero lies within ``tol`` of the pole in the z-plane) leaves the
    torque-driven dynamics.  Returns ``(theta, pairs removed)`` (conjugates
    count once).
    """
    o = fit.orders
    theta = np.array(fit.theta, dtype=float)
    a_roots = list(np.roots(fit.A)) if fit.A.size > 1 else []
    b = np.trim_zeros(fit.B, "f")
    b_roots = list(np.roots(b)) if b.size > 1 else []
    removed = 0
    for p in poles:
        zi = int(np.argmin(np.abs(np.array(b_roots) - p))) if b_roots else -1
        if zi < 0 or abs(b_roots[zi] - p) > tol:
            continue
        for target in ({p, np.conj(p)} if abs(p.imag) > 1e-12 else {p}):
            a_roots.pop(int(np.argmin(np.abs(np.array(a_roots) - target))))
            b_roots.pop(int(np.argmin(np.abs(np.array(b_roots) - target))))
        removed += 1
    if removed:
        a_new = np.real(np.poly(a_roots)) if a_roots else np.ones(1)
        b_new = b[0] * np.real(np.poly(b_roots)) if b_roots else b[:1]
        theta[:o.na] = np.pad(a_new[1:], (0, o.na - a_new.size + 1))
        theta[o.na:o.na + o.nb] = np.pad(b_new, (0, o.nb - b_new.size))
    return theta, removed


def stable_theta(theta: np.ndarray, orders: ArmaxOrders) -> tuple[np.ndarray, int]:
    """The model's parameters with every unstable pole reflected, ``(theta, how many)``.

    A pole :math:`p` with :math:`|p| > 1` becomes :math:`1/\\bar p`, and
    ``B`` is divided by :math:`|p|`, which keeps the magnitude of the
    frequency response (:math:`|e^{j\\omega} - p| = |p|\\,|e^{j\\omega} -
    1/\\bar p|`) and changes only its phase.  An unstable ``B/A`` cannot be
    simulated; this is the stable model with the same magnitude response.
    """
    theta = np.array(theta, dtype=float)
    A = orders.split(theta)[0]
    roots = np.roots(A) if A.size > 1 else np.empty(0)
    unstable = np.abs(roots) > 1.0
    if not unstable.any():
        return theta, 0
    na, nb = orders.na, orders.nb
    theta[:na] = reflect_unstable_roots(A)[1:]
    theta[na:na + nb] /= float(np.prod(np.abs(roots[unstable])))
    return theta, int(np.count_nonzero(unstable))


def compare(fit: ArmaxFit, y: np.ndarray, u: np.ndarray, skip: int | None = None,
            cancel: Sequence[complex] = ()) -> Comparison:
    """MATLAB ``compare``: the model's simulated and one-step predicted output against ``y``.

    The simulation starts from the first measured outputs (``y[:max_lag]``)
    and uses the model without the pole-zero pairs of ``cancel`` (see
    :func:`cancel_pairs`) and with unstable poles reflected (:func:`stable_theta`);
    the first ``skip`` samples (default: the model's largest lag) are left
    out of both fits.
    """
    y = np.asarray(y, dtype=float).ravel()
    u = np.asarray(u, dtype=float).ravel()
    k = fit.orders.max_lag if skip is None else int(skip)
    if y.size - k < 2 * fit.d:
        raise EstimationError(f"compare: {y.size} samples are too few for a model with {fit.d} parameters")
    theta, n_cancelled = cancel_pairs(fit, cancel)
    theta, n_reflected = stable_theta(theta, fit.orders)
    y_sim = simulate_model(u, fit.orders, theta, y0=y[:fit.orders.max_lag])
    y_pred = y - predict_errors(y, u, fit.orders, fit.theta)
    return Comparison(y, y_sim, y_pred, fit_percent(y[k:], y_sim[k:]), fit_percent(y[k:], y_pred[k:]), k,
                      n_reflected, n_cancelled)


def plateau_signals(data: BenchData, point: PointResult) -> tuple[np.ndarray, np.ndarray]:
    """The decimated, mean-free (dyno speed [rad/s], dyno torque [Nm]) of one operating point, as identified."""
    dt_raw = float(np.median(np.diff(data.time_s)))
    return _segment(data, point.plateau, max(1, int(round(point.dt / dt_raw))))


def held_out_span(point: PointResult, size: int) -> tuple[int, int, bool]:
    """``(start, stop, held_out)``: the longest stretch of the plateau outside the fit window.

    Falls back to the fit window itself (``held_out`` False) when the
    plateau holds less than a second besides it.
    """
    a, b = point.window
    before, after = (0, a), (b, size)
    best = max(before, after, key=lambda s: s[1] - s[0])
    if (best[1] - best[0]) * point.dt >= 1.0:
        return best[0], best[1], True
    return a, b, False
