"""Batch ARMAX estimation by prediction-error minimisation (PEM).

Notes
-----
For the model of :mod:`online_id.estimation.model`, :math:`A y = B u + C e` (plus a
constant ``k`` when ``orders.offset``), the one-step prediction error is

.. math::

    \\varepsilon(t, \\theta) = \\frac{A(q) y(t) - B(q) u(t) - k}{C(q)}

computed with zero initial conditions.  PEM minimises
:math:`V(\\theta) = \\frac{1}{n} \\sum_{t \\ge t_0} \\varepsilon(t)^2` where the
first :math:`t_0` samples (at least ``orders.max_lag``) are left out of the
criterion because the regressor is incomplete there.  Its gradient follows by
filtering,

.. math::

    \\partial\\varepsilon / \\partial a_i = y(t-i) / C, \\quad
    \\partial\\varepsilon / \\partial b_j = -u(t-nk-j) / C, \\quad
    \\partial\\varepsilon / \\partial c_k = -\\varepsilon(t-k) / C,

and the minimisation is a trust-region Gauss-Newton: by default scipy's
``least_squares(method="trf")`` iteration, with each step's subproblem reduced
by a QR factorisation of the :math:`n \\times d` Jacobian instead of an SVD
(:mod:`online_id.estimation.trust_region`: the same steps, the factorisation at a fifth to a third of the cost); or, with ``solver="lm"``, a
Levenberg-Marquardt iteration on the normal equations, whose Jacobian is
formed and reduced to :math:`J^T J` and :math:`J^T \\varepsilon` block by
block (a few MB whatever :math:`n`), about ten times faster per step.  Its
step solves, in the variables scaled by the column norms :math:`D` of
:math:`J` (MINPACK's scaling, ``x_scale="jac"`` in scipy),

.. math::

    (D^{-1} J^T J D^{-1} + \\lambda I) D \\delta = -D^{-1} J^T \\varepsilon,

with :math:`\\lambda` adapted from the ratio :math:`\\rho` of actual to
predicted reduction (Nielsen's rule: :math:`\\lambda \\leftarrow \\lambda
\\max(1/3, 1 - (2\\rho - 1)^3)` on success, doubled growth on failure).
Both stop on the same relative tolerances (loss, step, and the cosine between
the residual and every Jacobian column) and reach the same minimum to within
them; their covariances are computed the same way.  The predictor is stable
only if :math:`C` is minimum phase, so trial points with a root of :math:`C`
on or outside the unit circle are rejected (the residual function returns
``inf`` and the trust region shrinks), and every start value and every result
has such roots reflected into the unit circle, :math:`z \\to 1/\\bar z`.  The
reflection leaves the noise spectrum :math:`|C|^2 \\sigma^2` unchanged up to a
scale of :math:`\\sigma^2`, so it changes no identifiable property of the
model (Ljung, *System Identification*, 1999, sec. 4.2).
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass

import numpy as np
from scipy.linalg import solve_triangular
from scipy.signal import lfilter, lfiltic

from online_id.estimation.model import ArmaxOrders
from online_id.estimation.trust_region import trust_region_lsq
from online_id.errors import EstimationError


@dataclass(frozen=True)
class ArmaxFit:
    """Result of a batch ARMAX fit.

    Attributes
    ----------
    orders
        Model orders (convention of :class:`ArmaxOrders`).
    theta
        Parameter vector ``[a, b, c, (offset)]``.
    A, B, C
        Polynomials in powers of :math:`q^{-1}` (``B`` with ``nk`` leading zeros).
    residuals
        One-step prediction errors on the samples in the criterion.
    V
        Loss, the mean squared residual.
    n
        Number of samples in the criterion (``len(residuals)``).
    d
        Number of estimated parameters.
    fpe
        Akaike's final prediction error :math:`V (1 + d/n) / (1 - d/n)`.
    aic
        Akaike's information criterion :math:`n \\ln V + 2 d` (MATLAB's ``aic``
        without the constant :math:`n (\\ln 2\\pi + 1)`, which does not change
        the ranking of models fitted to the same samples).
    converged
        Whether the optimiser met a tolerance (always true for linear LS).
    n_iter
        Jacobian evaluations (Gauss-Newton steps taken, plus one).
    message
        Optimiser status message.
    covariance
        Asymptotic covariance of ``theta``, :math:`V (J^T J)^{-1}` with the
        Jacobian :math:`J` of the residuals at the optimum.
    """

    orders: ArmaxOrders
    theta: np.ndarray
    A: np.ndarray
    B: np.ndarray
    C: np.ndarray
    residuals: np.ndarray
    V: float
    n: int
    d: int
    fpe: float
    aic: float
    converged: bool
    n_iter: int
    message: str
    covariance: np.ndarray

    @property
    def std_errors(self) -> np.ndarray:
        """Standard errors of ``theta`` (square roots of the covariance diagonal)."""
        return np.sqrt(np.maximum(np.diag(self.covariance), 0.0))


def fpe_criterion(V: float, n: int, d: int) -> float:
    """Akaike's final prediction error :math:`V (1 + d/n) / (1 - d/n)`."""
    if d >= n:
        return float("inf")
    return float(V * (1.0 + d / n) / (1.0 - d / n))


