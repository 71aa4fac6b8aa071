"""ARMAX estimated with filterpy's Kalman filter (parameters as a random walk).

The parameter vector :math:`\\theta` is the Kalman state, the regressor
:math:`\\varphi(t)` (same layout as :class:`online_id.estimation.model.ArmaxOrders`,
a posteriori residuals in the C-part) is the measurement row.

Notes
-----
State-space model of the parameters:

.. math::

    \\theta(t) = \\theta(t-1) + w(t),      \\quad w \\sim N(0, q I)

    y(t) = \\varphi(t)^T \\theta(t) + v(t),  \\quad v \\sim N(0, r)

filterpy's ``predict`` with fading memory :math:`\\alpha` gives
:math:`P^- = \\alpha^2 P + Q`; with :math:`\\alpha^2 = 1/\\lambda` and
:math:`q = 0` the gain of ``update`` is

.. math::

    K = \\frac{P \\varphi / \\lambda}{\\varphi^T P \\varphi / \\lambda + r}
      = \\frac{P \\varphi}{\\varphi^T P \\varphi + r \\lambda}

so the filter equals RELS with forgetting :math:`\\lambda`
(:class:`online_id.estimation.rels.RecursiveArmax`) when ``r = 1`` and both start
from the same ``p0``.  More generally, the parameter estimates are unchanged
when ``r`` and ``p0`` are scaled together (``r = c``, ``p0 -> c p0``; the
covariance is then ``c`` times the RELS one).
"""

from __future__ import annotations

import copy
import math

import numpy as np
from filterpy.kalman import KalmanFilter

from online_id.estimation.model import ArmaxOrders
from online_id.estimation.rels import check_block, check_lam, check_positive, check_theta0
from online_id.errors import ConfigError


