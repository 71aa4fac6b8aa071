"""Tests of the RELS ARMAX estimator (online_id.estimation.rels)."""

from __future__ import annotations

import pickle

import numpy as np
import pytest
import scipy.signal as sig

from online_id.estimation.model import ArmaxOrders
from online_id.estimation.rels import RecursiveArmax, RecursiveEstimator
from online_id.errors import ConfigError, InputDataError


def random_stable_poly(rng: np.random.Generator, order: int, radius: float) -> np.ndarray:
    """Monic polynomial in q^-1 with random roots inside ``radius`` (conjugate pairs)."""
    roots: list[complex] = []
    while len(roots) < order:
        if order - len(roots) >= 2 and rng.random() < 0.6:
            z = rng.uniform(0.2, radius) * np.exp(1j * rng.uniform(0.1, np.pi - 0.1))
            roots += [z, np.conj(z)]
        else:
            roots.append(rng.uniform(-radius, radius))
    return np.real(np.poly(roots)) if order else np.array([1.0])


def simulate(rng, a, b, c, n, noise_std, offset=0.0):
    """Simulate A y = B u + C e (+ offset / A(1) steady-state contribution)."""
    u = rng.standard_normal(n)
    e = noise_std * rng.standard_normal(n)
    y = sig.lfilter(b, a, u) + sig.lfilter(c, a, e) + offset / np.sum(a)
    return y, u


def arx_regressors(orders: ArmaxOrders, y: np.ndarray, u: np.ndarray) -> np.ndarray:
    """Phi for nc = 0, zero pre-sample history (as the recursive estimator)."""
    n = len(y)
    cols = []
    for k in range(1, orders.na + 1):
        cols.append(-np.concatenate((np.zeros(k), y[: n - k])))
    for k in range(orders.nk, orders.nk + orders.nb):
        cols.append(np.concatenate((np.zeros(k), u[: n - k])))
    if orders.offset:
        cols.append(np.ones(n))
    return np.column_stack(cols)


def reference_rels(orders, y, u, lam, p0, trace_max=np.inf):
    """Slow plain-numpy RELS with the same equations (full matrix, then symmetrised)."""
    n = orders.n_params
    theta = np.zeros(n)
    P = np.eye(n) * p0
    yh = np.zeros(orders.na)
    uh = np.zeros(orders.nk + orders.nb)
    eh = np.zeros(orders.nc)
    errs = []
    for yt, ut in zip(y, u):
        if uh.size:
            uh = np.concatenate(([ut], uh[:-1]))
        phi = np.concatenate((-yh, uh[orders.nk :], eh, [1.0] if orders.offset else []))
        e = yt - phi @ theta
        K = P @ phi / (lam + phi @ P @ phi)
        theta = theta + K * e
        P = (P - np.outer(K, phi @ P)) / lam
        P = 0.5 * (P + P.T)
        if np.trace(P) > trace_max:
            P *= trace_max / np.trace(P)
        eps = yt - phi @ theta
        if yh.size:
            yh = np.concatenate(([yt], yh[:-1]))
        if eh.size:
            eh = np.concatenate(([eps], eh[:-1]))
        errs.append(e)
    return theta, P, np.array(errs)


@pytest.mark.parametrize(
    ("seed", "orders"),
    [
        (0, ArmaxOrders(2, 2, 0)),
        (1, ArmaxOrders(4, 3, 0, nk=2)),
        (2, ArmaxOrders(3, 4, 0, nk=0)),
        (3, ArmaxOrders(1, 2, 0, offset=True)),
        (4, ArmaxOrders(0, 5, 0)),
    ],
)
def test_rls_equals_regularised_batch_least_squares(seed, orders):
    rng = np.random.default_rng(seed)
    a = random_stable_poly(rng, orders.na, 0.9)
    b = np.concatenate((np.zeros(orders.nk), rng.standard_normal(orders.nb)))
    y, u = simulate(rng, a, b, [1.0], 400, 0.1, offset=0.5 if orders.offset else 0.0)
    p0 = 1e8
    est = RecursiveArmax(orders, lam=1.0, p0=p0, trace_max=np.inf)
    est.update_block(y, u)
    Phi = arx_regressors(orders, y, u)
    n = orders.n_params
    theta_batch = np.linalg.solve(Phi.T @ Phi + np.eye(n) / p0, Phi.T @ y)
    theta_lstsq = np.linalg.lstsq(Phi, y, rcond=None)[0]
    assert np.linalg.norm(est.theta - theta_batch) <= 1e-8 * np.linalg.norm(theta_batch)
    assert np.linalg.norm(est.theta - theta_lstsq) <= 1e-6 * np.linalg.norm(theta_lstsq)