def reflect_unstable_roots(poly: np.ndarray, max_radius: float = 1.0) -> np.ndarray:
    """Monic polynomial with every root outside ``max_radius`` moved inside.

    Roots with :math:`|z| > 1` are reflected to :math:`1/\\bar z`; if
    ``max_radius < 1`` roots still beyond it are then pulled onto that radius.
    ``poly`` is in powers of :math:`q^{-1}` with leading coefficient 1.
    """
    poly = np.asarray(poly, dtype=float)
    if poly.size <= 1 or not np.all(np.isfinite(poly)):
        return poly.copy()
    roots = np.roots(poly)
    radius = np.abs(roots)
    if np.all(radius <= max_radius):
        return poly.copy()
    outside = radius > 1.0
    roots[outside] = 1.0 / np.conj(roots[outside])
    radius = np.abs(roots)
    beyond = radius > max_radius
    roots[beyond] *= max_radius / radius[beyond]
    return np.real(np.poly(roots))


def predict_errors(y: np.ndarray, u: np.ndarray, orders: ArmaxOrders,
                   theta: np.ndarray) -> np.ndarray:
    """One-step prediction errors :math:`(A y - B u - k)/C` of an ARMAX model.

    Filters run from zero initial conditions, so the first ``orders.max_lag``
    values are transient.  ``C`` is used as given: an unstable ``C`` gives
    growing errors (see :func:`reflect_unstable_roots`).
    """
    y, u = _as_signals(y, u)
    return _errors(y, u, orders, np.asarray(theta, dtype=float))


def simulate_model(u: np.ndarray, orders: ArmaxOrders, theta: np.ndarray,
                   y0: np.ndarray | None = None) -> np.ndarray:
    """Simulated (noise-free) output :math:`(B u + k)/A`.

    Parameters
    ----------
    u
        Input sequence.
    orders, theta
        The model.
    y0
        Optional measured outputs at the start (e.g. ``y[:orders.max_lag]``).
        The simulation returns them unchanged and continues from them, so the
        initial state matches the data; otherwise it starts from rest.

    Returns
    -------
    np.ndarray
        Simulated output, same length as ``u``.
    """
    u = np.asarray(u, dtype=float).ravel()
    A, B, _ = orders.split(theta)
    v = lfilter(B, [1.0], u)
    if orders.offset:
        v = v + float(theta[-1])
    if y0 is None or len(y0) == 0:
        return lfilter([1.0], A, v)
    y0 = np.asarray(y0, dtype=float).ravel()
    k = min(len(y0), len(u))
    out = np.empty_like(v)
    out[:k] = y0[:k]
    if orders.na == 0:
        out[k:] = v[k:]
        return out
    past = np.zeros(orders.na)
    m = min(k, orders.na)
    past[:m] = y0[:k][::-1][:m]
    zi = lfiltic([1.0], A, past)
    out[k:] = lfilter([1.0], A, v[k:], zi=zi)[0]
    return out


