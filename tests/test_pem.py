"""Tests of the batch ARMAX estimator (online_id.estimation.pem)."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.signal import lfilter

from online_id.estimation.model import ArmaxOrders
from online_id.estimation.pem import (
    ArmaxFit,
    fit_armax,
    fit_arx,
    fit_percent,
    fpe_criterion,
    hannan_rissanen,
    predict_errors,
    reflect_unstable_roots,
    select_order,
    simulate_model,
)
from online_id.errors import EstimationError


def stable_poly(rng: np.random.Generator, order: int, r_max: float) -> np.ndarray:
    """Random monic polynomial in q^-1 with all roots inside radius r_max."""
    roots: list[complex] = []
    while len(roots) < order:
        if order - len(roots) >= 2 and rng.random() < 0.5:
            z = rng.uniform(0.3, r_max) * np.exp(1j * rng.uniform(0.3, 2.8))
            roots += [z, np.conj(z)]
        else:
            roots.append(rng.uniform(-r_max, r_max))
    return np.atleast_1d(np.real(np.poly(roots)))


def simulate(seed: int, orders: ArmaxOrders, n: int = 5000, sigma: float = 0.3,
             offset: float = 0.0):
    """Random stable ARMAX truth and data from zero initial conditions."""
    rng = np.random.default_rng(seed)
    A = stable_poly(rng, orders.na, 0.85)
    C = stable_poly(rng, orders.nc, 0.7)
    b = rng.normal(size=orders.nb)
    theta = np.concatenate((A[1:], b, C[1:], [offset] if orders.offset else []))
    A, B, C = orders.split(theta)
    u = rng.normal(size=n)
    e = sigma * rng.normal(size=n)
    y = lfilter(B, A, u) + lfilter(C, A, e)
    if orders.offset:
        y = y + lfilter([offset], A, np.ones(n))
    return y, u, e, theta


CASES = [  # (na, nb, nc, nk, seed)
    (1, 1, 1, 1, 0),
    (2, 2, 1, 1, 1),
    (2, 3, 2, 2, 2),
    (3, 2, 3, 1, 3),
    (4, 4, 2, 1, 4),
    (2, 4, 4, 0, 5),
    (4, 3, 4, 1, 6),
]


@pytest.mark.parametrize("na, nb, nc, nk, seed", CASES)
def test_fit_armax_recovers_parameters(na, nb, nc, nk, seed):
    orders = ArmaxOrders(na, nb, nc, nk)
    y, u, _, theta = simulate(seed, orders)
    fit = fit_armax(y, u, orders)
    assert fit.converged, fit.message
    err = np.abs(fit.theta - theta)
    assert np.all((err < 5 * fit.std_errors) | (err < 0.05)), (err, fit.std_errors)
    assert np.all(np.abs(np.roots(fit.C)) < 1.0)
    assert fit.V == pytest.approx(0.09, rel=0.1)
    assert fit.n == y.size - orders.max_lag and fit.d == orders.n_params


def test_fit_armax_with_offset():
    orders = ArmaxOrders(2, 2, 1, offset=True)
    y, u, _, theta = simulate(7, orders, offset=2.5)
    fit = fit_armax(y, u, orders)
    err = np.abs(fit.theta - theta)
    assert np.all(err < 5 * fit.std_errors), (err, fit.std_errors)


def test_fit_arx_equals_lstsq():
    orders = ArmaxOrders(3, 2, 0, nk=2)
    y, u, _, _ = simulate(11, orders)
    fit = fit_arx(y, u, orders)
    t = np.arange(orders.max_lag, y.size)
    phi = np.column_stack([-y[t - 1], -y[t - 2], -y[t - 3], u[t - 2], u[t - 3]])
    expected, *_ = np.linalg.lstsq(phi, y[t], rcond=None)
    np.testing.assert_allclose(fit.theta, expected, rtol=0, atol=1e-10)
    np.testing.assert_allclose(fit.residuals, y[t] - phi @ expected, atol=1e-10)
    # the ARMAX entry point with nc = 0 is the same linear problem
    np.testing.assert_allclose(fit_armax(y, u, orders).theta, expected, atol=1e-10)


def test_predict_errors_on_truth_return_noise():
    orders = ArmaxOrders(3, 2, 2, nk=1)
    y, u, e, theta = simulate(12, orders)
    eps = predict_errors(y, u, orders, theta)
    np.testing.assert_allclose(eps[orders.max_lag:], e[orders.max_lag:], rtol=0, atol=1e-10)


def test_jacobian_matches_finite_differences():
    from online_id.estimation.pem import _PemProblem

    orders = ArmaxOrders(2, 2, 2, nk=1, offset=True)
    y, u, _, theta = simulate(13, orders, n=400, offset=0.3)
    problem = _PemProblem(y, u, orders, orders.max_lag)
    jac = problem.jacobian(theta)
    h = 1e-6
    for i in range(theta.size):
        step = np.zeros_like(theta)
        step[i] = h
        fd = (problem.residuals(theta + step) - problem.residuals(theta - step)) / (2 * h)
        np.testing.assert_allclose(jac[:, i], fd, atol=1e-6)


def test_select_order_picks_true_order():
    true = ArmaxOrders(2, 2, 1)
    y, u, _, _ = simulate(21, true, n=4000)
    candidates = [ArmaxOrders(n, n, m) for n in (1, 2, 3) for m in (1, 2)]
    calls = []
    best, fits = select_order(y, u, candidates, progress=lambda i, k, f: calls.append(i))
    assert len(fits) == len(candidates) and calls == list(range(len(candidates)))
    true_fit = fits[candidates.index(ArmaxOrders(2, 2, 1))]
    assert best.orders == true or (
        best.orders.na >= 2 and best.orders.nb >= 2 and best.fpe >= 0.99 * true_fit.fpe)
    assert len({f.n for f in fits}) == 1  # one common criterion window


def test_select_order_aic_and_theta0s():
    y, u, _, _ = simulate(22, ArmaxOrders(1, 1, 1), n=2000)
    cands = [ArmaxOrders(1, 1, 1), ArmaxOrders(2, 2, 2)]
    best, fits = select_order(y, u, cands, criterion="aic", theta0s=[None, None])
    assert best.aic == min(f.aic for f in fits)
    with pytest.raises(EstimationError, match="criterion"):
        select_order(y, u, cands, criterion="bic")


def test_fpe_and_aic_formulas():
    y, u, _, _ = simulate(23, ArmaxOrders(2, 2, 1), n=1000)
    fit = fit_armax(y, u, ArmaxOrders(2, 2, 1))
    n, d, V = fit.n, fit.d, fit.V
    assert V == pytest.approx(np.mean(fit.residuals**2))
    assert fit.fpe == pytest.approx(V * (1 + d / n) / (1 - d / n), rel=1e-14)
    assert fit.aic == pytest.approx(n * np.log(V) + 2 * d, rel=1e-14)
    assert fpe_criterion(2.0, 100, 10) == pytest.approx(2.0 * 1.1 / 0.9)


def test_fit_percent_and_simulation():
    orders = ArmaxOrders(2, 2, 1)
    y, u, _, theta = simulate(24, orders, sigma=0.0)
    assert fit_percent(y, y) == 100.0
    assert fit_percent(y, np.full_like(y, y.mean())) == pytest.approx(0.0)
    assert fit_percent(y, simulate_model(u, orders, theta)) == pytest.approx(100.0)
    # continuing from measured initial outputs reproduces the data exactly
    np.testing.assert_allclose(simulate_model(u, orders, theta, y0=y[:5]), y, atol=1e-9)


def test_theta0_near_truth_reaches_same_optimum():
    orders = ArmaxOrders(3, 2, 2)
    y, u, _, theta = simulate(31, orders)
    ref = fit_armax(y, u, orders, tol=1e-12)
    rng = np.random.default_rng(0)
    start = theta + 0.02 * rng.normal(size=theta.size)
    fit = fit_armax(y, u, orders, theta0=start, tol=1e-12)
    assert fit.V == pytest.approx(ref.V, rel=1e-9)
    np.testing.assert_allclose(fit.theta, ref.theta, atol=1e-3 * ref.std_errors.min() + 1e-6)


def test_unstable_start_and_reflection():
    C = np.real(np.poly([1.25, 0.5]))
    D = reflect_unstable_roots(C)
    np.testing.assert_allclose(np.sort(np.abs(np.roots(D))), [0.5, 0.8])
    orders = ArmaxOrders(2, 2, 2)
    y, u, _, theta = simulate(32, orders)
    bad = theta.copy()
    bad[4:] = C[1:]  # C with a root at 1.25
    fit = fit_armax(y, u, orders, theta0=bad)
    assert np.all(np.abs(np.roots(fit.C)) < 1.0)
    assert fit.V == pytest.approx(0.09, rel=0.1)


def test_hannan_rissanen_start_is_close():
    orders = ArmaxOrders(2, 2, 2)
    y, u, _, theta = simulate(33, orders)
    assert np.max(np.abs(hannan_rissanen(y, u, orders) - theta)) < 0.1


def test_fit_is_frozen_dataclass():
    y, u, _, _ = simulate(34, ArmaxOrders(1, 1, 1), n=500)
    fit = fit_armax(y, u, ArmaxOrders(1, 1, 1))
    assert isinstance(fit, ArmaxFit)
    with pytest.raises(AttributeError):
        fit.V = 0.0  # type: ignore[misc]


def test_errors_too_few_samples():
    orders = ArmaxOrders(4, 4, 4)
    rng = np.random.default_rng(0)
    y, u = rng.normal(size=20), rng.normal(size=20)
    with pytest.raises(EstimationError, match="too few samples: 20 for 12 parameters"):
        fit_armax(y, u, orders)


def test_errors_non_finite():
    y, u, _, _ = simulate(40, ArmaxOrders(1, 1, 1), n=300)
    y[17] = np.nan
    with pytest.raises(EstimationError, match="y has 1 non-finite values .*index 17"):
        fit_armax(y, u, ArmaxOrders(1, 1, 1))
    with pytest.raises(EstimationError, match="u has"):
        fit_arx(np.ones(300), np.r_[np.inf, np.ones(299)], ArmaxOrders(1, 1, 0))


def test_errors_constant_input():
    y = np.random.default_rng(1).normal(size=300)
    with pytest.raises(EstimationError, match="input u is constant"):
        fit_armax(y, np.full(300, 3.0), ArmaxOrders(1, 1, 1))


def test_errors_shape_and_theta0():
    y = np.random.default_rng(2).normal(size=300)
    u = np.random.default_rng(3).normal(size=300)
    with pytest.raises(EstimationError, match="299"):
        fit_armax(y, u[:299], ArmaxOrders(1, 1, 1))
    with pytest.raises(EstimationError, match="theta0"):
        fit_armax(y, u, ArmaxOrders(1, 1, 1), theta0=np.zeros(2))


# -- the Levenberg-Marquardt solver (solver="lm") ------------------------------------------

@pytest.mark.parametrize("orders", [ArmaxOrders(12, 12, 12, 1), ArmaxOrders(8, 6, 4, 2, offset=True),
                                    ArmaxOrders(3, 1, 2, 0, offset=True), ArmaxOrders(2, 0, 1, 1)],
                         ids=str)
def test_normal_equations_equal_the_jacobian_products(orders):
    from online_id.estimation.pem import _PemProblem

    y, u, _, theta = simulate(31, orders if orders.nb else ArmaxOrders(2, 1, 1, 1), n=3000)
    t0 = orders.max_lag + 5
    problem = _PemProblem(y, u, orders, t0)
    theta = np.zeros(orders.n_params)
    theta[: orders.na] = 0.02
    theta[orders.na + orders.nb] = -0.5  # C = 1 - 0.5 q^-1: a stable predictor
    H, g = problem.normal_equations(theta)
    J, eps = problem.jacobian(theta), problem.residuals(theta)
    assert np.max(np.abs(H - J.T @ J)) <= 1e-12 * np.max(np.abs(H))
    assert np.max(np.abs(g - J.T @ eps)) <= 1e-12 * np.max(np.abs(g))


@pytest.mark.parametrize("na, nb, nc, nk, seed", CASES)
def test_lm_solver_reaches_the_trf_optimum(na, nb, nc, nk, seed):
    orders = ArmaxOrders(na, nb, nc, nk)
    y, u, _, theta = simulate(seed, orders)
    trf = fit_armax(y, u, orders)
    lm = fit_armax(y, u, orders, solver="lm")
    assert lm.converged, lm.message
    assert lm.V == pytest.approx(trf.V, rel=1e-5)
    assert np.all(np.abs(lm.theta - trf.theta) < 0.05 * trf.std_errors + 1e-6)
    np.testing.assert_allclose(lm.covariance, trf.covariance, rtol=1e-2, atol=1e-3 * np.max(trf.covariance))
    assert np.all(np.abs(np.roots(lm.C)) < 1.0)


def test_lm_solver_with_offset_and_bad_name():
    orders = ArmaxOrders(2, 2, 1, offset=True)
    y, u, _, theta = simulate(7, orders, offset=2.5)
    fit = fit_armax(y, u, orders, solver="lm")
    assert np.all(np.abs(fit.theta - theta) < 5 * fit.std_errors)
    with pytest.raises(EstimationError, match="solver"):
        fit_armax(y, u, orders, solver="svd")


def test_lm_solver_stops_at_max_iter():
    orders = ArmaxOrders(3, 2, 3, 1)
    y, u, _, _ = simulate(3, orders)
    fit = fit_armax(y, u, orders, solver="lm", max_iter=2)
    assert not fit.converged and "maximum" in fit.message
