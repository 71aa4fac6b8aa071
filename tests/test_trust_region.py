"""The QR trust-region least squares takes scipy's ``trf`` steps (online_id.estimation.trust_region)."""

import numpy as np
import pytest
from scipy.linalg import svd
from scipy.optimize import least_squares

from online_id.estimation.model import ArmaxOrders
from online_id.estimation.pem import _PemProblem, hannan_rissanen
from online_id.estimation.trust_region import subproblem_data, trust_region_lsq


@pytest.mark.parametrize("seed", range(6))
def test_the_qr_gives_the_singular_values_and_projections_of_the_svd(seed):
    rng = np.random.default_rng(seed)
    m, n = int(rng.integers(40, 4000)), int(rng.integers(2, 30))
    # columns of very different size and a near-dependent pair, as in an over-parametrised model
    J = rng.standard_normal((m, n)) * 10.0 ** rng.uniform(-4, 4, n)
    J[:, -1] = J[:, 0] * 3.0 + 1e-7 * rng.standard_normal(m)
    f = rng.standard_normal(m)
    U, s, Vt = svd(J, full_matrices=False)
    s2, V2, uf2 = subproblem_data(J, f)
    np.testing.assert_allclose(s2, s, rtol=1e-9, atol=1e-13 * s[0])
    sign = np.sign(np.sum(V2 * Vt.T, axis=0))  # singular vectors are defined up to sign
    well = s > 1e-6 * s[0]  # (a near-zero singular value's vector is not determined)
    np.testing.assert_allclose((sign * uf2)[well], (U.T @ f)[well], atol=1e-9 * np.linalg.norm(f))
    np.testing.assert_allclose((V2 * sign)[:, well], Vt.T[:, well], atol=1e-8)


def _exp_problem(rng):
    """A sum of damped exponentials with random truth, noise and start: a curved, badly scaled problem."""
    t = np.linspace(0.0, 5.0, int(rng.integers(50, 800)))
    truth = np.array([rng.uniform(0.5, 5), rng.uniform(0.2, 3), rng.uniform(-3, 3), rng.uniform(2, 9)])
    y = truth[0] * np.exp(-truth[1] * t) + truth[2] * np.exp(-truth[3] * t) + 0.01 * rng.standard_normal(t.size)

    def fun(x):
        return x[0] * np.exp(-x[1] * t) + x[2] * np.exp(-x[3] * t) - y

    def jac(x):
        e1, e2 = np.exp(-x[1] * t), np.exp(-x[3] * t)
        return np.column_stack([e1, -x[0] * t * e1, e2, -x[2] * t * e2])

    return fun, jac, truth * rng.uniform(0.6, 1.4, 4)


@pytest.mark.parametrize("seed", range(8))
def test_the_iteration_is_scipys_trf_on_random_curve_fits(seed):
    rng = np.random.default_rng(100 + seed)
    fun, jac, x0 = _exp_problem(rng)
    tol = float(10.0 ** rng.uniform(-10, -3))
    ref = least_squares(fun, x0, jac=jac, method="trf", x_scale="jac", ftol=tol, xtol=tol, gtol=tol)
    got = trust_region_lsq(fun, jac, x0, ftol=tol, xtol=tol, gtol=tol)
    assert (got.status, got.nfev, got.njev) == (ref.status, ref.nfev, ref.njev)
    np.testing.assert_allclose(got.x, ref.x, rtol=1e-7, atol=1e-10)
    assert got.message == ref.message


@pytest.mark.parametrize("seed", range(6))
def test_the_iteration_is_scipys_trf_on_armax_prediction_error_fits(seed):
    """The window fits' problem: random stable ARMAX plants and orders, refused trial points included."""
    rng = np.random.default_rng(200 + seed)
    na, nb, nc = int(rng.integers(2, 7)), int(rng.integers(1, 6)), int(rng.integers(1, 5))
    orders = ArmaxOrders(na, nb, nc, 1, bool(rng.integers(0, 2)))
    poles = 0.95 * rng.uniform(0.3, 1.0, na) * np.exp(1j * rng.uniform(0.05, 2.5, na))
    A = np.real(np.poly(np.concatenate([poles[: na // 2], np.conj(poles[: na // 2]), np.abs(poles[na // 2 * 2:])])))
    n = int(rng.integers(600, 3000))
    u = rng.standard_normal(n)
    e = 0.1 * rng.standard_normal(n)
    from scipy.signal import lfilter
    C = np.real(np.poly(0.6 * rng.uniform(-1, 1, nc)))
    y = lfilter(np.r_[0.0, rng.standard_normal(nb)], A, u) + lfilter(C, A, e) + (0.3 if orders.offset else 0.0)
    problem = _PemProblem(y, u, orders, orders.max_lag)
    x0 = hannan_rissanen(y, u, orders) + 0.05 * rng.standard_normal(orders.n_params)
    x0[na + nb: na + nb + nc] *= 0.5  # keep the start's C minimum phase
    max_nfev = int(rng.integers(3, 60))
    ref = least_squares(problem.residuals, x0, jac=problem.jacobian, method="trf", x_scale="jac",
                        ftol=1e-6, xtol=1e-6, gtol=1e-6, max_nfev=max_nfev)
    got = trust_region_lsq(problem.residuals, problem.jacobian, x0, ftol=1e-6, xtol=1e-6, gtol=1e-6,
                           max_nfev=max_nfev)
    assert (got.status, got.nfev, got.njev) == (ref.status, ref.nfev, ref.njev)
    np.testing.assert_allclose(got.x, ref.x, rtol=1e-6, atol=1e-9)


def test_a_start_with_non_finite_residuals_is_refused():
    with pytest.raises(ValueError, match="not finite"):
        trust_region_lsq(lambda x: np.full(5, np.inf), lambda x: np.ones((5, 1)), np.zeros(1))