def fit_percent(y: np.ndarray, yhat: np.ndarray) -> float:
    """NRMSE fit in percent, :math:`100 (1 - \\|y-\\hat y\\| / \\|y-\\bar y\\|)` (MATLAB)."""
    y = np.asarray(y, dtype=float).ravel()
    yhat = np.asarray(yhat, dtype=float).ravel()
    if y.shape != yhat.shape:
        raise EstimationError(f"fit_percent: y has {y.size} samples but yhat has {yhat.size}")
    spread = np.linalg.norm(y - y.mean())
    if spread == 0.0:
        raise EstimationError("fit_percent: y is constant, the NRMSE fit is undefined")
    return float(100.0 * (1.0 - np.linalg.norm(y - yhat) / spread))


def fit_arx(y: np.ndarray, u: np.ndarray, orders: ArmaxOrders, *,
            n_skip: int | None = None) -> ArmaxFit:
    """ARX fit (``C = 1``) by linear least squares.

    Parameters
    ----------
    y, u
        Output and input, equal length.
    orders
        Model orders.  If ``orders.nc > 0`` the ``c`` entries of ``theta`` are
        returned as zeros (an ARMAX start value with ``C = 1``).
    n_skip
        Samples left out at the start of the criterion, default ``max_lag``.

    Returns
    -------
    ArmaxFit
        Loss and criteria computed with the ``na + nb (+1)`` ARX parameters.
    """
    y, u = _as_signals(y, u)
    arx = ArmaxOrders(orders.na, orders.nb, 0, orders.nk, orders.offset)
    t0 = _check(y, u, orders, n_skip)
    phi = _regressors(y, u, arx, t0)
    eta, *_ = np.linalg.lstsq(phi, y[t0:], rcond=None)
    theta = _insert_c(eta, orders, np.zeros(orders.nc))
    eps = y[t0:] - phi @ eta
    cov_arx = _covariance(phi, float(np.mean(eps**2)))
    cov = np.zeros((orders.n_params, orders.n_params))
    keep = _arx_index(orders)
    cov[np.ix_(keep, keep)] = cov_arx
    return _make_fit(orders, theta, eps, arx.n_params, True, 1,
                     "linear least squares", cov)


