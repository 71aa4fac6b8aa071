"""Recursive extended least squares (RELS / RPLR) ARMAX estimator.

The model, the parameter vector :math:`\\theta` and the regressor
:math:`\\varphi(t)` follow :class:`online_id.estimation.model.ArmaxOrders` exactly.
The C-part of the regressor holds the *a posteriori* residuals
:math:`\\varepsilon(t-k)` (pseudo-linear regression).

Notes
-----
One step of the recursion, with forgetting factor :math:`\\lambda`:

.. math::

    e(t) = y(t) - \\varphi(t)^T \\hat\\theta(t-1)            \\quad \\text{(a priori error)}

    K(t) = \\frac{P(t-1) \\varphi(t)}{\\lambda + \\varphi(t)^T P(t-1) \\varphi(t)}

    \\hat\\theta(t) = \\hat\\theta(t-1) + K(t) e(t)

    P(t) = \\frac{1}{\\lambda}\\left(P(t-1) - K(t) \\varphi(t)^T P(t-1)\\right)

    \\varepsilon(t) = y(t) - \\varphi(t)^T \\hat\\theta(t)   \\quad \\text{(a posteriori residual)}

The rank-one term is formed as :math:`(P\\varphi)(P\\varphi)^T / d` with
the product of the two vector entries taken first, so the (i, j) and (j, i)
entries are the same floating-point number: :math:`P` stays *exactly*
symmetric without an explicit symmetrisation pass.

Numerical guards, all inside the compiled step:

* **trace bound** -- if :math:`\\operatorname{tr} P > ` ``trace_max`` after the
  update, :math:`P` is scaled by ``trace_max / tr P`` (covariance wind-up
  during poor excitation with :math:`\\lambda < 1`);
* **reset** -- if an input sample is not finite, or the update produces a
  non-finite value or a non-positive denominator (covariance no longer
  positive definite), :math:`\\hat\\theta` is kept from before the step,
  :math:`P = p_0 I`, and ``n_resets`` is incremented; NaN never enters the
  state.  A non-finite input sample also clears the regressor history
  (the regressor restarts as at construction);
* **frozen adaptation** -- an exponentially weighted variance of the input
  :math:`u` (weight :math:`w_t = \\max(1-\\lambda, 1/t)`, i.e. a plain running
  variance while :math:`t < 1/(1-\\lambda)` and for :math:`\\lambda = 1`) is
  tracked; while it is below ``min_excitation``, :math:`\\hat\\theta` and
  :math:`P` are frozen (the gain is zero) and the regressor history still
  advances.

All state lives in one contiguous float64 array so that the per-sample call
into the numba-compiled step passes one array and two floats.
"""

from __future__ import annotations

import math
from typing import Any, Protocol, runtime_checkable

import numpy as np
from numba import njit

from online_id.estimation.model import ArmaxOrders
from online_id.errors import ConfigError, InputDataError

# Layout of the state vector: a header of scalars, then the arrays.
_LAM = 0
_P0 = 1
_TRACE_MAX = 2
_MIN_EXC = 3
_NA = 4
_NB = 5
_NC = 6
_NK = 7
_OFFSET = 8
_N_SAMPLES = 9
_N_RESETS = 10
_FROZEN = 11
_INNOVATION = 12
_U_MEAN = 13
_U_VAR = 14
_HEADER = 16


def _layout(orders: ArmaxOrders) -> dict[str, tuple[int, int]]:
    """(start, length) of each array in the state vector."""
    n = orders.n_params
    sizes = [
        ("theta", n),
        ("P", n * n),
        ("K", n),
        ("phi", n),
        ("Pphi", n),
        ("theta_prev", n),
        ("y_hist", orders.na),
        ("u_hist", orders.nk + orders.nb),
        ("eps_hist", orders.nc),
    ]
    out: dict[str, tuple[int, int]] = {}
    start = _HEADER
    for name, size in sizes:
        out[name] = (start, size)
        start += size
    out["_total"] = (start, 0)
    return out


@njit(cache=True, fastmath=False)
def _reset_cov(P, p0):  # pragma: no cover - compiled
    """P = p0 I in place."""
    P[:, :] = 0.0
    for i in range(P.shape[0]):
        P[i, i] = p0


