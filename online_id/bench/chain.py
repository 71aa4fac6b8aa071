"""A torsional network of rigid inertias joined by compliant shafts, couplings and gear stages.

The network is a tree (a chain, possibly with side branches) of ``n`` rigid elements, each on its
own shaft, with angle ``theta_i`` and speed ``omega_i`` measured on that shaft.  A :class:`Joint`
connects element ``a`` to element ``b`` through an ideal (massless, lossless) gear of ratio ``r``
(``omega_a / omega_b`` at rest) followed by a compliance on ``b``'s side.

Notes
-----
The twist of a joint and its torque, acting on ``b`` and reacted on ``a``::

    delta   = theta_a / r - theta_b
    tau     = c * dz(delta) + d * delta' * [in contact] + F_c * tanh(delta' / eps)
    J_b omega_b' += tau,      J_a omega_a' -= tau / r

where ``dz`` is the dead zone of a backlash of total width ``g`` (``dz(x) = x`` without one).  The
gear passes the power ``tau * omega_a / r`` it takes on ``a`` to ``b`` unchanged.  Linearised
(no gap, no dry friction) the network is ``M theta'' + D theta' + K theta = f`` with
``M = diag(J)`` and, for each joint with ``g = e_a / r - e_b``, ``K += c g g^T`` and
``D += d g g^T``; :meth:`Network.modes` gives its modes from the eigenvalues of the state matrix.

:func:`integrate` steps the nonlinear network, its motors (first-order torque actuators, an
optional PI speed loop at a controller rate, a PRBS added to the command), an engine torque that
is a function of the crank angle (and speed) and external torques, with the classical fourth-order
Runge-Kutta scheme at a fixed internal step, and stores the state at a lower rate.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numba import njit

from online_id.errors import ConfigError

DRY_FRICTION_EPS = 0.01
"""Speed [rad/s] over which dry friction changes sign (``tanh(v / eps)``); small against the twist rates."""


@dataclass(frozen=True)
class Joint:
    """A compliant connection of element ``a`` to element ``b`` through a gear of ``ratio`` (see module notes)."""

    a: int
    b: int
    stiffness: float
    damping: float
    ratio: float = 1.0
    gap_rad: float = 0.0
    coulomb_nm: float = 0.0

    def __post_init__(self) -> None:
        if self.stiffness <= 0 or self.damping < 0 or self.ratio <= 0 or self.gap_rad < 0 or self.coulomb_nm < 0:
            raise ConfigError(f"joint {self.a}-{self.b}: stiffness and ratio must be > 0, damping, gap and "
                              f"coulomb >= 0 (got {self})")


@dataclass(frozen=True)
class Mode:
    """One oscillating mode of the linearised network: the pole ``s`` with ``Im(s) > 0``."""

    freq_hz: float
    """Undamped natural frequency ``|s| / 2 pi``."""
    damped_hz: float
    """Damped natural frequency ``Im(s) / 2 pi``."""
    zeta: float
    """Damping ratio ``-Re(s) / |s|``."""


@dataclass(frozen=True)
class Network:
    """Rigid elements (``inertia`` [kg m^2], ``names``) joined into a tree by ``joints``."""

    inertia: tuple[float, ...]
    joints: tuple[Joint, ...]
    names: tuple[str, ...] = field(default=())

    def __post_init__(self) -> None:
        n = len(self.inertia)
        if n < 1 or any(j <= 0 for j in self.inertia):
            raise ConfigError(f"network: inertias must be > 0 (got {self.inertia})")
        if len(self.joints) != n - 1:
            raise ConfigError(f"network: {n} elements need {n - 1} joints to form a tree (got {len(self.joints)})")
        if self.names and len(self.names) != n:
            raise ConfigError(f"network: {n} elements but {len(self.names)} names")
        parent = list(range(n))

        def root(i: int) -> int:
            while parent[i] != i:
                i = parent[i]
            return i

        for jt in self.joints:
            if not (0 <= jt.a < n and 0 <= jt.b < n) or root(jt.a) == root(jt.b):
                raise ConfigError(f"network: joint {jt.a}-{jt.b} leaves the elements 0..{n - 1} or closes a loop")
            parent[root(jt.a)] = root(jt.b)

    @property
    def size(self) -> int:
        return len(self.inertia)

    def name(self, i: int) -> str:
        return self.names[i] if self.names else f"element{i}"

    def index(self, name: str) -> int:
        return list(self.names).index(name)

    def _joint_vectors(self) -> list[tuple[Joint, np.ndarray]]:
        out = []
        for jt in self.joints:
            g = np.zeros(self.size)
            g[jt.a] += 1.0 / jt.ratio
            g[jt.b] -= 1.0
            out.append((jt, g))
        return out

    def mass_matrix(self) -> np.ndarray:
        return np.diag(np.asarray(self.inertia, dtype=float))

    def stiffness_matrix(self) -> np.ndarray:
        return sum((jt.stiffness * np.outer(g, g) for jt, g in self._joint_vectors()), np.zeros((self.size,) * 2))

    def damping_matrix(self) -> np.ndarray:
        return sum((jt.damping * np.outer(g, g) for jt, g in self._joint_vectors()), np.zeros((self.size,) * 2))

    def rates(self, reference: int = 0) -> np.ndarray:
        """Speed of every element over the speed of ``reference`` when the network turns rigidly."""
        rate = np.full(self.size, np.nan)
        rate[reference] = 1.0
        for _ in range(self.size):
            for jt in self.joints:  # omega_b = omega_a / ratio in the rigid motion
                if np.isnan(rate[jt.b]) and not np.isnan(rate[jt.a]):
                    rate[jt.b] = rate[jt.a] / jt.ratio
                elif np.isnan(rate[jt.a]) and not np.isnan(rate[jt.b]):
                    rate[jt.a] = rate[jt.b] * jt.ratio
        return rate

    def reflected_inertia(self, reference: int) -> float:
        """The network's inertia seen on the shaft of ``reference`` (rigid motion, kinetic energy)."""
        rate = self.rates(reference)
        return float(np.sum(np.asarray(self.inertia) * rate ** 2))

    def modes(self) -> list[Mode]:
        """The oscillating modes of the free linearised network, by increasing undamped frequency."""
        m_inv = np.diag(1.0 / np.asarray(self.inertia, dtype=float))
        n = self.size
        a = np.zeros((2 * n, 2 * n))
        a[:n, n:] = np.eye(n)
        a[n:, :n] = -m_inv @ self.stiffness_matrix()
        a[n:, n:] = -m_inv @ self.damping_matrix()
        s = np.linalg.eigvals(a)
        s = s[(s.imag > 1e-6 * max(1.0, float(np.max(np.abs(s)))))]
        modes = [Mode(float(abs(p)) / (2 * np.pi), float(p.imag) / (2 * np.pi), float(-p.real / abs(p))) for p in s]
        return sorted(modes, key=lambda m: m.freq_hz)

    def undamped_hz(self) -> np.ndarray:
        """Natural frequencies of the undamped network from ``K v = w^2 M v`` (the rigid mode left out)."""
        from scipy.linalg import eigh

        w2 = eigh(self.stiffness_matrix(), self.mass_matrix(), eigvals_only=True)
        w2 = w2[w2 > 1e-9 * max(1.0, float(np.max(w2)))]
        return np.sqrt(np.sort(w2)) / (2 * np.pi)

    def joint_arrays(self) -> tuple[np.ndarray, ...]:
        """The joints as arrays for :func:`integrate`: a, b, stiffness, damping, ratio, gap, coulomb."""
        js = self.joints
        return (np.array([j.a for j in js], dtype=np.int64), np.array([j.b for j in js], dtype=np.int64),
                np.array([j.stiffness for j in js]), np.array([j.damping for j in js]),
                np.array([j.ratio for j in js]), np.array([j.gap_rad for j in js]),
                np.array([j.coulomb_nm for j in js]))