def fit_armax(y: np.ndarray, u: np.ndarray, orders: ArmaxOrders, *,
              theta0: np.ndarray | None = None, max_iter: int = 50, tol: float = 1e-6,
              n_skip: int | None = None, start_radius: float = 0.99,
              solver: str = "trf") -> ArmaxFit:
    """ARMAX fit by prediction-error minimisation (see module notes).

    Parameters
    ----------
    y, u
        Output and input, equal length.
    orders
        Model orders.
    theta0
        Start value (e.g. from the recursive estimator); default is the
        two-stage Hannan-Rissanen estimate (:func:`hannan_rissanen`).
    max_iter
        Maximum number of residual evaluations of the optimiser (one per
        Gauss-Newton step, one more per rejected step).
    tol
        Relative tolerance on the loss, the step and the gradient.
    n_skip
        Samples left out at the start of the criterion, default ``max_lag``.
    start_radius
        Roots of :math:`C` at the start value beyond this radius are pulled in
        (reflected, then scaled) before the search begins; a warm start from
        an earlier optimum may allow more than the default.
    solver
        ``"trf"`` (scipy's trust-region reflective, SVD per step) or
        ``"lm"`` (Levenberg-Marquardt on block-accumulated normal equations;
        faster and with memory independent of the Jacobian's size); see the
        module notes.  Both reach the same minimum within ``tol``.

    Returns
    -------
    ArmaxFit
        The fit; ``converged`` is false if ``max_iter`` was reached first.

    Raises
    ------
    EstimationError
        Too few samples, non-finite data, constant input, bad ``theta0``.
    """
    y, u = _as_signals(y, u)
    t0 = _check(y, u, orders, n_skip)
    if theta0 is not None:
        theta0 = np.array(theta0, dtype=float).ravel()
        if theta0.shape != (orders.n_params,) or not np.all(np.isfinite(theta0)):
            raise EstimationError(
                f"theta0 must be {orders.n_params} finite values for {orders}, "
                f"got shape {theta0.shape}")
    if solver not in ("trf", "lm"):
        raise EstimationError(f'solver must be "trf" or "lm", got {solver!r}')
    if orders.nc == 0:
        return fit_arx(y, u, orders, n_skip=t0)
    if theta0 is None:
        theta0 = hannan_rissanen(y, u, orders)
    theta0 = _stabilized(theta0, orders, max_radius=start_radius)
    problem = _PemProblem(y, u, orders, t0)
    if not np.all(np.isfinite(problem.residuals(theta0))):
        raise EstimationError("prediction errors at the start value are not finite")
    if solver == "lm":
        x, converged, n_iter, message = _levenberg_marquardt(problem, theta0, tol, max(int(max_iter), 1))
        theta = _stabilized(x, orders, max_radius=1.0)
        eps = problem.residuals(theta)
        H, _ = problem.normal_equations(theta)
        cov = float(np.mean(eps**2)) * np.linalg.pinv(H)
        return _make_fit(orders, theta, eps, orders.n_params, converged, n_iter, message, cov)
    result = trust_region_lsq(problem.residuals, problem.jacobian, theta0, ftol=tol, xtol=tol, gtol=tol,
                              max_nfev=max(int(max_iter), 1))
    theta = _stabilized(result.x, orders, max_radius=1.0)
    eps = problem.residuals(theta)
    cov = _covariance(problem.jacobian(theta), float(np.mean(eps**2)))
    n_iter = int(result.njev)
    return _make_fit(orders, theta, eps, orders.n_params, bool(result.status > 0),
                     n_iter, str(result.message), cov)


