"""ARMAX model with extra regressors: the baseline and every augmented model.

Notes
-----
With the input aligned for a sensor delay of ``delay`` samples
(:math:`u_d(t) = u(t - d)`, :math:`d < 0` shifts the input forward), the
model is

.. math::

    A(q) y(t) = B(q) u_d(t) + \\sum_j g_j x_j(t) + k + C(q) e(t)

where the :math:`x_j` are the columns that the effects add (sin/cos of a
shaft angle, a dead-zone feature of the torsion, the sign of the velocity,
...), each already lagged.  Written with the equation error
:math:`v(t) = y(t) - \\varphi(t)^T \\eta`, :math:`\\eta = [a, b, g, k]`, the
one-step prediction error is :math:`\\varepsilon = v / C` and its gradient is

.. math::

    \\partial \\varepsilon / \\partial \\eta = -\\varphi / C, \\qquad
    \\partial \\varepsilon / \\partial c_k = -\\varepsilon(t - k) / C,

so prediction-error minimisation runs as in :mod:`online_id.estimation.pem`
(trust-region Gauss-Newton, ``C`` kept minimum phase) starting from the
least-squares (``C = 1``) estimate.  Columns that depend on the output
(Coulomb friction on the output speed) use the measured output in the
predictor and the simulated output in a simulation.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import Protocol

import numpy as np
from scipy.signal import lfilter, lfiltic

from online_id.estimation.pem import reflect_unstable_roots
from online_id.diagnose.data import DiagnoseData, Split
from online_id.estimation.trust_region import trust_region_lsq
from online_id.errors import EstimationError


class Term(Protocol):
    """An effect that adds regressor columns to the model."""

    kind: str

    def columns(self, data: DiagnoseData, lags: np.ndarray) -> np.ndarray:
        """Regressor columns ``(n, m)`` on the measured data."""

    def output_static(self) -> tuple[object, np.ndarray] | None:
        """``(f, lags)`` if the columns are ``f(y(t - lag))`` of the output, else ``None``."""


@dataclass(frozen=True)
class Structure:
    """Orders, sensor-delay alignment and extra terms of a model."""

    na: int
    nb: int
    nc: int
    nk: int = 1
    delay: int = 0
    terms: tuple = field(default_factory=tuple)

    def __post_init__(self) -> None:
        if self.na < 0 or self.nb < 1 or self.nc < 0 or self.nk < 0:
            raise EstimationError(f"bad model orders na={self.na} nb={self.nb} nc={self.nc} nk={self.nk}")

    @property
    def max_lag(self) -> int:
        return max(self.na, self.nk + self.nb - 1, self.nc, 1)

    @property
    def input_lags(self) -> np.ndarray:
        return self.nk + np.arange(self.nb)

    def with_term(self, term: object) -> "Structure":
        return replace(self, terms=self.terms + (term,))


@dataclass(frozen=True)
class AugmentedFit:
    """A fitted model: ``eta = [a, b, g, k]`` and ``C``.

    Attributes
    ----------
    structure
        The model structure.
    eta
        Parameters of the equation error.
    C
        Noise polynomial (leading 1).
    n_term_cols
        Number of columns each term added, in order.
    V_est
        Mean squared one-step error on the estimation samples.
    split
        Estimation and held-out samples (the fit used the estimation samples
        from ``max_lag`` on).
    """

    structure: Structure
    eta: np.ndarray
    C: np.ndarray
    n_term_cols: tuple[int, ...]
    V_est: float
    split: Split

    @property
    def A(self) -> np.ndarray:
        return np.concatenate(([1.0], self.eta[: self.structure.na]))

    @property
    def n_params(self) -> int:
        return int(self.eta.size + self.C.size - 1)

    def term_params(self, i: int) -> np.ndarray:
        """Fitted coefficients of term ``i``."""
        s = self.structure
        start = s.na + s.nb + sum(self.n_term_cols[:i])
        return self.eta[start:start + self.n_term_cols[i]]

    def errors(self, data: DiagnoseData) -> np.ndarray:
        """One-step prediction errors over the whole record (filters from sample 0)."""
        phi, _ = regressors(data, self.structure)
        return lfilter([1.0], self.C, data.y - phi @ self.eta)

    def simulate(self, data: DiagnoseData, start: int, stop: int | None = None) -> np.ndarray:
        """Simulated output from sample ``start`` on (to ``stop``), measured output elsewhere.

        Roots of ``A`` outside the unit circle (an equation-error model may
        place one near the Nyquist frequency) are reflected inside for the
        simulation, which keeps the amplitude response of ``1/A``.
        """
        return self.simulate_windows(data, [(start, data.y.size if stop is None else stop)])

    def simulate_windows(self, data: DiagnoseData, wins: list[tuple[int, int]]) -> np.ndarray:
        """Simulation over each window ``(w0, w1)``, started from the measured output before ``w0``."""
        s = self.structure
        phi, _ = regressors(data, s)
        y = data.y
        A = reflect_unstable_roots(self.A, 1.0)
        a = A[1:]
        # exogenous part of phi @ eta (everything but the output lags and output-dependent terms)
        mask = np.ones(self.eta.size, dtype=bool)
        mask[: s.na] = False
        dependent = []
        col = s.na + s.nb
        for term, m in zip(s.terms, self.n_term_cols):
            stat = term.output_static()
            if stat is not None:
                mask[col:col + m] = False
                dependent.append((stat[0], np.asarray(stat[1], dtype=int), self.eta[col:col + m]))
            # columns that predict a disturbance from the measured residual's past: no part of a simulation
            mask[col + m - getattr(term, "predictor_cols", 0):col + m] = False
            col += m
        w = phi[:, mask] @ self.eta[mask]
        out = y.astype(float).copy()
        for w0, w1 in wins:
            if not dependent:
                # y(t) = -sum a_i y(t-i) + w(t): a filter started from the measured output
                if s.na == 0:
                    out[w0:w1] = w[w0:w1]
                else:
                    past = y[max(w0 - s.na, 0):w0][::-1].astype(float)
                    zi = lfiltic([1.0], A, np.pad(past, (0, s.na - past.size)))
                    out[w0:w1] = lfilter([1.0], A, w[w0:w1], zi=zi)[0]
            else:
                sim = y.astype(float).copy()
                for t in range(w0, w1):
                    acc = w[t]
                    for i in range(s.na):
                        if t - 1 - i >= 0:
                            acc -= a[i] * sim[t - 1 - i]
                    for f, lags, g in dependent:
                        idx = t - lags
                        vals = np.where(idx >= 0, sim[np.maximum(idx, 0)], 0.0)
                        acc += float(f(vals) @ g)
                    sim[t] = acc
                out[w0:w1] = sim[w0:w1]
        return out


def windows(runs: list[tuple[int, int]], horizon: int | None) -> list[tuple[int, int]]:
    """Each run ``(a, b)`` cut into windows of ``horizon`` samples (``None``: the run whole)."""
    out = []
    for a, b in runs:
        step = (b - a) if horizon is None else max(1, int(horizon))
        out += [(w, min(w + step, b)) for w in range(a, b, step)]
    return out


def align_input(u: np.ndarray, delay: int) -> np.ndarray:
    """Input shifted by ``delay`` samples (held at the ends)."""
    if delay == 0:
        return u
    if delay > 0:
        return np.concatenate((np.full(delay, u[0]), u[:-delay]))
    d = -delay
    return np.concatenate((u[d:], np.full(d, u[-1])))


def lag_matrix(x: np.ndarray, lags: np.ndarray) -> np.ndarray:
    """Columns ``x(t - lag)``, zero before the start."""
    lags = np.asarray(lags, dtype=int)
    idx = np.arange(x.size)[:, None] - lags[None, :]
    out = x[np.maximum(idx, 0)]
    out[idx < 0] = 0.0
    return out


def regressors(data: DiagnoseData, s: Structure) -> tuple[np.ndarray, tuple[int, ...]]:
    """Full-length regressor matrix ``[-y lags, u lags, term columns, 1]``."""
    u = align_input(data.u, s.delay)
    cols = [-lag_matrix(data.y, np.arange(1, s.na + 1)), lag_matrix(u, s.input_lags)]
    widths = []
    for term in s.terms:
        x = np.asarray(term.columns(data, s.input_lags), dtype=float)
        x = x.reshape(data.y.size, -1)
        cols.append(x)
        widths.append(x.shape[1])
    cols.append(np.ones((data.y.size, 1)))
    return np.hstack(cols), tuple(widths)


def as_split(data: DiagnoseData, split: Split | int) -> Split:
    """A :class:`Split`; an integer ``n_est`` means the first ``n_est`` samples estimate."""
    if isinstance(split, Split):
        return split
    return Split(len(data), int(split) / len(data))


def fit_structure(data: DiagnoseData, s: Structure, split: Split | int, *,
                  C_fixed: np.ndarray | None = None, max_iter: int = 40) -> AugmentedFit:
    """Fit a structure on the estimation samples of ``split`` (criterion from ``max_lag``).

    Parameters
    ----------
    data
        The record.
    s
        Model structure.
    split
        Estimation and held-out samples (an integer: the first ``n`` samples).
    C_fixed
        If given, ``C`` is held at this polynomial and ``eta`` follows by
        least squares on the ``1/C``-filtered equation error (fast; used in
        parameter searches).  Otherwise ``nc = s.nc`` and PEM is run.
    max_iter
        Maximum residual evaluations of the PEM optimiser.
    """
    split = as_split(data, split)
    phi, widths = regressors(data, s)
    t0 = s.max_lag + max(abs(s.delay), 0)
    rows = split.est_rows(t0)
    if rows.size <= 2 * phi.shape[1]:
        raise EstimationError(f"{data.source}: too few estimation samples ({rows.size}) for "
                              f"{phi.shape[1]} parameters")
    end = int(rows[-1]) + 1  # the filters are causal: nothing after the last estimation sample counts
    phi, y = phi[:end], data.y[:end]
    scale = np.maximum(np.sqrt(np.mean(phi[rows] ** 2, axis=0)), 1e-300)
    if C_fixed is not None:
        C = np.asarray(C_fixed, dtype=float)
        eta = _ls(lfilter([1.0], C, phi, axis=0)[rows] / scale, lfilter([1.0], C, y)[rows]) / scale
        eps = lfilter([1.0], C, y - phi @ eta)[rows]
        return AugmentedFit(s, eta, C, widths, float(np.mean(eps**2)), split)
    eta0 = _ls(phi[rows] / scale, y[rows]) / scale
    if s.nc == 0:
        eps = (y - phi @ eta0)[rows]
        return AugmentedFit(s, eta0, np.ones(1), widths, float(np.mean(eps**2)), split)
    problem = _Pem(phi, y, s.nc, rows, scale)
    x0 = np.concatenate((eta0 * scale, np.zeros(s.nc)))
    res = trust_region_lsq(problem.residuals, problem.jacobian, x0, ftol=1e-7, xtol=1e-7, gtol=1e-7,
                           max_nfev=max_iter)
    x = problem.stable(res.x)
    eta = x[: phi.shape[1]] / scale
    C = np.concatenate(([1.0], x[phi.shape[1]:]))
    eps = problem.residuals(x)
    if not np.all(np.isfinite(eps)):
        raise EstimationError(f"{data.source}: the prediction-error fit diverged")
    return AugmentedFit(s, eta, C, widths, float(np.mean(eps**2)), split)


def fit_extension(data: DiagnoseData, cur: AugmentedFit, term: object, split: Split | int) -> AugmentedFit:
    """``cur`` with one more term, fitted with ``A``, ``B``, ``C`` and the older terms held.

    Only the new term's coefficients and the constant are estimated: by least
    squares on the ``1/C``-filtered equation error of ``cur``.  Refitting the
    whole model for a disturbance term lets the least-squares ``A`` move (on
    the benches it moved a root at the Nyquist frequency from 1.02 to 1.05),
    which changed the simulation far more than the term did: a true effect
    that lowers the one-step error could then lower the simulation fit.
    """
    split = as_split(data, split)
    s = cur.structure.with_term(term)
    phi, widths = regressors(data, s)
    k0 = cur.eta.size - 1  # everything of cur but its constant
    rows = split.est_rows(s.max_lag + max(abs(s.delay), 0))
    end = int(rows[-1]) + 1
    target = lfilter([1.0], cur.C, data.y[:end] - phi[:end, :k0] @ cur.eta[:k0])[rows]
    X = lfilter([1.0], cur.C, phi[:end, k0:], axis=0)[rows]
    scale = np.maximum(np.sqrt(np.mean(X**2, axis=0)), 1e-300)
    g = _ls(X / scale, target) / scale
    eta = np.concatenate((cur.eta[:k0], g))
    eps = target - X @ g
    return AugmentedFit(s, eta, cur.C, widths, float(np.mean(eps**2)), split)


def _ls(phi: np.ndarray, y: np.ndarray) -> np.ndarray:
    eta, *_ = np.linalg.lstsq(phi, y, rcond=1e-10)
    return eta


class _Pem:
    """Residuals and Jacobian of the PEM criterion for scaled ``eta`` and ``c`` (filters over the whole
    record, criterion on ``rows``).

    Notes
    -----
    The Jacobian is :math:`-[\\varphi / C, \\; \\varepsilon(t-1) / C, \\dots, \\varepsilon(t-n_c) / C]` on
    ``rows``. Each column is filtered on its own, so the regressor is filtered as its transpose (every
    column contiguous: the same recursion on the same numbers, faster), and the lagged errors' columns are
    the lags of one filtered error (``lfilter`` is causal and starts at rest: a column that is zero before
    its lag filters to zeros there, then to the filtered error). The errors at a stable ``C`` are the ones
    :meth:`residuals` computed at the same ``x`` (the optimiser asks for both at each point).
    """

    def __init__(self, phi: np.ndarray, y: np.ndarray, nc: int, rows: np.ndarray, scale: np.ndarray):
        self.phi = phi / scale
        self._phi_t = np.ascontiguousarray(self.phi.T)  # (see notes)
        self.y, self.nc, self.rows = y, nc, rows
        self.m = phi.shape[1]
        self._key: bytes | None = None  # the x of the errors in _eps
        self._eps = np.empty(0)

    def stable(self, x: np.ndarray) -> np.ndarray:
        x = np.array(x, dtype=float)
        C = np.concatenate(([1.0], x[self.m:]))
        x[self.m:] = reflect_unstable_roots(C, 0.999)[1:]
        return x

    def _errors(self, x: np.ndarray, C: np.ndarray) -> np.ndarray:
        """The prediction errors over the whole record at ``x`` with a stable ``C`` (kept for the Jacobian)."""
        key = x.tobytes()
        if key != self._key:
            self._eps = lfilter([1.0], C, self.y - self.phi @ x[: self.m])
            self._key = key
        return self._eps

    def residuals(self, x: np.ndarray) -> np.ndarray:
        C = np.concatenate(([1.0], x[self.m:]))
        if C.size > 1 and np.max(np.abs(np.roots(C))) >= 1.0:
            return np.full(self.rows.size, 1e150)
        return self._errors(x, C)[self.rows]

    def jacobian(self, x: np.ndarray) -> np.ndarray:
        C = np.concatenate(([1.0], x[self.m:]))
        rows, m = self.rows, self.m
        if C.size > 1 and np.max(np.abs(np.roots(C))) >= 1.0:
            C = reflect_unstable_roots(C, 0.999)
            eps = lfilter([1.0], C, self.y - self.phi @ x[:m])
        else:
            eps = self._errors(x, C)
        J = np.empty((rows.size, m + self.nc))
        J[:, :m] = lfilter([1.0], C, self._phi_t)[:, rows].T
        filtered = lfilter([1.0], C, eps)
        for k in range(1, self.nc + 1):  # eps(t - k) / C, zero before the record
            lagged = rows - k
            J[:, m + k - 1] = np.where(lagged >= 0, filtered[np.maximum(lagged, 0)], 0.0)
        return np.negative(J, out=J)
