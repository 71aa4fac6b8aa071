"""Tests of the filterpy Kalman ARMAX estimator (online_id.estimation.kalman)."""

from __future__ import annotations

import pickle

import numpy as np
import pytest
import scipy.signal as sig

from online_id.estimation.kalman import KalmanArmax
from online_id.estimation.model import ArmaxOrders
from online_id.estimation.rels import RecursiveArmax, RecursiveEstimator
from online_id.errors import ConfigError


def data(seed: int, n: int = 1500):
    rng = np.random.default_rng(seed)
    u = rng.standard_normal(n)
    e = 0.2 * rng.standard_normal(n)
    y = sig.lfilter([0, 1.0, 0.4], [1, -1.2, 0.5], u) + sig.lfilter([1, 0.3], [1, -1.2, 0.5], e)
    return y, u


def rel(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.linalg.norm(a - b) / np.linalg.norm(b))


@pytest.mark.parametrize("lam", [1.0, 0.995])
@pytest.mark.parametrize("orders", [ArmaxOrders(2, 2, 0), ArmaxOrders(2, 2, 1, offset=True)])
def test_kalman_with_q0_r1_equals_rels(lam, orders):
    y, u = data(1)
    rels = RecursiveArmax(orders, lam=lam, p0=1e3, trace_max=np.inf)
    kal = KalmanArmax(orders, q=0.0, r=1.0, p0=1e3, lam=lam)
    assert kal.kf.alpha == pytest.approx(1.0 / np.sqrt(lam), rel=1e-15)
    errs_r = rels.update_block(y, u)
    errs_k = kal.update_block(y, u)
    assert rel(kal.theta, rels.theta) < 1e-8
    assert rel(kal.P, rels.P) < 1e-8
    assert rel(errs_k, errs_r) < 1e-8
    assert rel(kal.gain, rels.gain) < 1e-8


@pytest.mark.parametrize("lam", [1.0, 0.995])
def test_kalman_scaled_r_and_p0_gives_same_theta(lam):
    # r = lam with p0 -> lam * p0 is the same filter: theta equal, P scaled by lam
    orders = ArmaxOrders(2, 2, 1)
    y, u = data(2)
    rels = RecursiveArmax(orders, lam=lam, p0=1e3, trace_max=np.inf)
    kal = KalmanArmax(orders, q=0.0, r=lam, p0=lam * 1e3, lam=lam)
    errs_r = rels.update_block(y, u)
    errs_k = kal.update_block(y, u)
    assert rel(kal.theta, rels.theta) < 1e-8
    assert rel(errs_k, errs_r) < 1e-8
    assert rel(kal.P, lam * rels.P) < 1e-8


def test_kalman_random_walk_tracks_step():
    rng = np.random.default_rng(3)
    n = 3000
    u = rng.standard_normal(n)
    y = np.zeros(n)
    for t in range(1, n):
        a1 = -0.5 if t < n // 2 else -0.8
        y[t] = -a1 * y[t - 1] + u[t - 1] + 0.05 * rng.standard_normal()
    kal = KalmanArmax(ArmaxOrders(1, 1, 0), q=1e-4, r=0.05**2)
    kal.update_block(y, u)
    assert abs(kal.theta[0] + 0.8) < 0.03
    assert abs(kal.theta[1] - 1.0) < 0.03


def test_kalman_interface_guards_and_pickle():
    orders = ArmaxOrders(2, 2, 1)
    y, u = data(4, 400)
    y_copy, u_copy = y.copy(), u.copy()
    kal = KalmanArmax(orders, lam=0.995)
    assert isinstance(kal, RecursiveEstimator)
    kal.update_block(y[:200], u[:200])
    theta = kal.theta
    assert np.isnan(kal.update(y=np.nan, u=1.0))
    assert kal.n_resets == 1 and np.array_equal(kal.theta, theta)
    clone = pickle.loads(pickle.dumps(kal))
    copy = kal.copy()
    errs = kal.update_block(y[200:], u[200:])
    assert np.array_equal(clone.update_block(y[200:], u[200:]), errs)
    assert np.array_equal(copy.update_block(y[200:], u[200:]), errs)
    assert np.array_equal(clone.theta, kal.theta)
    assert np.array_equal(y, y_copy) and np.array_equal(u, u_copy)
    assert kal.n_samples == 401  # 400 data samples + the NaN one
    a, b, c = kal.polynomials()
    assert a[0] == 1.0 and c[0] == 1.0 and b[0] == 0.0
    kal.reset(p0=7.0)
    assert np.array_equal(kal.P, 7.0 * np.eye(5))


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [({"lam": 1.2}, "lam"), ({"r": 0.0}, "r"), ({"q": -1.0}, "q"), ({"p0": 0.0}, "p0")],
)
def test_kalman_invalid_configuration(kwargs, match):
    with pytest.raises(ConfigError, match=match):
        KalmanArmax(ArmaxOrders(1, 1, 0), **kwargs)