def hannan_rissanen(y: np.ndarray, u: np.ndarray, orders: ArmaxOrders,
                    long_order: int | None = None) -> np.ndarray:
    """Two-stage start value for ARMAX (Hannan and Rissanen, 1982).

    A long ARX model (order ``long_order``, default ``clip(4 max(na,nb,nc),
    20, 80)`` limited by the data length) estimates the innovations
    :math:`\\hat e`; then ``theta`` follows by least squares on the regressor
    with :math:`\\hat e(t-k)` in place of :math:`e(t-k)`.  Roots of ``C``
    are reflected into radius 0.99.
    """
    y, u = _as_signals(y, u)
    _check(y, u, orders, None)
    if orders.nc == 0:
        return fit_arx(y, u, orders).theta
    n = y.size
    if long_order is None:
        long_order = int(np.clip(4 * max(orders.na, orders.nb, orders.nc), 20, 80))
    long_order = int(max(1, min(long_order, (n - orders.nk) // 10)))
    nb_long = long_order if orders.nb > 0 else 0
    long = ArmaxOrders(long_order, nb_long, 0, orders.nk, orders.offset)
    t_long = long.max_lag
    phi = _regressors(y, u, long, t_long)
    eta, *_ = np.linalg.lstsq(phi, y[t_long:], rcond=None)
    e_hat = np.zeros(n)
    e_hat[t_long:] = y[t_long:] - phi @ eta
    t0 = min(t_long + orders.nc, n - orders.n_params - 1)
    t0 = max(t0, orders.max_lag)
    phi2 = _regressors(y, u, orders, t0, e=e_hat)
    theta, *_ = np.linalg.lstsq(phi2, y[t0:], rcond=None)
    return _stabilized(theta, orders, max_radius=0.99)


def select_order(y: np.ndarray, u: np.ndarray, candidates: Iterable[ArmaxOrders], *,
                 criterion: str = "fpe",
                 theta0s: Sequence[np.ndarray | None] | Mapping[ArmaxOrders, np.ndarray] | None = None,
                 progress: Callable[[int, int, ArmaxFit], None] | None = None,
                 **fit_kwargs) -> tuple[ArmaxFit, list[ArmaxFit]]:
    """Fit every candidate order and return the best by FPE or AIC.

    All candidates use the same criterion window (the largest ``max_lag``
    is skipped for every one), so their losses are comparable.

    Parameters
    ----------
    y, u
        Output and input.
    candidates
        Orders to try.
    criterion
        ``"fpe"`` or ``"aic"``.
    theta0s
        Start values, either aligned with ``candidates`` (``None`` entries use
        the default start) or a mapping from orders to start values.
    progress
        Called as ``progress(i, total, fit)`` after each fit.
    **fit_kwargs
        Passed to :func:`fit_armax` (``max_iter``, ``tol``).

    Returns
    -------
    tuple[ArmaxFit, list[ArmaxFit]]
        The best fit and all fits in the order of ``candidates``.
    """
    candidates = list(candidates)
    if criterion not in ("fpe", "aic"):
        raise EstimationError(f'criterion must be "fpe" or "aic", got {criterion!r}')
    if not candidates:
        raise EstimationError("select_order needs at least one candidate order")
    if theta0s is not None and not isinstance(theta0s, Mapping):
        theta0s = list(theta0s)
        if len(theta0s) != len(candidates):
            raise EstimationError(f"theta0s has {len(theta0s)} entries for "
                                  f"{len(candidates)} candidates")
    t0 = max(o.max_lag for o in candidates)
    fits: list[ArmaxFit] = []
    for i, orders in enumerate(candidates):
        if theta0s is None:
            start = None
        elif isinstance(theta0s, Mapping):
            start = theta0s.get(orders)
        else:
            start = theta0s[i]
        fit = fit_armax(y, u, orders, theta0=start, n_skip=t0, **fit_kwargs)
        fits.append(fit)
        if progress is not None:
            progress(i, len(candidates), fit)
    best = min(fits, key=lambda f: getattr(f, criterion))
    return best, fits


# -- internals ---------------------------------------------------------------

class _PemProblem:
    """Residuals and Jacobian of the PEM criterion, sharing one filter pass."""

    def __init__(self, y: np.ndarray, u: np.ndarray, orders: ArmaxOrders, t0: int):
        self.y, self.u, self.orders, self.t0 = y, u, orders, t0
        self._key: bytes | None = None
        self._eps = np.empty(0)

    def _full(self, theta: np.ndarray) -> np.ndarray:
        key = theta.tobytes()
        if key != self._key:
            self._eps = _errors(self.y, self.u, self.orders, theta)
            self._key = key
        return self._eps

    def residuals(self, theta: np.ndarray) -> np.ndarray:
        _, _, C = self.orders.split(theta)
        if C.size > 1 and np.max(np.abs(np.roots(C))) >= 1.0:
            return np.full(self.y.size - self.t0, np.inf)
        return self._full(theta)[self.t0:]

    def _filtered(self, theta: np.ndarray) -> tuple[list[tuple[np.ndarray, np.ndarray]], np.ndarray]:
        """Signals filtered by :math:`1/C` with their signs, each with its lags; and the errors."""
        o = self.orders
        _, _, C = o.split(theta)
        eps = self._full(theta)
        parts = [(lfilter([1.0], C, self.y), np.arange(1, o.na + 1)),
                 (lfilter([-1.0], C, self.u), o.nk + np.arange(o.nb)),
                 (lfilter([-1.0], C, eps), np.arange(1, o.nc + 1))]
        if o.offset:
            parts.append((lfilter([-1.0], C, np.ones_like(self.y)), np.zeros(1, dtype=int)))
        return parts, eps

    def jacobian(self, theta: np.ndarray) -> np.ndarray:
        """:math:`\\partial \\varepsilon / \\partial \\theta` on the criterion's samples, column-major (the
        trust-region step factorises it by columns)."""
        parts, _ = self._filtered(theta)
        t0, n = self.t0, self.y.size
        J = np.empty((n - t0, self.orders.n_params), order="F")
        k = 0
        for x, lags in parts:
            for lag in lags:
                J[:, k] = x[t0 - lag:n - lag]  # (t0 >= max_lag: every lag is inside the data)
                k += 1
        return J

    def normal_equations(self, theta: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """:math:`J^T J` and :math:`J^T \\varepsilon` without forming :math:`J`.

        Equal to ``J.T @ J`` and ``J.T @ eps`` of :meth:`jacobian` and
        :meth:`residuals` up to rounding.  The columns of :math:`J` are
        consecutive lags of a few filtered signals, so the Gram matrix of
        two of them needs dot products only for its first row and column; the
        rest follows along the diagonals by adding the sample that enters at
        the start and removing the one that leaves at the end,

        .. math::

            H_{i+1, j+1} = H_{i j} + x(t_0 - 1 - l_i) z(t_0 - 1 - m_j)
                           - x(n - 1 - l_i) z(n - 1 - m_j).
        """
        parts, eps = self._filtered(theta)
        t0, n = self.t0, self.y.size
        d = self.orders.n_params
        H = np.empty((d, d))
        g = np.empty(d)
        first = np.cumsum([0] + [lags.size for _, lags in parts])
        e = eps[t0:]
        for p, (x, lx) in enumerate(parts):
            for i, lag in enumerate(lx):
                g[first[p] + i] = x[t0 - lag:n - lag] @ e
            for q in range(p, len(parts)):
                z, lz = parts[q]
                if lx.size == 0 or lz.size == 0:
                    continue
                M = _lagged_gram(x, lx, z, lz, t0, n)
                H[first[p]:first[p + 1], first[q]:first[q + 1]] = M
                H[first[q]:first[q + 1], first[p]:first[p + 1]] = M.T
        return H, g


def _lagged_gram(x: np.ndarray, lx: np.ndarray, z: np.ndarray, lz: np.ndarray, t0: int, n: int) -> np.ndarray:
    """:math:`M_{ij} = \\sum_{t=t_0}^{n-1} x(t - l_i) z(t - m_j)` for consecutive lags ``lx``, ``lz``."""
    M = np.empty((lx.size, lz.size))
    a = int(lx[0])
    xa = x[t0 - a:n - a]
    for j, b in enumerate(lz):
        M[0, j] = xa @ z[t0 - b:n - b]
    b = int(lz[0])
    zb = z[t0 - b:n - b]
    for i in range(1, lx.size):
        a = int(lx[i])
        M[i, 0] = x[t0 - a:n - a] @ zb
    # one step down a diagonal: the sample at t0 - 1 enters, the one at n - 1 leaves
    enter = np.outer(x[t0 - 1 - lx[:-1]], z[t0 - 1 - lz[:-1]])
    leave = np.outer(x[n - 1 - lx[:-1]], z[n - 1 - lz[:-1]])
    step = enter - leave
    for i in range(lx.size - 1):
        M[i + 1, 1:] = M[i, :-1] + step[i, :]
    return M


def _fir(b: np.ndarray, x: np.ndarray) -> np.ndarray:
    """``lfilter(b, [1.0], x)`` of a 1-D ``x``: the convolution scipy's ``lfilter`` computes for a denominator of
    1 (``np.convolve(b, x)``, its first ``len(x)`` samples), without the ``apply_along_axis`` it wraps it in: the
    same floats, at a fifth of the call's cost on a window refit's 2,500 samples."""
    if b.size == 0:  # (lfilter's own error)
        return lfilter(b, [1.0], x)
    return np.convolve(b, x)[: x.size]


def _errors(y: np.ndarray, u: np.ndarray, orders: ArmaxOrders, theta: np.ndarray) -> np.ndarray:
    A, B, C = orders.split(theta)
    v = _fir(A, y) - _fir(B, u)
    if orders.offset:
        v = v - theta[-1]
    return lfilter([1.0], C, v)


def _levenberg_marquardt(problem: _PemProblem, theta: np.ndarray, tol: float,
                         max_nfev: int) -> tuple[np.ndarray, bool, int, str]:
    """Minimise ``problem.residuals`` from ``theta`` (see module notes).

    Returns the minimiser, whether a tolerance was met, the number of
    Jacobian evaluations and a status message.
    """
    theta = np.array(theta, dtype=float)
    eps = problem.residuals(theta)
    F = 0.5 * float(eps @ eps)  # F = ||eps||^2 / 2
    nfev = 1
    H, g = problem.normal_equations(theta)  # H = J^T J, g = J^T eps
    njev = 1
    D = np.sqrt(np.diag(H))
    D[D == 0.0] = 1.0
    lam, nu = 1e-3, 2.0
    eye = np.eye(theta.size)
    while True:
        Ds = np.outer(D, D)
        Hs = H / Ds  # scaled: D^-1 J^T J D^-1
        gs = g / D
        if np.max(np.abs(gs)) <= tol * np.sqrt(2.0 * F):  # cos(residual, every column) <= tol
            return theta, True, njev, "the gradient is below tol (cosine to every Jacobian column)"
        if nfev >= max_nfev:
            return theta, False, njev, "the maximum number of function evaluations is exceeded"
        try:
            L = np.linalg.cholesky(Hs + lam * eye)
            ds = -_cho_solve(L, gs)  # (Hs + lam I) ds = -gs
        except np.linalg.LinAlgError:
            lam *= nu
            nu *= 2.0
            continue
        step = ds / D
        trial = theta + step
        eps_new = problem.residuals(trial)
        nfev += 1
        F_new = 0.5 * float(eps_new @ eps_new) if np.all(np.isfinite(eps_new)) else np.inf
        predicted = -(gs @ ds + 0.5 * ds @ (Hs @ ds))  # L(0) - L(ds) of the linear model
        rho = (F - F_new) / predicted if predicted > 0 and np.isfinite(F_new) else -1.0
        small_step = np.linalg.norm(step) <= tol * (tol + np.linalg.norm(theta))
        if rho > 0:
            small_loss = (F - F_new) <= tol * F and rho > 0.25
            theta, eps, F = trial, eps_new, F_new
            H, g = problem.normal_equations(theta)
            njev += 1
            D = np.maximum(D, np.sqrt(np.diag(H)))
            lam *= max(1.0 / 3.0, 1.0 - (2.0 * rho - 1.0) ** 3)
            nu = 2.0
            if small_loss:
                return theta, True, njev, "the relative reduction of the loss is below tol"
            if small_step:
                return theta, True, njev, "the relative step is below tol"
        else:
            if small_step:
                return theta, True, njev, "the relative step is below tol"
            lam *= nu
            nu *= 2.0


def _cho_solve(L: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Solve :math:`L L^T x = b` for lower-triangular ``L``."""
    z = solve_triangular(L, b, lower=True)
    return solve_triangular(L.T, z, lower=False)


def _lag_matrix(x: np.ndarray, lags: np.ndarray, t0: int) -> np.ndarray:
    """Columns ``x(t - lag)`` for ``t = t0 .. len(x)-1`` (zero before the start)."""
    idx = np.arange(t0, x.size)[:, None] - np.asarray(lags, dtype=int)[None, :]
    out = x[np.maximum(idx, 0)]
    out[idx < 0] = 0.0
    return out


def _regressors(y: np.ndarray, u: np.ndarray, orders: ArmaxOrders, t0: int,
                e: np.ndarray | None = None) -> np.ndarray:
    """Rows :math:`\\varphi(t)^T`, ``t >= t0``, with ``e`` in the C part."""
    cols = [-_lag_matrix(y, np.arange(1, orders.na + 1), t0),
            _lag_matrix(u, orders.nk + np.arange(orders.nb), t0)]
    if e is not None:
        cols.append(_lag_matrix(e, np.arange(1, orders.nc + 1), t0))
    if orders.offset:
        cols.append(np.ones((y.size - t0, 1)))
    return np.hstack(cols)


def _arx_index(orders: ArmaxOrders) -> np.ndarray:
    """Positions in theta of the a, b and offset entries."""
    idx = list(range(orders.na + orders.nb))
    if orders.offset:
        idx.append(orders.n_params - 1)
    return np.array(idx, dtype=int)


def _insert_c(eta: np.ndarray, orders: ArmaxOrders, c: np.ndarray) -> np.ndarray:
    ab = eta[: orders.na + orders.nb]
    tail = eta[orders.na + orders.nb:]
    return np.concatenate((ab, c, tail))


def _stabilized(theta: np.ndarray, orders: ArmaxOrders, max_radius: float) -> np.ndarray:
    theta = np.array(theta, dtype=float)
    if orders.nc > 0:
        _, _, C = orders.split(theta)
        i = orders.na + orders.nb
        theta[i:i + orders.nc] = reflect_unstable_roots(C, max_radius)[1:]
    return theta


def _covariance(jac: np.ndarray, V: float) -> np.ndarray:
    return V * np.linalg.pinv(jac.T @ jac)


def _make_fit(orders: ArmaxOrders, theta: np.ndarray, eps: np.ndarray, d: int,
              converged: bool, n_iter: int, message: str, cov: np.ndarray) -> ArmaxFit:
    A, B, C = orders.split(theta)
    n = int(eps.size)
    V = float(np.mean(eps**2))
    aic = float(n * np.log(V) + 2 * d) if V > 0 else float("-inf")
    return ArmaxFit(orders=orders, theta=theta, A=A, B=B, C=C, residuals=eps, V=V, n=n,
                    d=int(d), fpe=fpe_criterion(V, n, d), aic=aic, converged=converged,
                    n_iter=n_iter, message=message, covariance=cov)


def _as_signals(y: np.ndarray, u: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    y = np.asarray(y, dtype=float)
    u = np.asarray(u, dtype=float)
    if y.ndim != 1 or u.ndim != 1:
        raise EstimationError(f"y and u must be 1-D, got shapes {y.shape} and {u.shape}")
    if y.size != u.size:
        raise EstimationError(f"y has {y.size} samples but u has {u.size}")
    return y, u


def _check(y: np.ndarray, u: np.ndarray, orders: ArmaxOrders, n_skip: int | None) -> int:
    """Validate the data for ``orders``; return the first sample in the criterion."""
    t0 = orders.max_lag if n_skip is None else int(n_skip)
    if t0 < orders.max_lag:
        raise EstimationError(f"n_skip={t0} is below max_lag={orders.max_lag} of {orders}")
    d = orders.n_params
    if y.size <= 2 * d + t0:
        raise EstimationError(
            f"too few samples: {y.size} for {d} parameters and {t0} skipped start samples "
            f"(need more than 2*{d} + {t0} = {2 * d + t0}) with {orders}")
    for name, x in (("y", y), ("u", u)):
        bad = np.flatnonzero(~np.isfinite(x))
        if bad.size:
            raise EstimationError(f"{name} has {bad.size} non-finite values "
                                  f"(first at index {bad[0]}: {x[bad[0]]})")
    if orders.nb > 0 and np.ptp(u) <= 1e-12 * max(1.0, float(np.max(np.abs(u)))):
        raise EstimationError(f"input u is constant ({u[0]:g}): no excitation, "
                              "the B parameters cannot be estimated")
    return t0
