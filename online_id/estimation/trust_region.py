"""Unbounded trust-region least squares with its subproblem solved through a QR factorisation.

Notes
-----
:func:`trust_region_lsq` is ``scipy.optimize.least_squares(fun, x0, jac=jac, method="trf",
x_scale="jac")`` for a problem without bounds and with the linear loss: the same iteration
(scipy 1.17's ``trf_no_bounds``: the trust-region subproblem solved exactly by Moré's method,
the radius updated from the ratio of actual to predicted reduction, the variables scaled by the
Jacobian's column norms, the same three stopping tests and termination codes), with one change in how
the subproblem's data are computed. scipy takes a thin SVD of the scaled :math:`m \\times n`
Jacobian :math:`J_h = U S V^T` at every step, of which the step needs only :math:`S`, :math:`V` and
:math:`U^T f`. Here the augmented matrix :math:`[J_h \\; f]` is reduced by one Householder QR
(LAPACK ``dgeqrt``), :math:`[J_h \\; f] = Q [R \\; q]`, and the SVD is taken of the
:math:`n \\times n` triangle, :math:`R = U_R S V^T`: then :math:`J_h = (Q U_R) S V^T` and
:math:`U^T f = U_R^T q_{1:n}`. Both factorisations are backward stable, so the two give the same
singular values and projections to rounding (relative differences of order :math:`10^{-15}`, checked in
``tests/test_trust_region.py``), and the iterations the same steps; the QR never forms an
:math:`m \\times n` factor and costs a fifth to a third of the SVD for the tall Jacobians of the PEM window
fits (:math:`m` in the thousands, :math:`n` 10-30).

Reference: J. J. Moré, "The Levenberg-Marquardt algorithm: implementation and theory", in
*Numerical Analysis*, ed. G. A. Watson, Lecture Notes in Mathematics 630, Springer, 1977, pp. 105-116;
the iteration follows scipy's implementation (BSD licence) of M. A. Branch, T. F. Coleman and Y. Li,
SIAM J. Sci. Comput. 21 (1999) 1-23, without bounds.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from numpy.linalg import norm
from scipy.linalg import lapack, svd

EPS = np.finfo(float).eps
QR_BLOCK = 8  # dgeqrt's block size (fastest of 2-12 for 2,500-10,000 x 21-31 on AMD EPYC)

MESSAGES = {
    0: "The maximum number of function evaluations is exceeded.",
    1: "`gtol` termination condition is satisfied.",
    2: "`ftol` termination condition is satisfied.",
    3: "`xtol` termination condition is satisfied.",
    4: "Both `ftol` and `xtol` termination conditions are satisfied.",
}


@dataclass(frozen=True)
class LsqResult:
    """What :func:`trust_region_lsq` found (the fields of scipy's ``OptimizeResult`` it is used for)."""

    x: np.ndarray
    cost: float
    status: int
    nfev: int
    njev: int

    @property
    def message(self) -> str:
        return MESSAGES[self.status]


def subproblem_data(J_h: np.ndarray, f: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(s, V, uf)`` of the thin SVD ``J_h = U diag(s) V^T`` with ``uf = U^T f``, through a QR of ``[J_h f]``.

    Needs ``m >= n`` (``J_h`` is ``m x n``).
    """
    m, n = J_h.shape
    aug = np.empty((m, n + 1), order="F")
    aug[:, :n] = J_h
    aug[:, n] = f
    # the compact-WY Householder QR with small blocks: 1.3-1.9 times as fast as dgeqrf on these tall matrices
    qr, _, info = lapack.dgeqrt(min(QR_BLOCK, n + 1), aug, overwrite_a=1)
    if info != 0:
        raise np.linalg.LinAlgError(f"QR of the Jacobian failed (LAPACK dgeqrt info {info})")
    U_r, s, Vt = svd(np.triu(qr[:n, :n]), check_finite=False)
    return s, Vt.T, U_r.T @ qr[:n, n]


def _solve_subproblem(m: int, uf: np.ndarray, s: np.ndarray, V: np.ndarray, Delta: float, initial_alpha: float,
                      rtol: float = 0.01, max_iter: int = 10) -> tuple[np.ndarray, float]:
    """Moré's trust-region step from the SVD data (scipy's ``solve_lsq_trust_region``) of an ``m``-row Jacobian
    with at least as many rows as columns (:func:`trust_region_lsq` refuses fewer)."""

    def phi_and_derivative(alpha):
        denom = s**2 + alpha
        p_norm = norm(suf / denom)
        return p_norm - Delta, -np.sum(suf**2 / denom**3) / p_norm

    suf = s * uf
    full_rank = s[-1] > EPS * m * s[0]
    if full_rank:
        p = -V.dot(uf / s)
        if norm(p) <= Delta:
            return p, 0.0
    alpha_upper = norm(suf) / Delta
    if full_rank:
        phi, phi_prime = phi_and_derivative(0.0)
        alpha_lower = -phi / phi_prime
    else:
        alpha_lower = 0.0
    if not full_rank and initial_alpha == 0:
        alpha = max(0.001 * alpha_upper, (alpha_lower * alpha_upper) ** 0.5)
    else:
        alpha = initial_alpha
    for _ in range(max_iter):
        if alpha < alpha_lower or alpha > alpha_upper:
            alpha = max(0.001 * alpha_upper, (alpha_lower * alpha_upper) ** 0.5)
        phi, phi_prime = phi_and_derivative(alpha)
        if phi < 0:
            alpha_upper = alpha
        ratio = phi / phi_prime
        alpha_lower = max(alpha_lower, alpha - ratio)
        alpha -= (phi + Delta) * ratio / Delta
        if np.abs(phi) < rtol * Delta:
            break
    p = -V.dot(suf / (s**2 + alpha))
    p *= Delta / norm(p)
    return p, alpha


def _termination(dF: float, F: float, dx_norm: float, x_norm: float, ratio: float, ftol: float,
                 xtol: float) -> int | None:
    ftol_satisfied = dF < ftol * F and ratio > 0.25
    xtol_satisfied = dx_norm < xtol * (xtol + x_norm)
    if ftol_satisfied and xtol_satisfied:
        return 4
    if ftol_satisfied:
        return 2
    if xtol_satisfied:
        return 3
    return None


def trust_region_lsq(fun: Callable[[np.ndarray], np.ndarray], jac: Callable[[np.ndarray], np.ndarray],
                     x0: np.ndarray, *, ftol: float = 1e-8, xtol: float = 1e-8, gtol: float = 1e-8,
                     max_nfev: int | None = None) -> LsqResult:
    """Minimise ``0.5 ||fun(x)||^2`` from ``x0`` (see module notes: scipy's unbounded ``trf`` with ``x_scale="jac"``).

    ``fun`` may return non-finite residuals at a trial point (the step is refused and the radius
    shrunk); at ``x0`` they must be finite (``ValueError`` otherwise, as scipy). Needs at least as
    many residuals as variables.
    """
    x = np.atleast_1d(np.asarray(x0, dtype=float)).copy()
    f = np.asarray(fun(x), dtype=float)
    if not np.all(np.isfinite(f)):
        raise ValueError("Residuals are not finite in the initial point.")
    J = np.asarray(jac(x), dtype=float)
    m, n = J.shape
    if m < n:
        raise ValueError(f"{m} residuals for {n} variables: the QR subproblem needs m >= n")
    nfev = njev = 1
    if max_nfev is None:
        max_nfev = 100 * n
    cost = 0.5 * np.dot(f, f)
    g = J.T.dot(f)
    scale_inv = np.sum(J**2, axis=0) ** 0.5
    scale_inv[scale_inv == 0] = 1
    scale = 1 / scale_inv
    Delta = norm(x * scale_inv)
    if Delta == 0:
        Delta = 1.0
    alpha = 0.0
    status = None
    while True:
        if norm(g, ord=np.inf) < gtol:
            status = 1
        if status is not None or nfev == max_nfev:
            break
        g_h = scale * g
        J_h = J * scale
        s, V, uf = subproblem_data(J_h, f)
        actual_reduction = -1.0
        while actual_reduction <= 0 and nfev < max_nfev:
            step_h, alpha = _solve_subproblem(m, uf, s, V, Delta, alpha)
            Js = J_h.dot(step_h)
            predicted_reduction = -(0.5 * np.dot(Js, Js) + np.dot(step_h, g_h))
            step = scale * step_h
            x_new = x + step
            f_new = np.asarray(fun(x_new), dtype=float)
            nfev += 1
            step_h_norm = norm(step_h)
            if not np.all(np.isfinite(f_new)):
                Delta = 0.25 * step_h_norm
                continue
            cost_new = 0.5 * np.dot(f_new, f_new)
            actual_reduction = cost - cost_new
            if predicted_reduction > 0:
                with np.errstate(over="ignore"):  # a vanishing predicted reduction: the ratio is +-inf
                    ratio = actual_reduction / predicted_reduction
            elif predicted_reduction == actual_reduction == 0:
                ratio = 1
            else:
                ratio = 0
            Delta_new = Delta
            if ratio < 0.25:
                Delta_new = 0.25 * step_h_norm
            elif ratio > 0.75 and step_h_norm > 0.95 * Delta:
                Delta_new = 2.0 * Delta
            status = _termination(actual_reduction, cost, norm(step), norm(x), ratio, ftol, xtol)
            if status is not None:
                break
            alpha *= Delta / Delta_new
            Delta = Delta_new
        if actual_reduction > 0:
            x, f, cost = x_new, f_new, cost_new
            J = np.asarray(jac(x), dtype=float)
            njev += 1
            g = J.T.dot(f)
            scale_inv = np.maximum(np.sum(J**2, axis=0) ** 0.5, scale_inv)
            scale = 1 / scale_inv
    return LsqResult(x=x, cost=float(cost), status=0 if status is None else int(status), nfev=nfev, njev=njev)
