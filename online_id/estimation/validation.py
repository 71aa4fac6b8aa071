"""Model validation against the data: measured frequency response and MATLAB ``compare``-style fits.

Numerical only (numpy, scipy); the plots are in :mod:`online_id.report`.

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
from online_id.estimation.pem import (
    ArmaxFit,
    fit_percent,
    predict_errors,
    reflect_unstable_roots,
    simulate_model,
)


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
            cancel: Sequence[complex] = (), initial: str = "measured") -> Comparison:
    """MATLAB ``compare``: the model's simulated and one-step predicted output against ``y``.

    The simulation uses the model without the pole-zero pairs of ``cancel``
    (see :func:`cancel_pairs`) and with unstable poles reflected
    (:func:`stable_theta`); it starts from the first measured outputs
    (``y[:max_lag]``, ``initial="measured"``) or from the initial state that
    fits ``y`` best in least squares (``initial="estimate"``, MATLAB's
    default ``'e'``: the model's free responses, one per state, are fitted to
    what the input does not explain).  The first ``skip`` samples (default:
    the model's largest lag) are left out of both fits.
    """
    y = np.asarray(y, dtype=float).ravel()
    u = np.asarray(u, dtype=float).ravel()
    k = fit.orders.max_lag if skip is None else int(skip)
    if y.size - k < 2 * fit.d:
        raise EstimationError(f"compare: {y.size} samples are too few for a model with {fit.d} parameters")
    if initial not in ("measured", "estimate"):
        raise EstimationError(f'compare: initial must be "measured" or "estimate", got {initial!r}')
    theta, n_cancelled = cancel_pairs(fit, cancel)
    theta, n_reflected = stable_theta(theta, fit.orders)
    if initial == "estimate":
        y_sim = _simulate_estimated_start(u, y, fit.orders, theta)
    else:
        y_sim = simulate_model(u, fit.orders, theta, y0=y[:fit.orders.max_lag])
    y_pred = y - predict_errors(y, u, fit.orders, fit.theta)
    return Comparison(y, y_sim, y_pred, fit_percent(y[k:], y_sim[k:]), fit_percent(y[k:], y_pred[k:]), k,
                      n_reflected, n_cancelled)


def _simulate_estimated_start(u: np.ndarray, y: np.ndarray, orders: ArmaxOrders, theta: np.ndarray) -> np.ndarray:
    """``B/A u`` from rest plus the free response of the initial state that fits ``y`` best (least squares)."""
    from scipy.signal import lfilter

    A, B, _ = orders.split(theta)
    forced = simulate_model(u, orders, theta)
    n_state = max(A.size, B.size) - 1
    if n_state == 0:
        return forced
    a = np.pad(A, (0, n_state + 1 - A.size))
    free = np.empty((y.size, n_state))
    for i in range(n_state):
        zi = np.zeros(n_state)
        zi[i] = 1.0
        free[:, i] = lfilter([1.0], a, np.zeros(y.size), zi=zi)[0]
    scale = np.maximum(np.linalg.norm(free, axis=0), 1e-300)
    x0, *_ = np.linalg.lstsq(free / scale, y - forced, rcond=1e-10)
    return forced + (free / scale) @ x0


Z99 = 2.576  # two-sided 99 % point of the normal distribution
RESID_LAGS = 25  # MATLAB resid's default number of lags


@dataclass(frozen=True)
class ResidualCorrelation:
    """MATLAB ``resid``: the residual's autocorrelation and its cross-correlation with the input, with bounds.

    ``auto[k]`` is the normalised autocorrelation of the residual at lag
    ``lags[k]`` (0..M, ``auto[0] = 1``); ``cross[k]`` is
    :math:`\\mathrm{corr}(e(t), u(t - \\tau))` at ``cross_lags[k] = tau``
    (-M..M: positive lags, the residual follows the input).  A correlation
    outside its ``+-bound`` (99 % by default) rejects whiteness, or
    independence from the input, at that lag.
    """

    lags: np.ndarray
    auto: np.ndarray
    auto_bound: float
    cross_lags: np.ndarray
    cross: np.ndarray
    cross_bound: float
    n: int
    confidence: float

    @property
    def auto_outside(self) -> int:
        """Lags 1..M whose autocorrelation leaves the band."""
        return int(np.count_nonzero(np.abs(self.auto[1:]) > self.auto_bound))

    @property
    def cross_outside(self) -> int:
        """Lags -M..M whose cross-correlation leaves the band."""
        return int(np.count_nonzero(np.abs(self.cross) > self.cross_bound))

    def as_dict(self) -> dict:
        return {"n_samples": self.n, "confidence": self.confidence, "lags": self.lags.tolist(),
                "autocorrelation": self.auto.tolist(), "autocorrelation_bound": self.auto_bound,
                "autocorrelation_outside": self.auto_outside, "cross_lags": self.cross_lags.tolist(),
                "cross_correlation": self.cross.tolist(), "cross_correlation_bound": self.cross_bound,
                "cross_correlation_outside": self.cross_outside}


def _correlation(a: np.ndarray, b: np.ndarray, lags: np.ndarray) -> np.ndarray:
    """:math:`\\sum_t a(t) b(t - \\tau) / (N \\sigma_a \\sigma_b)` of the mean-free ``a``, ``b`` per lag."""
    a = a - a.mean()
    b = b - b.mean()
    scale = a.size * np.sqrt(np.mean(a * a) * np.mean(b * b))
    if scale == 0.0:
        return np.zeros(lags.size)
    return np.array([(a[k:] @ b[:b.size - k] if k >= 0 else a[:k] @ b[-k:]) for k in lags]) / scale


def residual_correlation(e: np.ndarray, u: np.ndarray, max_lag: int = RESID_LAGS,
                         confidence: float = 0.99) -> ResidualCorrelation:
    """Autocorrelation of ``e`` (lags 0..max_lag) and its cross-correlation with ``u`` (-max_lag..max_lag).

    Notes
    -----
    Bounds as MATLAB's ``resid`` draws them: for a white residual of
    :math:`N` samples the autocorrelation at a lag :math:`\\ne 0` has the
    standard deviation :math:`1/\\sqrt N`; the cross-correlation of a
    residual independent of the input has (Bartlett)
    :math:`\\sigma^2 = \\frac 1N \\sum_{|k| \\le M} \\rho_{ee}(k)\\,\\rho_{uu}(k)`,
    which is :math:`1/N` for a white residual whatever the input's
    spectrum.  The band is :math:`\\pm z\\sigma` with the two-sided normal
    quantile :math:`z` (2.576 for 99 %).
    """
    from scipy.stats import norm

    e = np.asarray(e, dtype=float).ravel()
    u = np.asarray(u, dtype=float).ravel()
    if e.size != u.size:
        raise EstimationError(f"residual_correlation: e has {e.size} samples but u has {u.size}")
    max_lag = int(max_lag)
    if e.size < 4 * max_lag:
        raise EstimationError(f"residual_correlation: {e.size} samples are too few for {max_lag} lags")
    z = float(norm.ppf(0.5 + confidence / 2.0))
    lags = np.arange(0, max_lag + 1)
    both = np.arange(-max_lag, max_lag + 1)
    auto = _correlation(e, e, lags)
    cross = _correlation(e, u, both)
    r_ee = _correlation(e, e, both)
    r_uu = _correlation(u, u, both)
    var_cross = max(float(r_ee @ r_uu), 0.0) / e.size
    return ResidualCorrelation(lags, auto, z / np.sqrt(e.size), both, cross, z * np.sqrt(var_cross), int(e.size),
                               float(confidence))
