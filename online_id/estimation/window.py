"""Prediction-error refits of the ARMAX model over a sliding window of the stream (no I/O).

Notes
-----
Recursive extended least squares is cheap per sample but, on a bench, far
from efficient: the speed sensor noise is white on the *output*, so the
true noise polynomial is close to :math:`A` and has roots near the unit
circle; the pseudo-linear regression then converges slowly and its pole
estimate wanders (about +-2 % in :math:`f_0` with a 20 s memory on the
default simulated bench, where a batch fit of 20 s is within 0.05 %).

The seed paper starts its prediction-error fit from the recursive estimate.
:class:`SlidingPem` does the same, continuously: every ``refit_s`` seconds it
fits the ARMAX model by prediction-error minimisation
(:func:`~online_id.estimation.pem.fit_armax`) to the last ``window_s`` seconds,
started from its previous solution (a few Gauss-Newton steps to a relative
tolerance of 1e-3, about 15 ms for 10 s at 500 Hz). A *cold* fit -- two starts, Hannan-Rissanen and the
recursive estimate, the lower loss wins (:func:`fit_two_starts`) -- runs
first, after a gap, after a failed fit, and when the engine speed has moved
to another operating point (the compression poles move with it).

A window is fitted only when it is steady and excited: the engine speed
varies by at most ``max_speed_span_rpm`` between the means of its half-second
blocks, and the RMS of the (DC-blocked) torque is at least
``min_excitation_nm``. Otherwise the last fit is marked stale.

Refits fall due at fixed sample counts. With ``auto`` they run inside
:meth:`SlidingPem.push`; the service pipeline instead runs a due refit on the
next sample that publishes nothing, so a refit (10-20 ms, a cold one about
0.5 s) never delays an estimate frame. Either way the schedule depends only
on the samples, so a replay gives the same results as the live stream,
whatever the machine's speed.
"""

from __future__ import annotations

import math

import numpy as np

from online_id.estimation.model import ArmaxOrders
from online_id.estimation.pem import ArmaxFit, fit_armax
from online_id.estimation.rels import RecursiveArmax
from online_id.errors import EstimationError


FIT_ERRORS = (EstimationError, FloatingPointError, ValueError, np.linalg.LinAlgError)


def fit_two_starts(y: np.ndarray, u: np.ndarray, orders: ArmaxOrders, recursive_start: bool = True,
                   starts: tuple = ()) -> ArmaxFit:
    """PEM fit from two starts (Hannan-Rissanen, and the recursive estimate); the lower loss wins.

    The prediction-error criterion of an over-parametrised ARMAX model has
    local minima: one start alone can settle where the compression oscillator
    is missing from the model. ``starts`` (e.g. earlier solutions; None
    entries are skipped) are tried as further starts; one that fails is
    left out.
    """
    fits = [fit_armax(y, u, orders)]
    for theta0 in starts:
        if theta0 is None:
            continue
        try:
            fits.append(fit_armax(y, u, orders, theta0=np.asarray(theta0, dtype=float)))
        except FIT_ERRORS:
            pass
    if recursive_start:
        est = RecursiveArmax(orders, lam=1.0, p0=1e3)
        est.update_block(y, u)
        if np.all(np.isfinite(est.theta)):
            try:
                fits.append(fit_armax(y, u, orders, theta0=est.theta))
            except EstimationError:
                pass
    return min(fits, key=lambda f: f.V)


def _finite(fit: ArmaxFit) -> bool:
    return bool(np.all(np.isfinite(fit.theta)) and np.all(np.isfinite(fit.covariance)))


