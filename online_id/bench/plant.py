"""The bench plant: numba kernels for the nonlinear model and its linear modes.

Notes
-----
State vector ``x`` (indices below), all in rad, rad/s:

.. math::

    \\dot\\varphi = y_1 - y_2, \\qquad \\dot\\theta_1 = y_1, \\qquad \\dot\\theta_2 = y_2

    J_1 \\dot y_1 = -T_s - u - T_{dist}

    J_2 \\dot y_2 = T_s - w(\\theta_2, y_2) - T_{23}

    T_s = c_s\\,\\mathrm{dz}(\\varphi) + d_s (y_1 - y_2)

    w = \\mathrm{sign}(y_2)(b_0 + b_1|y_2| + b_2 y_2^2)
        - V \\sum_i k_i\\, g(\\mathrm{wrap}(\\theta_2 - \\vartheta_i)),
    \\qquad g(x) = \\frac{x}{\\sigma} e^{1/2 - x^2/(2\\sigma^2)}

so compression (x < 0, before top dead centre) brakes the engine and
expansion drives it.  ``dz`` is the backlash dead zone (identity without
backlash; torque zero inside the gap).  The optional third inertia has
:math:`\\dot\\varphi_2 = y_2 - y_3`, :math:`J_3 \\dot y_3 = T_{23} =
c_2 \\varphi_2 + d_2 (y_2 - y_3)`.  ``u`` is the dyno torque (control + test
signal, held per sample) plus ripple :math:`A_r \\sin(o\\,\\theta_1 + \\psi)`;
``T_dist`` is a sinusoidal disturbance plus ``gain * x_s`` of the structural
mode :math:`\\ddot x_s + 2\\zeta_s\\omega_s \\dot x_s + \\omega_s^2 x_s = n(t)`.
Effects for the diagnosis (off by default, then the arithmetic is unchanged):
an unmeasured order torque :math:`A \\sin(o\\,\\theta_i + \\psi)` on the dyno
(added to ``T_dist``) or the engine (subtracted in the ``J_2`` equation), and
Coulomb friction in the coupling, :math:`F_c \\tanh((y_1 - y_2)/v_\\epsilon)`
added to ``T_s``.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

# state indices
PHI, Y1, Y2, THETA1, THETA2, PHI2, Y3, XS, VS = range(9)
N_STATES = 9

# parameter indices
(P_J1, P_J2, P_J3, P_C2, P_D2, P_B0, P_B1, P_B2, P_V, P_SIGMA, P_GAP,
 P_RIP_A, P_RIP_ORDER, P_RIP_PHASE, P_DIST_A, P_DIST_W, P_STR_W, P_STR_Z,
 P_STR_GAIN, P_ORD_A, P_ORD_ORDER, P_ORD_PHASE, P_ORD_ENGINE, P_COUL, P_COUL_V, P_THIRD_AT) = range(26)
N_PARAMS = 26
THIRD_AT = {"engine": 0.0, "between": 1.0, "dyno": 2.0}  # P_THIRD_AT: where the third inertia sits

_FOUR_PI = 4.0 * math.pi


@njit(cache=True)
def _shaft_torque(phi, dphi, c_s, d_s, gap):
    if gap > 0.0:
        half = 0.5 * gap
        if phi > half:
            return c_s * (phi - half) + d_s * dphi
        if phi < -half:
            return c_s * (phi + half) + d_s * dphi
        return 0.0
    return c_s * phi + d_s * dphi


@njit(cache=True)
def _engine_torque(theta2, y2, p, tdc, strength):
    # friction, eq. (3) of the paper, odd in speed
    ay = abs(y2)
    w = math.copysign(p[P_B0] + p[P_B1] * ay + p[P_B2] * ay * ay, y2)
    v = p[P_V]
    if v != 0.0:
        sigma = p[P_SIGMA]
        for i in range(tdc.size):
            x = (theta2 - tdc[i]) % _FOUR_PI
            if x >= 2.0 * math.pi:
                x -= _FOUR_PI
            w -= v * strength[i] * (x / sigma) * math.exp(0.5 - 0.5 * (x / sigma) ** 2)
    return w


@njit(cache=True)
def _ripple(theta1, p):
    return p[P_RIP_A] * math.sin(p[P_RIP_ORDER] * theta1 + p[P_RIP_PHASE])


@njit(cache=True)
def _derivative(x, t, u, c_s, d_s, force, p, tdc, strength, third, dx):
    y1 = x[Y1]
    y2 = x[Y2]
    at = p[P_THIRD_AT] if third else 0.0
    ym = x[Y3] if at == 1.0 else y2  # the shaft's engine-side end: the third inertia when it is between
    t_s = _shaft_torque(x[PHI], y1 - ym, c_s, d_s, p[P_GAP])
    if p[P_COUL] != 0.0:  # Coulomb friction in the coupling, smoothed over P_COUL_V rad/s
        t_s += p[P_COUL] * math.tanh((y1 - ym) / p[P_COUL_V])
    t_dyno = u + _ripple(x[THETA1], p)
    t_dist = p[P_DIST_A] * math.sin(p[P_DIST_W] * t) + p[P_STR_GAIN] * x[XS]
    t_eng = 0.0
    if p[P_ORD_A] != 0.0:  # unmeasured rotation-order torque on one shaft
        if p[P_ORD_ENGINE] != 0.0:
            t_eng = p[P_ORD_A] * math.sin(p[P_ORD_ORDER] * x[THETA2] + p[P_ORD_PHASE])
        else:
            t_dist += p[P_ORD_A] * math.sin(p[P_ORD_ORDER] * x[THETA1] + p[P_ORD_PHASE])
    t_23 = 0.0
    if third:
        if at == 1.0:  # between: the second spring from the third inertia to the engine
            t_23 = p[P_C2] * x[PHI2] + p[P_D2] * (ym - y2)
        elif at == 2.0:  # beyond the dyno
            t_23 = p[P_C2] * x[PHI2] + p[P_D2] * (y1 - x[Y3])
        else:
            t_23 = p[P_C2] * x[PHI2] + p[P_D2] * (y2 - x[Y3])
    dx[PHI] = y1 - ym
    dx[THETA1] = y1
    dx[THETA2] = y2
    if at == 1.0:
        dx[Y1] = (-t_s - t_dyno - t_dist) / p[P_J1]
        dx[Y2] = (t_23 - _engine_torque(x[THETA2], y2, p, tdc, strength) - t_eng) / p[P_J2]
        dx[PHI2] = ym - y2
        dx[Y3] = (t_s - t_23) / p[P_J3]
    elif at == 2.0:
        dx[Y1] = (-t_s - t_dyno - t_dist - t_23) / p[P_J1]
        dx[Y2] = (t_s - _engine_torque(x[THETA2], y2, p, tdc, strength) - t_eng) / p[P_J2]
        dx[PHI2] = y1 - x[Y3]
        dx[Y3] = t_23 / p[P_J3]
    else:
        dx[Y1] = (-t_s - t_dyno - t_dist) / p[P_J1]
        dx[Y2] = (t_s - _engine_torque(x[THETA2], y2, p, tdc, strength) - t_23 - t_eng) / p[P_J2]
        if third:
            dx[PHI2] = y2 - x[Y3]
            dx[Y3] = t_23 / p[P_J3]
        else:
            dx[PHI2] = 0.0
            dx[Y3] = 0.0
    w_s = p[P_STR_W]
    dx[XS] = x[VS]
    dx[VS] = force - 2.0 * p[P_STR_Z] * w_s * x[VS] - w_s * w_s * x[XS]


@njit(cache=True)
def run_plant(x, integral, k_start, k_stop, fs_hz, substeps, p, tdc, strength, third,
              kp, ki, ref, u_test, c_s, d_s, ctrl_noise, force,
              y1_out, y2_out, u_out):
    """Advance the plant over samples ``k_start .. k_stop - 1`` (in place).

    At each sample k the PI law ``u = -(kp e + ki I) + u_test[k]`` with
    ``e = ref[k] - (y1 + ctrl_noise[k])`` and ``I += e / fs`` is evaluated,
    ``y1, y2`` and the acting dyno torque (``u`` + ripple) are recorded, and
    the plant is integrated to the next sample by ``substeps`` RK4 steps with
    ``u``, ``c_s[k]``, ``d_s[k]``, ``force[k]`` held.  Returns the new
    integrator state; ``x`` is updated in place.
    """
    n = x.size
    k1 = np.empty(n)
    k2 = np.empty(n)
    k3 = np.empty(n)
    k4 = np.empty(n)
    tmp = np.empty(n)
    ts = 1.0 / fs_hz
    h = ts / substeps
    for k in range(k_start, k_stop):
        e = ref[k] - (x[Y1] + ctrl_noise[k])
        integral += e * ts
        u = -(kp * e + ki * integral) + u_test[k]
        y1_out[k] = x[Y1]
        y2_out[k] = x[Y2]
        u_out[k] = u + _ripple(x[THETA1], p)
        cs = c_s[k]
        ds = d_s[k]
        f = force[k]
        for s in range(substeps):
            t = k * ts + s * h
            _derivative(x, t, u, cs, ds, f, p, tdc, strength, third, k1)
            for i in range(n):
                tmp[i] = x[i] + 0.5 * h * k1[i]
            _derivative(tmp, t + 0.5 * h, u, cs, ds, f, p, tdc, strength, third, k2)
            for i in range(n):
                tmp[i] = x[i] + 0.5 * h * k2[i]
            _derivative(tmp, t + 0.5 * h, u, cs, ds, f, p, tdc, strength, third, k3)
            for i in range(n):
                tmp[i] = x[i] + h * k3[i]
            _derivative(tmp, t + h, u, cs, ds, f, p, tdc, strength, third, k4)
            for i in range(n):
                x[i] += h / 6.0 * (k1[i] + 2.0 * k2[i] + 2.0 * k3[i] + k4[i])
    return integral


def friction_torque_nm(speed_rad_s: float, b0: float, b1: float, b2: float) -> float:
    """Engine friction torque [Nm] at ``speed_rad_s`` (braking positive)."""
    a = abs(speed_rad_s)
    return math.copysign(b0 + b1 * a + b2 * a * a, speed_rad_s)


def linear_state_matrix(J1: float, J2: float, c_s: float, d_s: float,
                        third: tuple[float, float, float] | None = None, location: str = "engine") -> np.ndarray:
    """State matrix of the linear driveline (no friction, compression or backlash).

    States ``[phi, y1, y2]``, plus ``[phi2, y3]`` when ``third = (J3, c_2, d_2)``: hanging off the engine
    (``location="engine"``), between the shaft and the engine (``"between"``) or off the dyno (``"dyno"``).
    """
    if third is None:
        a = np.zeros((3, 3))
        a[0, 1], a[0, 2] = 1.0, -1.0
        a[1, :3] = [-c_s / J1, -d_s / J1, d_s / J1]
        a[2, :3] = [c_s / J2, d_s / J2, -d_s / J2]
        return a
    J3, c_2, d_2 = third
    # the chain of three inertias as masses m and two springs (i, j, c, d) on speeds [y1, y2, y3]
    springs = {"engine": ((0, 1, c_s, d_s), (1, 2, c_2, d_2)),
               "between": ((0, 2, c_s, d_s), (2, 1, c_2, d_2)),
               "dyno": ((0, 1, c_s, d_s), (0, 2, c_2, d_2))}[location]
    m = (J1, J2, J3)
    a = np.zeros((5, 5))  # states [phi, y1, y2, phi2, y3]: phi, phi2 the twists of the two springs
    speed = {0: 1, 1: 2, 2: 4}
    for k, (i, j, c, d) in enumerate(springs):
        tw = 0 if k == 0 else 3
        a[tw, speed[i]], a[tw, speed[j]] = 1.0, -1.0
        for node, sign in ((i, -1.0), (j, 1.0)):  # torque c tw + d (yi - yj) leaves i, enters j
            r = speed[node]
            a[r, tw] += sign * c / m[node]
            a[r, speed[i]] += sign * d / m[node]
            a[r, speed[j]] -= sign * d / m[node]
    return a


def linear_modes(J1: float, J2: float, c_s: float, d_s: float,
                 third: tuple[float, float, float] | None = None, location: str = "engine") -> list[dict[str, float]]:
    """Oscillatory modes ``{f_hz, zeta}`` of the linear driveline, lowest first.

    Notes
    -----
    For each eigenvalue ``s`` with ``Im(s) > 0``: ``f = |s| / 2 pi`` (undamped
    natural frequency) and ``zeta = -Re(s) / |s|``.  Overdamped pairs (real
    eigenvalues) are not reported.
    """
    eig = np.linalg.eigvals(linear_state_matrix(J1, J2, c_s, d_s, third, location))
    modes = [
        {"f_hz": float(abs(s) / (2 * math.pi)), "zeta": float(-s.real / abs(s))}
        for s in eig if s.imag > 1e-9 * max(1.0, abs(s))
    ]
    return sorted(modes, key=lambda m: m["f_hz"])