@njit(cache=True)
def _joint_torques(theta, omega, ja, jb, jk, jd, jr, jgap, jcou, out):
    """Torque of every joint on its element ``b`` (see module notes) into ``out``."""
    for j in range(ja.shape[0]):
        rel = theta[ja[j]] / jr[j] - theta[jb[j]]
        relv = omega[ja[j]] / jr[j] - omega[jb[j]]
        if jgap[j] > 0.0:
            half = 0.5 * jgap[j]
            if rel > half:
                tau = jk[j] * (rel - half) + jd[j] * relv
            elif rel < -half:
                tau = jk[j] * (rel + half) + jd[j] * relv
            else:
                tau = 0.0
        else:
            tau = jk[j] * rel + jd[j] * relv
        if jcou[j] > 0.0:
            tau += jcou[j] * np.tanh(relv / DRY_FRICTION_EPS)
        out[j] = tau


@njit(cache=True)
def _table(table, angle):
    """Linear interpolation of a table sampled uniformly over one period of ``4 pi`` at ``angle``."""
    n = table.shape[0]
    x = (angle / (4.0 * np.pi)) % 1.0 * n
    i = int(x)
    f = x - i
    if i >= n:
        i = n - 1
    return table[i] * (1.0 - f) + table[(i + 1) % n] * f