@pytest.mark.parametrize(
    ("seed", "orders", "lam"),
    [
        (10, ArmaxOrders(2, 2, 2), 1.0),
        (11, ArmaxOrders(3, 2, 1, nk=0), 0.99),
        (12, ArmaxOrders(2, 3, 3, nk=2, offset=True), 0.995),
    ],
)
def test_armax_recursion_equals_numpy_reference(seed, orders, lam):
    rng = np.random.default_rng(seed)
    a = random_stable_poly(rng, orders.na, 0.85)
    b = np.concatenate((np.zeros(orders.nk), rng.standard_normal(orders.nb)))
    c = random_stable_poly(rng, orders.nc, 0.4)
    y, u = simulate(rng, a, b, c, 600, 0.2)
    est = RecursiveArmax(orders, lam=lam, p0=100.0, trace_max=1e9)
    errs = est.update_block(y, u)
    theta_ref, P_ref, errs_ref = reference_rels(orders, y, u, lam, 100.0, trace_max=1e9)
    assert np.linalg.norm(est.theta - theta_ref) <= 1e-10 * np.linalg.norm(theta_ref)
    assert np.linalg.norm(est.P - P_ref) <= 1e-10 * np.linalg.norm(P_ref)
    assert np.max(np.abs(errs - errs_ref)) <= 1e-10 * np.max(np.abs(errs_ref))
    assert np.array_equal(est.P, est.P.T)


def test_update_and_update_block_are_bit_identical():
    rng = np.random.default_rng(20)
    orders = ArmaxOrders(3, 3, 2, offset=True)
    y, u = simulate(rng, [1, -1.2, 0.5, -0.1], [0, 1, 0.5, 0.2], [1, 0.3, 0.1], 500, 0.1)
    per_sample = RecursiveArmax(orders, lam=0.995)
    errs_ps = np.array([per_sample.update(y=yt, u=ut) for yt, ut in zip(y, u)])
    block = RecursiveArmax(orders, lam=0.995)
    errs_b = block.update_block(y, u)
    assert np.array_equal(errs_ps, errs_b)
    assert np.array_equal(per_sample.theta, block.theta)
    assert np.array_equal(per_sample.P, block.P)
    # across a block boundary: half a block, then per sample
    mixed = RecursiveArmax(orders, lam=0.995)
    errs_m1 = mixed.update_block(y[:250], u[:250])
    errs_m2 = [mixed.update(yt, ut) for yt, ut in zip(y[250:], u[250:])]
    assert np.array_equal(np.concatenate((errs_m1, errs_m2)), errs_b)
    assert np.array_equal(mixed.theta, block.theta)
    assert np.array_equal(mixed.P, block.P)


@pytest.mark.parametrize("seed", [30, 31, 32, 33])
def test_recovers_armax_parameters(seed):
    rng = np.random.default_rng(seed)
    orders = ArmaxOrders(2, 2, 1)
    a = random_stable_poly(rng, 2, 0.85)
    b = np.concatenate(([0.0], rng.uniform(0.5, 1.5, 1) * rng.choice([-1, 1]), rng.uniform(-0.5, 0.5, 1)))
    c = np.array([1.0, rng.uniform(-0.5, 0.5)])
    y, u = simulate(rng, a, b, c, 20000, 0.3)
    est = RecursiveArmax(orders, lam=1.0)
    est.update_block(y, u)
    theta_true = np.concatenate((a[1:], b[1:], c[1:]))
    np.testing.assert_allclose(est.theta, theta_true, atol=0.06)  # seed 30: ~0.04 at N=20000, 0.004 at 1e5
    a_hat, b_hat, c_hat = est.polynomials()
    assert a_hat[0] == 1.0 and c_hat[0] == 1.0 and b_hat[0] == 0.0