class KalmanArmax:
    """ARMAX parameters tracked by ``filterpy.kalman.KalmanFilter``.

    Parameters
    ----------
    orders
        Model orders; fixes the layout of ``theta`` and of the regressor.
    q
        Random-walk variance of each parameter per sample (``Q = q I``).
    r
        Measurement noise variance ``R``.
    p0
        Initial covariance ``P(0) = p0 I``, also used by resets.
    lam
        Fading memory: filterpy's ``alpha = 1/sqrt(lam)``; ``lam = 1`` is
        the plain Kalman filter.
    theta0
        Initial parameter vector (default zeros); copied, never mutated.

    Attributes
    ----------
    orders : ArmaxOrders
        The model orders.
    kf : filterpy.kalman.KalmanFilter
        The underlying filter (``kf.K`` gain, ``kf.y`` innovation, ``kf.S``).

    Notes
    -----
    See the module notes: with ``q = 0`` and ``r = 1`` the estimates equal
    RELS with forgetting factor ``lam``.  A non-finite sample keeps
    ``theta``, resets ``P = p0 I``, clears the regressor history, counts in
    ``n_resets`` and returns NaN.
    """

    def __init__(
        self,
        orders: ArmaxOrders,
        *,
        q: float = 0.0,
        r: float = 1.0,
        p0: float = 1e3,
        lam: float = 1.0,
        theta0: np.ndarray | None = None,
    ) -> None:
        if not isinstance(orders, ArmaxOrders):
            raise ConfigError(f"Expected orders of type ArmaxOrders, but got {type(orders).__name__}")
        q = float(q)
        if not (math.isfinite(q) and q >= 0.0):
            raise ConfigError(f"Expected q >= 0 and finite, but got {q!r}")
        self.orders = orders
        self.q = q
        self.r = check_positive("r", r)
        self.p0 = check_positive("p0", p0)
        self.lam = check_lam(lam)
        n = orders.n_params
        kf = KalmanFilter(dim_x=n, dim_z=1)
        kf.x = check_theta0(orders, theta0).reshape(n, 1)
        kf.P = np.eye(n) * self.p0
        kf.F = np.eye(n)  # theta(t) = theta(t-1) + w(t)
        kf.Q = np.eye(n) * q  # Q = q I
        kf.R = np.array([[self.r]])  # R = r
        kf.alpha = 1.0 / math.sqrt(self.lam)  # P- = alpha^2 P + Q = P / lam + Q
        self.kf = kf
        self._phi = np.zeros(n)
        self._y_hist = np.zeros(orders.na)
        self._u_hist = np.zeros(orders.nk + orders.nb)
        self._eps_hist = np.zeros(orders.nc)
        self._n_samples = 0
        self._n_resets = 0
        self._innovation = 0.0

    def update(self, y: float, u: float) -> float:
        """Process one sample; return the a priori prediction error e(t)."""
        o = self.orders
        y = float(y)
        u = float(u)
        self._n_samples += 1
        if not (math.isfinite(y) and math.isfinite(u)):
            self._reset_after_failure(clear_history=True)
            self._innovation = math.nan
            return math.nan
        # shift u(t) in first: with nk = 0, u(t) is part of phi(t)
        if self._u_hist.size:
            self._u_hist[1:] = self._u_hist[:-1]
            self._u_hist[0] = u
        # phi(t) = [-y(t-1..t-na), u(t-nk..t-nk-nb+1), eps(t-1..t-nc), 1]
        phi = self._phi
        phi[: o.na] = -self._y_hist
        phi[o.na : o.na + o.nb] = self._u_hist[o.nk : o.nk + o.nb]
        phi[o.na + o.nb : o.na + o.nb + o.nc] = self._eps_hist
        if o.offset:
            phi[-1] = 1.0
        H = phi.reshape(1, -1)
        x_prev = self.kf.x.copy()
        self.kf.predict()  # theta- = theta ; P- = alpha^2 P + Q
        self.kf.update(y, H=H)  # e = y - H theta- ; K = P- H^T / S ; theta = theta- + K e
        e = float(self.kf.y[0, 0])
        if not (math.isfinite(e) and np.all(np.isfinite(self.kf.x)) and np.all(np.isfinite(self.kf.P))):
            self.kf.x = x_prev
            self._reset_after_failure(clear_history=False)
            eps = e if math.isfinite(e) else 0.0
        else:
            eps = y - float(phi @ self.kf.x[:, 0])  # eps(t) = y(t) - phi^T theta(t)
        self._innovation = e
        if self._y_hist.size:
            self._y_hist[1:] = self._y_hist[:-1]
            self._y_hist[0] = y
        if self._eps_hist.size:
            self._eps_hist[1:] = self._eps_hist[:-1]
            self._eps_hist[0] = eps
        return e

    def update_block(self, y: np.ndarray, u: np.ndarray) -> np.ndarray:
        """Process a block of samples (a Python loop over :meth:`update`)."""
        y_arr, u_arr = check_block(y, u)
        out = np.empty_like(y_arr)
        for t in range(y_arr.shape[0]):
            out[t] = self.update(y_arr[t], u_arr[t])
        return out

    def _reset_after_failure(self, *, clear_history: bool) -> None:
        self.kf.P = np.eye(self.orders.n_params) * self.p0
        self.kf.K = np.zeros_like(self.kf.K)
        self._n_resets += 1
        if clear_history:
            self._y_hist[:] = 0.0
            self._u_hist[:] = 0.0
            self._eps_hist[:] = 0.0

    @property
    def theta(self) -> np.ndarray:
        """Parameter estimate (a copy)."""
        return self.kf.x[:, 0].copy()

    @property
    def P(self) -> np.ndarray:
        """Posterior covariance (a copy)."""
        return np.array(self.kf.P, dtype=float)

    @property
    def gain(self) -> np.ndarray:
        """Kalman gain K of the last update."""
        return np.asarray(self.kf.K, dtype=float).reshape(-1).copy()

    @property
    def innovation(self) -> float:
        """A priori error e(t) of the last update."""
        return self._innovation

    @property
    def regressor(self) -> np.ndarray:
        """Regressor phi(t) of the last update (a copy)."""
        return self._phi.copy()

    @property
    def n_samples(self) -> int:
        """Number of samples processed."""
        return self._n_samples

    @property
    def n_resets(self) -> int:
        """Number of automatic resets (non-finite values)."""
        return self._n_resets

    @property
    def frozen(self) -> bool:
        """Always False: the Kalman estimator has no excitation guard."""
        return False

    def polynomials(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Estimated ``(A, B, C)`` (see :meth:`ArmaxOrders.split`)."""
        return self.orders.split(self.theta)

    def reset(self, p0: float | None = None) -> None:
        """Restart adaptation: P = p0 I; theta and the history are kept."""
        value = self.p0 if p0 is None else check_positive("p0", p0)
        self.kf.P = np.eye(self.orders.n_params) * value

    def copy(self) -> KalmanArmax:
        """Independent copy that continues identically."""
        return copy.deepcopy(self)

    def __repr__(self) -> str:
        o = self.orders
        return (
            f"KalmanArmax(na={o.na}, nb={o.nb}, nc={o.nc}, nk={o.nk}, offset={o.offset}, "
            f"q={self.q}, r={self.r}, lam={self.lam}, n_samples={self.n_samples})"
        )
