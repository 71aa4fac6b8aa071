"""Absolute-value (direction-blind) sensor: the Wiener model :math:`y = |x|`.

Notes
-----
The linear part is an output-error model :math:`x = (B(q)/A(q)) u + x_0`
and the sensor returns :math:`y = |x|`.  The parameters minimise the
simulation error :math:`\\sum (|x(t)| - y(t))^2` on the estimation part
(``scipy.optimize.least_squares``), from several starts: the sign of
:math:`x` is first guessed from low-passed input, the linear part is fitted
by least squares to the sign-restored output :math:`s(t) y(t)`, and the sign
is updated from the simulated :math:`x` a few times before the nonlinear
fit.  The one-step predictor is an ARX model fitted by least squares to the
sign-restored output :math:`s(t) y(t)`, :math:`s = \\mathrm{sign}(x_{sim})`:
:math:`\\hat x(t) = -\\sum \\alpha_i s(t-i) y(t-i) + \\sum \\beta_j u(t-n_k-j) + k`,
and it predicts :math:`|\\hat x(t)|`.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.optimize import least_squares
from scipy.signal import lfilter

from online_id.diagnose.data import DiagnoseData
from online_id.diagnose.model import lag_matrix
from online_id.errors import EstimationError


@dataclass(frozen=True)
class WienerAbsFit:
    """Fitted :math:`y = |B/A\\,u + x_0|` (``nk`` input delay)."""

    a: np.ndarray
    b: np.ndarray
    x0: float
    nk: int
    V_est: float
    n_est: int
    predictor: np.ndarray
    kind: str = "absolute_value_sensor"

    @property
    def A(self) -> np.ndarray:
        return np.concatenate(([1.0], self.a))

    @property
    def n_params(self) -> int:
        return int(self.a.size + self.b.size + 1)

    def signed(self, u: np.ndarray) -> np.ndarray:
        """Simulated linear part :math:`x`."""
        return _simulate(self.a, self.b, self.x0, self.nk, u)

    def simulate(self, data: DiagnoseData, start: int) -> np.ndarray:
        """Simulated output :math:`|x|` (measured output before ``start``)."""
        out = data.y.astype(float).copy()
        out[start:] = np.abs(self.signed(data.u))[start:]
        return out

    def errors(self, data: DiagnoseData) -> np.ndarray:
        """One-step errors of the sign-restored predictor (see module notes)."""
        s = np.sign(self.signed(data.u))
        s[s == 0] = 1.0
        ys = s * data.y
        na, nb = self.a.size, self.b.size
        p = self.predictor
        xhat = (-lag_matrix(ys, np.arange(1, na + 1)) @ p[:na]
                + lag_matrix(data.u, self.nk + np.arange(nb)) @ p[na:na + nb] + p[-1])
        return data.y - np.abs(xhat)


def _simulate(a: np.ndarray, b: np.ndarray, x0: float, nk: int, u: np.ndarray) -> np.ndarray:
    B = np.concatenate((np.zeros(nk), b))
    return lfilter(B, np.concatenate(([1.0], a)), u) + x0


def _arx_signed(ys: np.ndarray, u: np.ndarray, na: int, nb: int, nk: int, t0: int) -> np.ndarray:
    phi = np.hstack((-lag_matrix(ys, np.arange(1, na + 1)),
                     lag_matrix(u, nk + np.arange(nb)), np.ones((ys.size, 1))))
    eta, *_ = np.linalg.lstsq(phi[t0:], ys[t0:], rcond=1e-10)
    a, b, k = eta[:na], eta[na:na + nb], eta[-1]
    A1 = 1.0 + a.sum()
    return np.concatenate((a, b, [k / A1 if abs(A1) > 1e-6 else 0.0]))


def fit_wiener_abs(data: DiagnoseData, na: int, nb: int, nk: int, n_est: int) -> WienerAbsFit:
    """Fit :math:`y = |B/A\\,u + x_0|` on samples ``0 .. n_est`` (see module notes)."""
    u, y = data.u[:n_est], data.y[:n_est]
    t0 = max(na, nk + nb - 1, 1)
    if n_est - t0 <= 4 * (na + nb + 1):
        raise EstimationError(f"{data.source}: too few samples for the absolute-value sensor model")

    def split(p: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
        return p[:na], p[na:na + nb], float(p[-1])

    def resid(p: np.ndarray) -> np.ndarray:
        a, b, x0 = split(p)
        if na and np.max(np.abs(np.roots(np.concatenate(([1.0], a))))) >= 1.0:
            return np.full(n_est - t0, 1e6 * (np.std(y) + 1.0))
        return (np.abs(_simulate(a, b, x0, nk, u)) - y)[t0:]

    uc = u - u.mean()
    starts = []
    for tau in (1.0, 3.0, 10.0, 30.0):
        lam = np.exp(-1.0 / tau)
        s = np.sign(lfilter([1.0 - lam], [1.0, -lam], uc))
        s[s == 0] = 1.0
        p = _arx_signed(s * y, u, na, nb, nk, t0)
        for _ in range(5):
            a, b, x0 = split(p)
            if na and np.max(np.abs(np.roots(np.concatenate(([1.0], a))))) >= 1.0:
                break
            s = np.sign(_simulate(a, b, x0, nk, u))
            s[s == 0] = 1.0
            p = _arx_signed(s * y, u, na, nb, nk, t0)
        starts.append(p)
    best = None
    for p0 in starts:
        a0 = p0[:na]
        if na and np.max(np.abs(np.roots(np.concatenate(([1.0], a0))))) >= 1.0:
            continue
        res = least_squares(resid, p0, method="trf", x_scale="jac", max_nfev=200)
        if best is None or res.cost < best.cost:
            best = res
    if best is None:
        raise EstimationError(f"{data.source}: no stable start for the absolute-value sensor model")
    a, b, x0 = split(best.x)
    V = float(np.mean(resid(best.x) ** 2))
    sgn = np.sign(_simulate(a, b, x0, nk, u))
    sgn[sgn == 0] = 1.0
    phi = np.hstack((-lag_matrix(sgn * y, np.arange(1, na + 1)),
                     lag_matrix(u, nk + np.arange(nb)), np.ones((n_est, 1))))
    pred, *_ = np.linalg.lstsq(phi[t0:], (sgn * y)[t0:], rcond=1e-10)
    return WienerAbsFit(a, b, x0, nk, V, n_est, pred)


def looks_direction_blind(y: np.ndarray) -> bool:
    """Whether ``y`` looks like the output of a sensor that cannot see direction.

    Such a sensor reports :math:`|x|`: the output has a floor at zero (its
    minimum lies within 5 % of its range from 0) and it visits the floor
    (at least 2 % of the samples lie within 10 % of the range above it).
    """
    y = np.asarray(y, dtype=float)
    span = float(np.ptp(y))
    if span <= 0:
        return False
    lo = float(np.min(y))
    return abs(lo) <= 0.05 * span and float(np.mean(y <= lo + 0.1 * span)) >= 0.02