def test_forgetting_tracks_parameter_step():
    rng = np.random.default_rng(40)
    n = 4000
    u = rng.standard_normal(n)
    e = 0.05 * rng.standard_normal(n)
    y = np.zeros(n)
    for t in range(1, n):
        a1 = -0.5 if t < n // 2 else -0.8
        y[t] = -a1 * y[t - 1] + u[t - 1] + e[t]
    orders = ArmaxOrders(1, 1, 0)
    fast = RecursiveArmax(orders, lam=0.99)
    slow = RecursiveArmax(orders, lam=1.0)
    fast.update_block(y, u)
    slow.update_block(y, u)
    assert abs(fast.theta[0] - (-0.8)) < 0.02
    assert abs(slow.theta[0] - (-0.8)) > 0.05


def test_non_finite_input_resets_without_corrupting_theta():
    rng = np.random.default_rng(50)
    orders = ArmaxOrders(2, 2, 1)
    y, u = simulate(rng, [1, -1.0, 0.3], [0, 1, 0.5], [1, 0.2], 1000, 0.1)
    est = RecursiveArmax(orders, lam=0.999, p0=50.0)
    est.update_block(y[:500], u[:500])
    theta_before = est.theta
    assert np.isnan(est.update(y=np.nan, u=u[500]))
    assert est.n_resets == 1
    assert np.array_equal(est.theta, theta_before)
    assert np.array_equal(est.P, 50.0 * np.eye(5))
    assert est.update(y=y[501], u=np.inf) != est.update(y[502], u[502])  # NaN != x
    assert est.n_resets == 2
    errs = est.update_block(y[503:], u[503:])
    assert np.all(np.isfinite(errs)) and np.all(np.isfinite(est.theta)) and np.all(np.isfinite(est.P))
    assert est.n_samples == 1000
    np.testing.assert_allclose(est.theta[:4], [-1.0, 0.3, 1.0, 0.5], atol=0.05)


def test_overflow_resets_and_keeps_previous_theta():
    orders = ArmaxOrders(1, 1, 0)
    est = RecursiveArmax(orders, lam=1.0, p0=1e300, trace_max=np.inf)
    est.update(1.0, 1.0)
    theta_before = est.theta
    est.update(1e200, 1e200)  # phi^T P phi overflows
    assert est.n_resets == 1
    assert np.array_equal(est.theta, theta_before)
    assert np.all(np.isfinite(est.P))


def test_trace_bound_holds():
    rng = np.random.default_rng(60)
    orders = ArmaxOrders(2, 2, 0)
    est = RecursiveArmax(orders, lam=0.9, p0=1.0, trace_max=10.0)
    y = 0.01 * rng.standard_normal(300)
    u = np.zeros(300)
    for yt, ut in zip(y, u):
        est.update(yt, ut)
        assert np.trace(est.P) <= 10.0 * (1 + 1e-12)
    assert np.trace(est.P) > 9.0  # it did wind up to the bound
    assert RecursiveArmax(orders, p0=2.0).trace_max == 8.0


def test_frozen_when_input_is_constant():
    rng = np.random.default_rng(70)
    orders = ArmaxOrders(1, 1, 0)
    u = np.concatenate((rng.standard_normal(500), np.full(500, 0.7)))
    y = sig.lfilter([0, 1.0], [1, -0.5], u) + 0.1 * rng.standard_normal(1000)
    est = RecursiveArmax(orders, lam=0.99, min_excitation=0.1)
    est.update_block(y[:500], u[:500])
    assert not est.frozen
    assert est.excitation > 0.5
    est.update_block(y[500:800], u[500:800])
    assert est.frozen
    theta, P = est.theta, est.P
    est.update_block(y[800:], u[800:])
    assert est.frozen
    assert np.array_equal(est.theta, theta) and np.array_equal(est.P, P)
    assert np.array_equal(est.gain, np.zeros(2))