class SlidingPem:
    """Periodic prediction-error fits over the last ``window_s`` seconds (see module notes)."""

    def __init__(self, orders: ArmaxOrders, dt: float, *, window_s: float = 10.0, refit_s: float = 1.0,
                 max_speed_span_rpm: float = 40.0, min_excitation_nm: float = 1.0,
                 warm_iterations: int = 40, warm_tol: float = 1e-3, auto: bool = True) -> None:
        self.orders = orders
        self.dt = float(dt)
        self.n_window = max(int(round(window_s / dt)), 4 * orders.n_params)
        self.n_refit = max(1, int(round(refit_s / dt)))
        self.n_block = max(1, int(round(0.5 / dt)))
        self.max_span_rad_s = max_speed_span_rpm * np.pi / 30.0
        self.min_excitation_nm = float(min_excitation_nm)
        self.warm_iterations = int(warm_iterations)
        self.warm_tol = float(warm_tol)
        self._buf = np.zeros((4, self.n_window))  # y, u, engine speed, load (raw torque); circular
        self._pos = 0
        self._count = 0
        self._since = 0
        self.fit: ArmaxFit | None = None
        self._start: np.ndarray | None = None  # an earlier solution (kept across a restart)
        self.fit_speed_rpm = float("nan")
        self.fit_load_nm = float("nan")  # mean raw torque of the fitted window (the load at the operating point)
        self.current = False  # the last refit attempt succeeded on a steady, excited window
        self.reason = "window filling"
        self.auto = auto  # refit inside push(); otherwise the owner calls refit() when it suits (``due``)
        self.due = False
        self.n_fits = 0
        self.n_cold = 0
        self.n_failed = 0

    # -- per sample ---------------------------------------------------------------------------
    def push(self, y: float, u: float, speed_rad_s: float, load_nm: float = 0.0) -> bool:
        """Add one decimated sample; returns True when a refit fell due (and ran, with ``auto``).

        ``y`` and ``u`` are the (DC-blocked) model signals, ``load_nm`` the raw
        torque, whose window mean is the load of the fit (``fit_load_nm``).
        """
        if not (math.isfinite(y) and math.isfinite(u) and math.isfinite(speed_rad_s)
                and math.isfinite(load_nm)):  # scalars: math is 10x cheaper
            self.clear()
            return False
        b = self._buf
        b[0, self._pos], b[1, self._pos], b[2, self._pos], b[3, self._pos] = y, u, speed_rad_s, load_nm
        self._pos = (self._pos + 1) % self.n_window
        self._count += 1
        self._since += 1
        if self._count < self.n_window or self._since < self.n_refit:
            return False
        self._since = 0
        self.due = True
        if self.auto:
            self.refit()
        return True

    def refit(self) -> None:
        """Run the refit that is due (a no-op when none is)."""
        if self.due:
            self.due = False
            self._refit()

    def clear(self) -> None:
        """Forget the window (after a gap): the next fit needs a full window of new samples."""
        self._count = 0
        self._since = 0
        self._pos = 0
        self.due = False
        self.current = False
        self.reason = "window filling"

    # -- fitting ----------------------------------------------------------------------------------
    def window(self) -> np.ndarray:
        """The window, oldest sample first: rows y, u, engine speed [rad/s], load [Nm]."""
        return np.roll(self._buf, -self._pos, axis=1)

    def _refit(self) -> None:
        if self._count < self.n_window:
            return
        w = self.window()
        y, u, n, load = w
        nb = self.n_window // self.n_block
        means = n[: nb * self.n_block].reshape(nb, self.n_block).mean(axis=1)
        span = float(means.max() - means.min()) if nb else 0.0
        speed_rpm = float(np.mean(n)) * 30.0 / np.pi
        if span > self.max_span_rad_s:
            self.current = False
            self.reason = f"speed not steady ({span * 30 / np.pi:.0f} rpm in the window)"
            return
        if float(np.std(u)) < self.min_excitation_nm:
            self.current = False
            self.reason = "torque excitation too low"
            return
        moved = (not np.isfinite(self.fit_speed_rpm)
                 or abs(speed_rpm - self.fit_speed_rpm) > 0.5 * self.max_span_rad_s * 30.0 / np.pi)
        try:
            if self._start is None or moved or not self.current:
                fit = fit_two_starts(y, u, self.orders, starts=() if moved else (self._start,))
                self.n_cold += 1
            else:
                fit = fit_armax(y, u, self.orders, theta0=self._start, max_iter=self.warm_iterations,
                                start_radius=0.999, tol=self.warm_tol)
        except FIT_ERRORS as err:
            self.n_failed += 1
            self.current = False
            self.reason = f"fit failed: {err}"
            return
        if not _finite(fit):
            self.n_failed += 1
            self.current = False
            self.reason = "fit failed: not finite"
            return
        self._adopt(fit, load)
        self.fit_speed_rpm = speed_rpm
        self.current = True
        self.reason = ""

    def _adopt(self, fit: ArmaxFit, load: np.ndarray) -> None:
        """``fit`` of the window whose raw torque is ``load`` becomes the current solution."""
        self.fit = fit
        self._start = fit.theta
        self.fit_load_nm = float(np.mean(load))
        self.n_fits += 1

    def verify(self, starts: tuple = ()) -> bool:
        """Refit the current window from several starts; adopt the fit of lowest loss (True if one was made).

        The starts: Hannan-Rissanen, the recursive estimate, the current
        solution and ``starts`` (e.g. the solution the baseline was learned
        with). Used before an alarm is raised (see
        :class:`~online_id.monitoring.detection.ChangeDetector`, *confirm*); about
        0.5 s, rare. A window that is not full, not steady or not excited is
        left as it is.
        """
        if self._count < self.n_window or not self.current:
            return False
        y, u, _n, load = self.window()
        try:
            fit = fit_two_starts(y, u, self.orders, starts=(self._start, *starts))
        except FIT_ERRORS:
            return False
        if not _finite(fit):
            return False
        self._adopt(fit, load)
        self.n_cold += 1
        return True

    # -- persistence --------------------------------------------------------------------------------
    def get_state(self) -> dict:
        """What a restart keeps: the last solution (a warm start once a new window is full)."""
        return {"theta": None if self._start is None else self._start.tolist(),
                "speed_rpm": self.fit_speed_rpm, "n_fits": self.n_fits}

    def load_state(self, state: dict) -> None:
        theta = state.get("theta")
        self.fit = None
        self._start = None
        self.fit_speed_rpm = float(state.get("speed_rpm", float("nan")))
        self.n_fits = int(state.get("n_fits", 0))
        if theta is not None:
            theta = np.asarray(theta, dtype=float)
            if theta.shape != (self.orders.n_params,) or not np.all(np.isfinite(theta)):
                raise EstimationError(f"saved window fit has {theta.shape} parameters, expected "
                                      f"{self.orders.n_params} finite values for {self.orders}")
        self._start = theta
        self.clear()