@njit(cache=True)
def _derivative(t, x, cmd, n, m, inertia, ja, jb, jk, jd, jr, jgap, jcou, eng_el, eng_gas, eng_mass, eng_fric,
                ord_el, ord_k, ord_amp, ord_ph, src_el, src_f, src_dt, mot_el, mot_tau, mot_sens_tau, tj, dx):
    theta = x[:n]
    omega = x[n:2 * n]
    torque = np.zeros(n)
    _joint_torques(theta, omega, ja, jb, jk, jd, jr, jgap, jcou, tj)
    for j in range(ja.shape[0]):
        torque[jb[j]] += tj[j]
        torque[ja[j]] -= tj[j] / jr[j]
    if eng_el >= 0:
        th = theta[eng_el]
        w = omega[eng_el]
        torque[eng_el] += _table(eng_gas, th) + _table(eng_mass, th) * w * w
        torque[eng_el] -= eng_fric[0] * np.tanh(w / DRY_FRICTION_EPS) + eng_fric[1] * w
    for k in range(ord_el.shape[0]):
        torque[ord_el[k]] += ord_amp[k] * np.sin(ord_k[k] * theta[ord_el[k]] + ord_ph[k])
    if src_el.shape[0] > 0:
        pos = t / src_dt
        i = int(pos)
        if i >= src_f.shape[0] - 1:
            i = src_f.shape[0] - 2
        f = pos - i
        for s in range(src_el.shape[0]):
            torque[src_el[s]] += src_f[i, s] * (1.0 - f) + src_f[i + 1, s] * f
    for q in range(m):
        tact = x[2 * n + q]
        torque[mot_el[q]] += tact
        dx[2 * n + q] = (cmd[q] - tact) / mot_tau[q]
        dx[2 * n + m + q] = (tact - x[2 * n + m + q]) / mot_sens_tau[q]
    for i in range(n):
        dx[i] = omega[i]
        dx[n + i] = torque[i] / inertia[i]


@njit(cache=True)
def _integrate(n_steps, h, store_every, ctrl_every, x0, inertia, ja, jb, jk, jd, jr, jgap, jcou, eng_el, eng_gas,
               eng_mass, eng_fric, ord_el, ord_k, ord_amp, ord_ph, src_el, src_f, src_dt, mot_el, mot_tau,
               mot_sens_tau, mot_bias, mot_pi_el, mot_kp, mot_ki, set_t, set_w, mot_prbs, prbs_bits, prbs_bit_s,
               ctrl_noise, out_x, out_cmd, out_joint):
    n = inertia.shape[0]
    m = mot_el.shape[0]
    x = x0.copy()
    k1 = np.zeros_like(x)
    k2 = np.zeros_like(x)
    k3 = np.zeros_like(x)
    k4 = np.zeros_like(x)
    xt = np.zeros_like(x)
    tj = np.zeros(ja.shape[0])
    cmd = np.zeros(m)
    integ = np.zeros(m)
    tc = h * ctrl_every
    nbits = prbs_bits.shape[0]
    for step in range(n_steps):
        t = step * h
        if step % ctrl_every == 0:
            c = step // ctrl_every
            prbs = prbs_bits[int(t / prbs_bit_s) % nbits] if nbits > 0 else 0.0
            for q in range(m):
                u = mot_bias[q] + mot_prbs[q] * prbs
                if mot_pi_el[q] >= 0:
                    target = np.interp(t, set_t, set_w[:, q])
                    err = target - (x[n + mot_pi_el[q]] + ctrl_noise[c, q])
                    integ[q] += mot_ki[q] * err * tc
                    u += mot_kp[q] * err + integ[q]
                cmd[q] = u
        if step % store_every == 0:
            r = step // store_every
            out_x[r, :] = x
            out_cmd[r, :] = cmd
            _joint_torques(x[:n], x[n:2 * n], ja, jb, jk, jd, jr, jgap, jcou, tj)
            out_joint[r, :] = tj
        _derivative(t, x, cmd, n, m, inertia, ja, jb, jk, jd, jr, jgap, jcou, eng_el, eng_gas, eng_mass, eng_fric,
                    ord_el, ord_k, ord_amp, ord_ph, src_el, src_f, src_dt, mot_el, mot_tau, mot_sens_tau, tj, k1)
        xt[:] = x + 0.5 * h * k1
        _derivative(t + 0.5 * h, xt, cmd, n, m, inertia, ja, jb, jk, jd, jr, jgap, jcou, eng_el, eng_gas, eng_mass,
                    eng_fric, ord_el, ord_k, ord_amp, ord_ph, src_el, src_f, src_dt, mot_el, mot_tau, mot_sens_tau,
                    tj, k2)
        xt[:] = x + 0.5 * h * k2
        _derivative(t + 0.5 * h, xt, cmd, n, m, inertia, ja, jb, jk, jd, jr, jgap, jcou, eng_el, eng_gas, eng_mass,
                    eng_fric, ord_el, ord_k, ord_amp, ord_ph, src_el, src_f, src_dt, mot_el, mot_tau, mot_sens_tau,
                    tj, k3)
        xt[:] = x + h * k3
        _derivative(t + h, xt, cmd, n, m, inertia, ja, jb, jk, jd, jr, jgap, jcou, eng_el, eng_gas, eng_mass,
                    eng_fric, ord_el, ord_k, ord_amp, ord_ph, src_el, src_f, src_dt, mot_el, mot_tau, mot_sens_tau,
                    tj, k4)
        x += (h / 6.0) * (k1 + 2.0 * k2 + 2.0 * k3 + k4)
    r = n_steps // store_every
    if r < out_x.shape[0]:
        out_x[r, :] = x
        out_cmd[r, :] = cmd
        _joint_torques(x[:n], x[n:2 * n], ja, jb, jk, jd, jr, jgap, jcou, tj)
        out_joint[r, :] = tj