def test_pickle_and_state_round_trip_continue_identically():
    rng = np.random.default_rng(80)
    orders = ArmaxOrders(2, 2, 2, nk=0, offset=True)
    y, u = simulate(rng, [1, -1.1, 0.4], [1.0, 0.5], [1, 0.3, 0.1], 600, 0.1)
    est = RecursiveArmax(orders, lam=0.995, min_excitation=1e-3)
    est.update_block(y[:300], u[:300])
    clones = [
        pickle.loads(pickle.dumps(est)),
        RecursiveArmax.from_state(est.get_state()),
        est.copy(),
    ]
    state = est.get_state()
    assert all(isinstance(v, (int, float, bool, np.ndarray)) for v in state.values())
    errs = est.update_block(y[300:], u[300:])
    for clone in clones:
        assert np.array_equal(clone.update_block(y[300:], u[300:]), errs)
        assert np.array_equal(clone.theta, est.theta)
        assert np.array_equal(clone.P, est.P)
        assert clone.n_samples == est.n_samples == 600


def test_inputs_not_mutated_and_same_seed_same_result():
    rng = np.random.default_rng(90)
    orders = ArmaxOrders(2, 2, 1)
    y, u = simulate(rng, [1, -1.0, 0.3], [0, 1, 0.5], [1, 0.2], 300, 0.1)
    y_copy, u_copy = y.copy(), u.copy()
    theta0 = np.array([0.1, 0.0, 0.5, 0.0, 0.0])
    theta0_copy = theta0.copy()
    est = RecursiveArmax(orders, theta0=theta0)
    out = est.update_block(y, u)
    est.update_block(y.astype(np.float32), list(u))
    assert np.array_equal(y, y_copy) and np.array_equal(u, u_copy)
    assert np.array_equal(theta0, theta0_copy)
    theta = est.theta
    theta[:] = 99.0
    assert not np.array_equal(est.theta, theta)
    again = RecursiveArmax(orders, theta0=theta0).update_block(y, u)
    assert np.array_equal(out, again)


def test_interface_and_properties():
    orders = ArmaxOrders(2, 1, 1)
    est = RecursiveArmax(orders, p0=10.0)
    assert isinstance(est, RecursiveEstimator)
    e = est.update(y=1.0, u=2.0)
    assert e == est.innovation == 1.0
    assert est.gain.shape == (4,)
    assert est.n_samples == 1 and est.n_resets == 0 and not est.frozen
    est.update(2, 3)  # ints are accepted
    est.reset()
    assert np.array_equal(est.P, 10.0 * np.eye(4))
    est.reset(p0=5.0)
    assert np.array_equal(est.P, 5.0 * np.eye(4))
    assert "RecursiveArmax(na=2" in repr(est)


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"lam": 0.0}, "lam"),
        ({"lam": 1.5}, "lam"),
        ({"lam": float("nan")}, "lam"),
        ({"p0": -1.0}, "p0"),
        ({"p0": float("inf")}, "p0"),
        ({"trace_max": 0.0}, "trace_max"),
        ({"min_excitation": -1.0}, "min_excitation"),
        ({"theta0": np.zeros(3)}, "theta0"),
    ],
)
def test_invalid_configuration_raises_config_error(kwargs, match):
    with pytest.raises(ConfigError, match=match):
        RecursiveArmax(ArmaxOrders(2, 2, 0), **kwargs)


def test_invalid_block_raises_input_data_error():
    est = RecursiveArmax(ArmaxOrders(1, 1, 0))
    with pytest.raises(InputDataError, match="equal length"):
        est.update_block(np.zeros(3), np.zeros(4))