@njit(cache=True, fastmath=False)
def _armax_step(s, y, u):  # pragma: no cover - compiled
    """One RELS sample on the state vector ``s``; returns the a priori error."""
    lam = s[_LAM]
    na = int(s[_NA])
    nb = int(s[_NB])
    nc = int(s[_NC])
    nk = int(s[_NK])
    off = int(s[_OFFSET])
    n = na + nb + nc + off
    nu = nk + nb
    # Views into the state vector (contiguous slices: the loops vectorise).
    i0 = _HEADER
    theta = s[i0 : i0 + n]
    i0 += n
    P = s[i0 : i0 + n * n].reshape((n, n))
    i0 += n * n
    K = s[i0 : i0 + n]
    i0 += n
    phi = s[i0 : i0 + n]
    i0 += n
    Pphi = s[i0 : i0 + n]
    i0 += n
    theta_prev = s[i0 : i0 + n]
    i0 += n
    y_hist = s[i0 : i0 + na]
    i0 += na
    u_hist = s[i0 : i0 + nu]
    i0 += nu
    eps_hist = s[i0 : i0 + nc]

    s[_N_SAMPLES] += 1.0

    # Non-finite input: keep theta, P = p0 I, restart the regressor history.
    if not (math.isfinite(y) and math.isfinite(u)):
        _reset_cov(P, s[_P0])
        K[:] = 0.0
        y_hist[:] = 0.0
        u_hist[:] = 0.0
        eps_hist[:] = 0.0
        s[_N_RESETS] += 1.0
        s[_INNOVATION] = np.nan
        return np.nan

    # Excitation: exponentially weighted input variance, w = max(1 - lam, 1/t).
    w = max(1.0 - lam, 1.0 / s[_N_SAMPLES])
    d = u - s[_U_MEAN]
    s[_U_MEAN] += w * d  # m(t) = m(t-1) + w d
    s[_U_VAR] = (1.0 - w) * (s[_U_VAR] + w * d * d)  # v(t) = (1-w) (v(t-1) + w d^2)
    frozen = s[_U_VAR] < s[_MIN_EXC]
    s[_FROZEN] = 1.0 if frozen else 0.0

    # Shift u(t) in first: with nk = 0, u(t) is part of phi(t).
    for k in range(nu - 1, 0, -1):
        u_hist[k] = u_hist[k - 1]
    if nu > 0:
        u_hist[0] = u

    # phi(t) = [-y(t-1..t-na), u(t-nk..t-nk-nb+1), eps(t-1..t-nc), 1]
    for k in range(na):
        phi[k] = -y_hist[k]
    for k in range(nb):
        phi[na + k] = u_hist[nk + k]
    for k in range(nc):
        phi[na + nb + k] = eps_hist[k]
    if off:
        phi[n - 1] = 1.0

    # e(t) = y(t) - phi^T theta(t-1)
    yhat = 0.0
    for k in range(n):
        yhat += phi[k] * theta[k]
    e = y - yhat
    s[_INNOVATION] = e

    ok = math.isfinite(e)
    if frozen or not ok:
        K[:] = 0.0
        eps = e
    else:
        theta_prev[:] = theta
        # Pphi = P(t-1) phi   (sweep over the rows of the symmetric P)
        Pphi[:] = 0.0
        for j in range(n):
            pj = phi[j]
            Pj = P[j]
            for i in range(n):
                Pphi[i] += Pj[i] * pj
        # d = lam + phi^T P(t-1) phi
        den = lam
        for k in range(n):
            den += phi[k] * Pphi[k]
        ok = math.isfinite(den) and den > 0.0
        if ok:
            inv_den = 1.0 / den
            inv_lam = 1.0 / lam
            # K = P phi / d ;  theta(t) = theta(t-1) + K e
            tsum = 0.0
            for k in range(n):
                K[k] = Pphi[k] * inv_den
                theta[k] += K[k] * e
                tsum += theta[k]
            # P(t) = (P(t-1) - (P phi)(P phi)^T / d) / lam   (exactly symmetric)
            trace = 0.0
            for i in range(n):
                gi = Pphi[i]
                Pi = P[i]
                for j in range(n):
                    Pi[j] = (Pi[j] - (gi * Pphi[j]) * inv_den) * inv_lam
                trace += Pi[i]
            ok = math.isfinite(tsum) and math.isfinite(trace)
            if ok and trace > s[_TRACE_MAX]:
                # trace guard: P <- P * trace_max / tr(P)
                scale = s[_TRACE_MAX] / trace
                for i in range(n):
                    Pi = P[i]
                    for j in range(n):
                        Pi[j] *= scale
        if ok:
            # eps(t) = y(t) - phi^T theta(t)
            eps = y
            for k in range(n):
                eps -= phi[k] * theta[k]
        else:
            theta[:] = theta_prev
            K[:] = 0.0
            eps = e
    if not ok:
        # theta(t) = theta(t-1), P(t) = p0 I
        _reset_cov(P, s[_P0])
        s[_N_RESETS] += 1.0
        if not math.isfinite(eps):
            eps = 0.0

    # Shift y(t) and eps(t) into the history.
    for k in range(na - 1, 0, -1):
        y_hist[k] = y_hist[k - 1]
    if na > 0:
        y_hist[0] = y
    for k in range(nc - 1, 0, -1):
        eps_hist[k] = eps_hist[k - 1]
    if nc > 0:
        eps_hist[0] = eps
    return e


