"""Standard deviations of the driveline parameters from the fits' covariances (delta method).

Notes
-----
Each operating point's fit gives the asymptotic covariance
:math:`\\Sigma_k` of its parameters :math:`\\theta_k` (``ArmaxFit.covariance``,
:math:`V (J^T J)^{-1}`); the points' data do not overlap, so the
:math:`\\theta_k` are independent.  The driveline follows from them through

1. the driveline pole of each point: frequency and damping
   (:func:`~online_id.analysis.poles.pole_gradient`);
2. the medians over the points (:func:`~online_id.analysis.poles.sort_poles`):
   taken to vary as the mean of the points' values times the median's
   efficiency factor for normal errors (:func:`_median_weights`);
3. the anti-resonance and high-frequency gain fitted to each point's
   frequency response ``B/A`` with the pole pair fixed to the medians
   (:func:`~online_id.analysis.physical.response_sensitivity`), and their
   medians;
4. :func:`~online_id.analysis.physical.parameters` (``c_s``, ``d_s``,
   ``J1``, ``J2`` from ``f0``, ``zeta``, ``fa``, the gain or given inertias;
   :func:`~online_id.analysis.physical.parameter_jacobian`).

With :math:`G_k = \\partial p / \\partial \\theta_k` of the whole chain, the
covariance of the parameters is :math:`\\sum_k G_k \\Sigma_k G_k^T` (first
order).  A given inertia has no standard deviation (None).  The 95 %
interval is :math:`\\pm 1.96\\,\\sigma` (normal approximation).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from online_id.analysis.physical import PHYSICAL, DrivelineParameters, parameter_jacobian, response_sensitivity
from online_id.analysis.poles import DRIVELINE, pole_gradient
from online_id.estimation.pem import ArmaxFit

Z95 = 1.959964


@dataclass(frozen=True)
class ParameterStd:
    """Standard deviations of ``f0_hz, zeta, c_s, d_s, J1, J2`` (None: given, or not identified)."""

    std: dict[str, float | None]

    def as_dict(self) -> dict:
        return dict(self.std)

    def interval(self, values: DrivelineParameters) -> dict[str, list[float] | None]:
        """95 % intervals ``[value - 1.96 std, value + 1.96 std]`` per parameter."""
        out: dict[str, list[float] | None] = {}
        for k in PHYSICAL:
            v, s = getattr(values, k), self.std.get(k)
            out[k] = None if v is None or s is None else [float(v - Z95 * s), float(v + Z95 * s)]
        return out


# var(median) / var(mean) of K independent normal samples (order statistics; K -> inf: pi/2)
MEDIAN_EFFICIENCY = {1: 1.0, 2: 1.0, 3: 1.346, 4: 1.193, 5: 1.434, 6: 1.287, 7: 1.468, 8: 1.339, 9: 1.487}


def _median_weights(values: Sequence[float]) -> np.ndarray:
    """Weights ``w`` with ``var(median) ~ sum w_k^2 var_k`` for independent estimates of one quantity.

    The median of K estimates of one value varies like their mean times the
    square root of :data:`MEDIAN_EFFICIENCY` (normal errors); the literal
    gradient of the median (the middle value alone) would give the middle
    point's variance, which overstates the spread of a median of several.
    """
    K = len(values)
    if K == 0:
        return np.zeros(0)
    return np.full(K, np.sqrt(MEDIAN_EFFICIENCY.get(K, np.pi / 2)) / K)


@dataclass(frozen=True)
class PointInputs:
    """What one operating point contributes: its fit, driveline pole and response fit (None where missing)."""

    fit: ArmaxFit
    dt: float
    pole_z: complex | None
    f_hz: np.ndarray | None  # the frequencies of the response fit
    response_fit: object | None  # ResponseFit


def driveline_std(points: Sequence[PointInputs], driveline: DrivelineParameters,
                  given: Sequence[str] = ()) -> ParameterStd:
    """Standard deviations of the driveline parameters (see module notes); ``given``: names of given inertias."""
    from online_id.analysis.physical import frequency_response

    K = len(points)
    d = [p.fit.theta.size for p in points]
    # 1-2: f0 and zeta, medians over the points with a driveline pole
    members = [k for k, p in enumerate(points) if p.pole_z is not None]
    grads = {k: pole_gradient(points[k].fit.A, points[k].pole_z, points[k].dt) for k in members}
    w_f = _median_weights([_damp_f(points[k])[0] for k in members])
    w_z = _median_weights([_damp_f(points[k])[1] for k in members])
    R = [np.zeros((2, d[k])) for k in range(K)]  # d (f0, zeta) / d theta_k
    for i, k in enumerate(members):
        na = points[k].fit.orders.na
        g_f, g_z = grads[k]
        if not (np.all(np.isfinite(g_f)) and np.all(np.isfinite(g_z))):
            return ParameterStd({n: None for n in PHYSICAL})
        R[k][0, :na] = w_f[i] * g_f
        R[k][1, :na] = w_z[i] * g_z
    # 3: anti-resonance and gain per point, their medians
    with_resp = [k for k, p in enumerate(points) if p.response_fit is not None and p.f_hz is not None]
    rows_fa = [np.zeros(d[k]) for k in range(K)]
    rows_g = [np.zeros(d[k]) for k in range(K)]
    if with_resp:
        w_fa = _median_weights([points[k].response_fit.fa_hz for k in with_resp])
        w_g = _median_weights([points[k].response_fit.gain for k in with_resp])
        for i, j in enumerate(with_resp):
            p = points[j]
            h = frequency_response(p.fit.B, p.fit.A, p.f_hz, p.dt)
            D, E = response_sensitivity(p.f_hz, h, p.response_fit, driveline.f0_hz, driveline.zeta)
            L = _log_response_gradient(p.fit, p.f_hz, p.dt)  # 2m x d
            direct = D @ L  # d (fa_j, gain_j) / d theta_j
            rows_fa[j] += w_fa[i] * direct[0]
            rows_g[j] += w_g[i] * direct[1]
            for k in range(K):  # through the pole pair (f0, zeta) the response fit is held to
                rows_fa[k] += w_fa[i] * (E[0] @ R[k])
                rows_g[k] += w_g[i] * (E[1] @ R[k])
    # 4: the physical parameters
    jac = parameter_jacobian(driveline.f0_hz, driveline.zeta, driveline.fa_hz,
                             (1.0 / driveline.J1) if driveline.source == "identified gain and anti-resonance" else None,
                             **_given_inertias(driveline, given))
    cov = np.zeros((len(PHYSICAL), len(PHYSICAL)))
    for k in range(K):
        G = jac @ np.vstack((R[k], rows_fa[k], rows_g[k]))
        G = np.where(np.isfinite(G), G, 0.0)
        cov += G @ points[k].fit.covariance @ G.T
    std = {}
    for i, name in enumerate(PHYSICAL):
        value = getattr(driveline, name)
        std[name] = None if value is None or name in given or not np.isfinite(jac[i]).all() else \
            float(np.sqrt(max(cov[i, i], 0.0)))
    return ParameterStd(std)


def _given_inertias(driveline: DrivelineParameters, given: Sequence[str]) -> dict:
    return {k: (getattr(driveline, k) if k in given else None) for k in ("J1", "J2")} | (
        {"J_total": driveline.J1 + driveline.J2} if "J_total" in given else {})


def _damp_f(p: PointInputs) -> tuple[float, float]:
    s = np.log(p.pole_z) / p.dt
    return float(abs(s) / (2 * np.pi)), float(-s.real / abs(s))


def _log_response_gradient(fit: ArmaxFit, f_hz: np.ndarray, dt: float) -> np.ndarray:
    """``[Re; Im]`` of :math:`\\partial \\log(B/A)(e^{j\\omega T}) / \\partial\\theta` (2m x d; C does not enter)."""
    o = fit.orders
    zinv = np.exp(-2j * np.pi * np.asarray(f_hz) * dt)
    a_val = np.polyval(fit.A[::-1], zinv)
    b_val = np.polyval(fit.B[::-1], zinv)
    L = np.zeros((zinv.size, fit.theta.size), dtype=complex)
    for k in range(1, o.na + 1):
        L[:, k - 1] = -zinv**k / a_val
    for j in range(o.nb):
        L[:, o.na + j] = zinv ** (o.nk + j) / b_val
    return np.vstack((L.real, L.imag))


def from_points(points, driveline: DrivelineParameters | None, response_bands: dict[int, np.ndarray],
                given: Sequence[str]) -> ParameterStd | None:
    """:func:`driveline_std` for :class:`~online_id.estimation.identification.PointResult` objects."""
    if driveline is None:
        return None
    inputs = []
    for k, p in enumerate(points):
        pole = next((q for q in p.poles if q.cls == DRIVELINE), None)
        inputs.append(PointInputs(p.fit, p.dt, pole.z if pole is not None else None, response_bands.get(k),
                                  p.response))
    return driveline_std(inputs, driveline, given)