@njit(cache=True, fastmath=False)
def _armax_block(s, y, u, out):  # pragma: no cover - compiled
    """The same step as :func:`_armax_step`, looped over a block of samples."""
    for t in range(y.shape[0]):
        out[t] = _armax_step(s, y[t], u[t])


@runtime_checkable
class RecursiveEstimator(Protocol):
    """Interface shared by the recursive ARMAX estimators."""

    orders: ArmaxOrders

    def update(self, y: float, u: float) -> float: ...

    def update_block(self, y: np.ndarray, u: np.ndarray) -> np.ndarray: ...

    @property
    def theta(self) -> np.ndarray: ...

    @property
    def P(self) -> np.ndarray: ...

    @property
    def gain(self) -> np.ndarray: ...

    @property
    def innovation(self) -> float: ...

    @property
    def n_samples(self) -> int: ...

    @property
    def n_resets(self) -> int: ...

    def polynomials(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]: ...

    def reset(self, p0: float | None = None) -> None: ...


def check_block(y: Any, u: Any) -> tuple[np.ndarray, np.ndarray]:
    """Validate a block of samples; return float64 contiguous 1-D arrays (never mutated)."""
    y_arr = np.ascontiguousarray(y, dtype=np.float64)
    u_arr = np.ascontiguousarray(u, dtype=np.float64)
    if y_arr.ndim != 1 or u_arr.ndim != 1 or y_arr.shape != u_arr.shape:
        raise InputDataError(
            f"Expected 1-D arrays y and u of equal length, but got shapes {y_arr.shape} and {u_arr.shape}"
        )
    return y_arr, u_arr


def check_theta0(orders: ArmaxOrders, theta0: Any) -> np.ndarray:
    """Validate an initial parameter vector (returns a new array)."""
    n = orders.n_params
    if theta0 is None:
        return np.zeros(n)
    theta = np.array(theta0, dtype=np.float64, copy=True)
    if theta.shape != (n,) or not np.all(np.isfinite(theta)):
        raise ConfigError(f"Expected theta0 of {n} finite values, but got shape {theta.shape}: {theta0!r}")
    return theta


def check_positive(name: str, value: float) -> float:
    """Validate a finite strictly positive setting."""
    value = float(value)
    if not (math.isfinite(value) and value > 0.0):
        raise ConfigError(f"Expected {name} > 0 and finite, but got {value!r}")
    return value


def check_lam(value: float) -> float:
    """Validate a forgetting factor."""
    value = float(value)
    if not 0.0 < value <= 1.0:
        raise ConfigError(f"Expected forgetting factor lam in (0, 1], but got {value!r}")
    return value


class RecursiveArmax:
    """ARMAX by recursive extended least squares with exponential forgetting.

    Parameters
    ----------
    orders
        Model orders; fixes the layout of ``theta`` and of the regressor.
    lam
        Forgetting factor :math:`\\lambda \\in (0, 1]`; the memory is about
        :math:`1/(1-\\lambda)` samples.
    p0
        Initial covariance :math:`P(0) = p_0 I`, also used by resets.
    theta0
        Initial parameter vector (default zeros); copied, never mutated.
    trace_max
        Upper bound on :math:`\\operatorname{tr} P` (default ``n_params * p0``,
        the initial trace: the estimator never becomes more uncertain in total
        than at the start).  ``np.inf`` disables the bound.
    min_excitation
        Adaptation is frozen while the exponentially weighted input variance
        is below this value (default 0: never frozen).

    Attributes
    ----------
    orders : ArmaxOrders
        The model orders.

    Notes
    -----
    See the module notes for the recursion and the guards.  ``update`` and
    ``update_block`` call the same compiled step and give bit-identical
    results.
    """

    def __init__(
        self,
        orders: ArmaxOrders,
        *,
        lam: float = 0.999,
        p0: float = 1e3,
        theta0: np.ndarray | None = None,
        trace_max: float | None = None,
        min_excitation: float = 0.0,
    ) -> None:
        if not isinstance(orders, ArmaxOrders):
            raise ConfigError(f"Expected orders of type ArmaxOrders, but got {type(orders).__name__}")
        lam = check_lam(lam)
        p0 = check_positive("p0", p0)
        theta = check_theta0(orders, theta0)
        n = orders.n_params
        if trace_max is None:
            trace_max = n * p0
        trace_max = float(trace_max)
        if not trace_max > 0.0:  # inf allowed
            raise ConfigError(f"Expected trace_max > 0, but got {trace_max!r}")
        min_excitation = float(min_excitation)
        if not (math.isfinite(min_excitation) and min_excitation >= 0.0):
            raise ConfigError(f"Expected min_excitation >= 0 and finite, but got {min_excitation!r}")
        if min_excitation > 0.0 and orders.nb == 0:
            raise ConfigError("min_excitation > 0 needs an input in the model (nb > 0), but got nb=0")
        self.orders = orders
        layout = _layout(orders)
        state = np.zeros(layout["_total"][0])
        state[[_LAM, _P0, _TRACE_MAX, _MIN_EXC]] = lam, p0, trace_max, min_excitation
        state[[_NA, _NB, _NC, _NK, _OFFSET]] = orders.na, orders.nb, orders.nc, orders.nk, int(orders.offset)
        self._bind(state)
        self._theta[:] = theta
        self._P[:] = np.eye(n) * p0

    def _bind(self, state: np.ndarray) -> None:
        """Attach the state vector and its views."""
        n = self.orders.n_params
        layout = _layout(self.orders)
        self._state = state

        def view(name: str) -> np.ndarray:
            start, size = layout[name]
            return state[start : start + size]

        self._theta = view("theta")
        self._P = view("P").reshape(n, n)
        self._K = view("K")
        self._phi = view("phi")
        self._y_hist = view("y_hist")
        self._u_hist = view("u_hist")
        self._eps_hist = view("eps_hist")

    # --- streaming -----------------------------------------------------------------

    def update(self, y: float, u: float) -> float:
        """Process one sample; return the a priori prediction error e(t).

        A non-finite sample resets the estimator and returns NaN.
        """
        return _armax_step(self._state, float(y), float(u))

    def update_block(self, y: np.ndarray, u: np.ndarray) -> np.ndarray:
        """Process a block of samples; return the a priori errors.

        Bit-identical to calling :meth:`update` on each sample in turn.
        """
        y_arr, u_arr = check_block(y, u)
        out = np.empty_like(y_arr)
        _armax_block(self._state, y_arr, u_arr, out)
        return out

    # --- results ---------------------------------------------------------------------

    @property
    def theta(self) -> np.ndarray:
        """Parameter estimate (a copy)."""
        return self._theta.copy()

    @property
    def P(self) -> np.ndarray:
        """Covariance matrix P (a copy)."""
        return self._P.copy()

    @property
    def gain(self) -> np.ndarray:
        """Gain K of the last update (zeros when frozen or reset)."""
        return self._K.copy()

    @property
    def innovation(self) -> float:
        """A priori error e(t) of the last update (NaN after a non-finite sample)."""
        return float(self._state[_INNOVATION])

    @property
    def regressor(self) -> np.ndarray:
        """Regressor phi(t) of the last update (a copy)."""
        return self._phi.copy()

    @property
    def n_samples(self) -> int:
        """Number of samples processed (including reset samples)."""
        return int(self._state[_N_SAMPLES])

    @property
    def n_resets(self) -> int:
        """Number of automatic resets (non-finite values, indefinite P)."""
        return int(self._state[_N_RESETS])

    @property
    def frozen(self) -> bool:
        """True while adaptation is frozen for lack of excitation."""
        return bool(self._state[_FROZEN])

    @property
    def excitation(self) -> float:
        """Exponentially weighted variance of the input u."""
        return float(self._state[_U_VAR])

    @property
    def lam(self) -> float:
        """Forgetting factor."""
        return float(self._state[_LAM])

    @property
    def trace_max(self) -> float:
        """Upper bound on the trace of P."""
        return float(self._state[_TRACE_MAX])

    def polynomials(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Estimated ``(A, B, C)`` (see :meth:`ArmaxOrders.split`)."""
        return self.orders.split(self._theta)

    # --- state management ------------------------------------------------------------

    def reset(self, p0: float | None = None) -> None:
        """Restart adaptation: P = p0 I (default: the constructor's p0).

        ``theta`` and the regressor history are kept; ``n_resets`` counts
        only automatic resets.
        """
        value = self._state[_P0] if p0 is None else check_positive("p0", p0)
        self._P[:] = np.eye(self.orders.n_params) * value

    def copy(self) -> RecursiveArmax:
        """Independent copy that continues identically."""
        new = object.__new__(type(self))
        new.orders = self.orders
        new._bind(self._state.copy())
        return new

    def __getstate__(self) -> dict[str, Any]:
        return {"orders": self.orders, "state": self._state.copy()}

    def __setstate__(self, d: dict[str, Any]) -> None:
        self.orders = d["orders"]
        self._bind(np.ascontiguousarray(d["state"], dtype=np.float64).copy())

    def get_state(self) -> dict[str, Any]:
        """State as plain floats, ints and arrays (for persistence, e.g. ``np.savez``)."""
        o = self.orders
        s = self._state
        return {
            "na": o.na,
            "nb": o.nb,
            "nc": o.nc,
            "nk": o.nk,
            "offset": bool(o.offset),
            "lam": float(s[_LAM]),
            "p0": float(s[_P0]),
            "trace_max": float(s[_TRACE_MAX]),
            "min_excitation": float(s[_MIN_EXC]),
            "n_samples": int(s[_N_SAMPLES]),
            "n_resets": int(s[_N_RESETS]),
            "frozen": bool(s[_FROZEN]),
            "innovation": float(s[_INNOVATION]),
            "u_mean": float(s[_U_MEAN]),
            "u_var": float(s[_U_VAR]),
            "theta": self.theta,
            "P": self.P,
            "gain": self.gain,
            "y_hist": self._y_hist.copy(),
            "u_hist": self._u_hist.copy(),
            "eps_hist": self._eps_hist.copy(),
        }

    @classmethod
    def from_state(cls, state: dict[str, Any]) -> RecursiveArmax:
        """Rebuild an estimator from :meth:`get_state` output."""
        try:
            orders = ArmaxOrders(
                int(state["na"]), int(state["nb"]), int(state["nc"]), int(state["nk"]), bool(state["offset"])
            )
            est = cls(
                orders,
                lam=state["lam"],
                p0=state["p0"],
                theta0=state["theta"],
                trace_max=state["trace_max"],
                min_excitation=state["min_excitation"],
            )
            n = orders.n_params
            s = est._state
            P = np.asarray(state["P"], dtype=np.float64)
            if P.shape != (n, n):
                raise ConfigError(f"Expected state P of shape ({n}, {n}), but got {P.shape}")
            est._P[:] = 0.5 * (P + P.T)  # the step relies on an exactly symmetric P
            for name, target in (
                ("gain", est._K),
                ("y_hist", est._y_hist),
                ("u_hist", est._u_hist),
                ("eps_hist", est._eps_hist),
            ):
                value = np.asarray(state[name], dtype=np.float64)
                if value.shape != target.shape:
                    raise ConfigError(f"Expected state {name} of shape {target.shape}, but got {value.shape}")
                target[:] = value
            s[_N_SAMPLES] = int(state["n_samples"])
            s[_N_RESETS] = int(state["n_resets"])
            s[_FROZEN] = float(bool(state["frozen"]))
            s[_INNOVATION] = float(state["innovation"])
            s[_U_MEAN] = float(state["u_mean"])
            s[_U_VAR] = float(state["u_var"])
        except KeyError as err:
            key = err.args[0]
            raise ConfigError(f"Expected key {key!r} in the estimator state, but it is missing") from err
        return est

    def __repr__(self) -> str:
        o = self.orders
        return (
            f"RecursiveArmax(na={o.na}, nb={o.nb}, nc={o.nc}, nk={o.nk}, offset={o.offset}, "
            f"lam={self.lam}, n_samples={self.n_samples}, n_resets={self.n_resets})"
        )
