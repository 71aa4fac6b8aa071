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

**After a change of operating point.** The DC blocker before the window
(a first-order high-pass, see :mod:`~online_id.estimation.online`) leaves a
decaying offset in both signals after a ramp of the speed: the speed's
offset starts at several rad/s, far above the response to the test torque,
and decays as :math:`d^k` (:math:`d` the blocker's decay per sample). A
window that held it was fitted poorly: on a simulated bench, 10 s of
invalid estimates with twice the damping after a 240 rpm ramp. So the fit
takes only the samples since the speed became steady (the newest
half-second blocks within ``max_speed_span_rpm``), less a guard of
``settle_guard_s``, once they are at least ``min_window_s``; and it removes
from each of :math:`y` and :math:`u` its least-squares fit of
:math:`a + b d^k` (:math:`k` counting the segment's samples): the mean and
the blocker's initial-condition response, a pole the ARMAX model lacks (on
a window long after a change both coefficients are about zero). The window
then grows by a refit a second until it is ``window_s`` long. The estimate
is valid again about ``settle_guard_s + min_window_s`` after the ramp ends
(6 s with the defaults; the whole window, 10 s, and whatever the transient
cost before), and its own uncertainty, from the shorter fit's covariance,
says how much less it knows.

A cold fit also starts from the caller's ``starts`` (the streaming
estimator passes the last solution whose estimate was valid: the driveline
is the same at the next operating point), and the caller may ask for a cold
fit where a warm one would do (it does so every other refit while the
estimate is not valid or its resonance has just moved by more than 0.5 %:
a warm-started fit can stay for many seconds in a minimum whose resonance
is poorly determined, or follow a step of the stiffness only slowly; the
cold fit keeps the lowest loss of all its starts, the warm one's among
them).

**After a change of the driveline.** A step of the stiffness in the middle
of a steady stretch reaches the 10 s window bit by bit: its fits hold two
systems and move from the one to the other over the window's length (the
estimate was within 1 % of a 10-15 % loss only 8-10 s after the step on
the simulated benches, and where the mixture is not valid, with backlash,
not at all before the next change of operating point). The caller may
therefore ask for a fit of the newest ``min_window_s`` of a longer segment
(``prepare(newest=True)``; the streaming estimator does so, in a steady
stretch longer than the window, when the valid estimate moved by more than
0.5 % since the refit before, and every other refit after one stopped being
valid), and judges it (:meth:`SlidingPem.settle_newest`):
where its estimate is valid (and, after a valid estimate of the long
window, differs from it by more than both their uncertainties allow:
``online.NEWEST_SIGMAS``), the older samples are cut and the segment grows
again from the cut as after a change of operating point (within 1 % of the
new resonance 5-6 s after the step); where it is not, the fit before it is
current again, as if the probe had not run (a shaft with backlash, whose
shorter fits are less often valid, or whose fits hop between nearby minima,
keeps its estimates).

Refits fall due at fixed sample counts. With ``auto`` they run inside
:meth:`SlidingPem.push`. The pipeline instead splits a refit in three:
:meth:`SlidingPem.prepare` checks the window and copies it into a
:class:`RefitJob` (no fitting), :func:`solve` fits it (a pure function: the
live service runs it in a worker process, off the receive path, see
:mod:`online_id.service.offload`) and :meth:`SlidingPem.complete` adopts the result.
A result for a window that was cleared meanwhile (a gap) is discarded. With
the inline worker of replay the three run back to back, so the schedule
depends only on the samples and a replay is reproducible whatever the
machine's speed.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from online_id.estimation.model import ArmaxOrders
from online_id.estimation.pem import ArmaxFit, fit_armax
from online_id.estimation.rels import RecursiveArmax
from online_id.errors import EstimationError


FIT_ERRORS = (EstimationError, FloatingPointError, ValueError, np.linalg.LinAlgError)
SOLVER = "trf"
"""The window's PEM solver (:func:`~online_id.estimation.pem.fit_armax`): scipy's trust-region solver.
The Levenberg-Marquardt solver of ``identify`` costs about a third as much, but measured on the window
refits it does not follow a 20 % stiffness step: warm-started from the previous window's optimum it stops
after about two steps at a loss 10 % above the optimum (the trust-region solver reaches it in four), and the
estimate lagged the step by more than ten refits instead of one (``tests/test_window.py``)."""


def fit_two_starts(y: np.ndarray, u: np.ndarray, orders: ArmaxOrders, recursive_start: bool = True,
                   starts: tuple = (), prefer_last_within: float = 0.0, **fit_kwargs) -> ArmaxFit:
    """PEM fit from two starts (Hannan-Rissanen, and the recursive estimate); the lower loss wins.

    The prediction-error criterion of an over-parametrised ARMAX model has
    local minima: one start alone can settle where the compression oscillator
    is missing from the model. ``starts`` (e.g. earlier solutions; None
    entries are skipped) are tried as further starts; one that fails is
    left out. ``prefer_last_within`` > 0: the fit from the last of
    ``starts`` wins if its loss is within that share of the lowest,
    ``V_last <= (1 + prefer_last_within) V_min`` -- where the
    criterion has nearly equal minima, the data do not tell them apart, and
    the caller's own solution (a baseline's) is kept. ``fit_kwargs`` (e.g.
    ``solver="lm"``) go to every :func:`~online_id.estimation.pem.fit_armax`.
    """
    fits = [fit_armax(y, u, orders, **fit_kwargs)]
    last = None
    for k, theta0 in enumerate(starts):
        if theta0 is None:
            continue
        try:
            fits.append(fit_armax(y, u, orders, theta0=np.asarray(theta0, dtype=float), **fit_kwargs))
            last = fits[-1] if k == len(starts) - 1 else None
        except FIT_ERRORS:
            pass
    if recursive_start:
        est = RecursiveArmax(orders, lam=1.0, p0=1e3)
        est.update_block(y, u)
        if np.all(np.isfinite(est.theta)):
            try:
                fits.append(fit_armax(y, u, orders, theta0=est.theta, **fit_kwargs))
            except EstimationError:
                pass
    best = min(fits, key=lambda f: f.V)
    if last is not None and prefer_last_within > 0.0 and last.V <= (1.0 + prefer_last_within) * best.V:
        return last
    return best


def _finite(fit: ArmaxFit) -> bool:
    return bool(np.all(np.isfinite(fit.theta)) and np.all(np.isfinite(fit.covariance)))


@dataclass(frozen=True)
class RefitJob:
    """A window to fit, copied out of the stream (see module notes).

    ``mode``: ``"warm"`` (a few Gauss-Newton steps from ``starts[0]``),
    ``"cold"`` (:func:`fit_two_starts` with ``starts`` as further starts) or
    ``"verify"`` (as cold, for :meth:`SlidingPem.prepare_verify`).
    """

    y: np.ndarray
    u: np.ndarray
    orders: ArmaxOrders
    mode: str
    starts: tuple
    load_nm: float
    speed_rpm: float
    generation: int
    warm_iterations: int = 40
    warm_tol: float = 1e-3
    prefer_last_within: float = 0.0  # verify: see fit_two_starts
    first: int = -1  # refit: stream count of the job's first sample (where a probe of the newest seconds cuts)
    newest: bool = False  # only the newest ``min_window_s`` of a longer segment (see SlidingPem.prepare)


def solve(job: RefitJob) -> ArmaxFit:
    """Fit the window of ``job`` (pure: runs in the pipeline or in a worker process)."""
    if job.mode == "warm":
        return fit_armax(job.y, job.u, job.orders, theta0=job.starts[0], max_iter=job.warm_iterations,
                         start_radius=0.999, tol=job.warm_tol, solver=SOLVER)
    return fit_two_starts(job.y, job.u, job.orders, starts=job.starts, prefer_last_within=job.prefer_last_within,
                          solver=SOLVER)


def solve_or_error(job: RefitJob) -> tuple[ArmaxFit | None, str | None]:
    """``(fit, None)`` of :func:`solve`, or ``(None, description)`` where the fit failed."""
    try:
        return solve(job), None
    except FIT_ERRORS as err:
        return None, str(err)


class SlidingPem:
    """Periodic prediction-error fits over the last ``window_s`` seconds (see module notes)."""

    def __init__(self, orders: ArmaxOrders, dt: float, *, window_s: float = 10.0, refit_s: float = 1.0,
                 max_speed_span_rpm: float = 40.0, min_excitation_nm: float = 1.0,
                 warm_iterations: int = 40, warm_tol: float = 1e-3, auto: bool = True,
                 min_window_s: float | None = None, settle_guard_s: float = 0.0,
                 dc_decay: float | None = None) -> None:
        self.orders = orders
        self.dt = float(dt)
        self.n_window = max(int(round(window_s / dt)), 4 * orders.n_params)
        self.window_s = self.n_window * self.dt
        # the shortest steady segment fitted after a change of operating point (default: the whole window)
        self.n_min = self.n_window if min_window_s is None else min(
            self.n_window, max(int(round(min_window_s / dt)), 4 * orders.n_params))
        self.n_guard = max(0, int(round(settle_guard_s / dt)))
        self.dc_decay = dc_decay  # per sample, of the DC blocker before the window (None: its transient stays)
        # d**k for k = 0 .. n_window - 1: the transient's regressor of a segment of any length (see _last)
        self._decay_k = None if dc_decay is None else float(dc_decay) ** np.arange(self.n_window)
        self._steady_since: int | None = None  # sample count at which the current steady stretch began
        self._cut: int | None = None  # sample count before which the window holds another system (see cut)
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
        self.fit_first = -1  # stream count of the first sample of the current fit
        self.fit_newest = False  # the current fit took only the newest min_window_s of a longer segment
        self._before: tuple | None = None  # the fit before a fit of the newest seconds (see settle_newest)
        self.current = False  # the last refit attempt succeeded on a steady, excited window
        self.reason = "window filling"
        self.auto = auto  # refit inside push(); otherwise the owner calls refit() when it suits (``due``)
        self.due = False
        self.n_fits = 0
        self.n_cold = 0
        self.n_failed = 0
        self._generation = 0  # counts clear(): a job prepared before a clear is stale

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
        if self._count < self.n_min or self._since < self.n_refit:
            return False
        self._since = 0
        self.due = True
        if self.auto:
            self.refit()
        return True

    def refit(self) -> None:
        """Run the refit that is due, here and now (a no-op when none is)."""
        self._run(self.prepare())

    def clear(self) -> None:
        """Forget the window (after a gap): the next fit needs ``min_window_s`` (and the guard) of new samples."""
        self._count = 0
        self._since = 0
        self._pos = 0
        self._steady_since = None
        self._cut = None
        self._generation += 1
        self.due = False
        self.current = False
        self.reason = "window filling"

    # -- fitting ----------------------------------------------------------------------------------
    def window(self) -> np.ndarray:
        """The window, oldest sample first: rows y, u, engine speed [rad/s], load [Nm]."""
        return np.roll(self._buf, -self._pos, axis=1)

    @property
    def steady_s(self) -> float:
        """Seconds the engine speed has been steady (less ``settle_guard_s``) as of the last refit, 0 if unknown;
        it keeps growing past the window's length while the speed stays (see :meth:`_segment`)."""
        if self._steady_since is None:
            return 0.0
        return max(0.0, (self._count - self._steady_since - self.n_guard) * self.dt)

    def _segment(self) -> tuple[int, float]:
        """How many of the newest samples to fit (0: none yet), and the speed span [rad/s] of the window.

        The steady stretch is the longest run of newest half-second blocks whose means lie within
        ``max_speed_span_rpm`` of each other; where it covers the whole window it continues the stretch
        found before. The segment is the stretch less ``settle_guard_s``, at most the window, and none
        while that is shorter than ``min_window_s`` (see the module notes).
        """
        n_avail = min(self._count, self.n_window)
        nb = n_avail // self.n_block
        if nb == 0:
            return 0, 0.0
        n = np.roll(self._buf[2], -self._pos)  # the engine speed, oldest first (the other rows are not needed)
        means = n[self.n_window - nb * self.n_block:].reshape(nb, self.n_block).mean(axis=1)
        lo = hi = float(means[-1])
        k = 0
        for m in means[::-1]:  # newest first: the steady suffix
            lo, hi = min(lo, float(m)), max(hi, float(m))
            if hi - lo > self.max_span_rad_s:
                break
            k += 1
        if k < nb:
            self._steady_since = self._count - k * self.n_block
        elif self._steady_since is None or self._steady_since > self._count - n_avail:
            self._steady_since = self._count - n_avail  # steady since the window began, or since the start
        span = float(np.ptp(means))
        usable = min(n_avail, self._count - self._steady_since - self.n_guard)
        if self._cut is not None:
            usable = min(usable, self._count - self._cut)
        return (usable if usable >= self.n_min else 0), span

    def _last(self, n_fit: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """The newest ``n_fit`` samples of the window: y, u (each less its DC blocker's transient), engine
        speed, load."""
        y, u, n, load = self.window()[:, self.n_window - n_fit:]
        if self._decay_k is not None:
            # the DC blocker's initial state decays as d**k in both signals: remove a + b d**k (module notes)
            X = np.column_stack((np.ones(n_fit), self._decay_k[:n_fit]))
            coef, *_ = np.linalg.lstsq(X, np.column_stack((y, u)), rcond=None)
            y, u = (np.column_stack((y, u)) - X @ coef).T
        return y, u, n, load

    def cut(self, first: int) -> None:
        """The samples before stream count ``first`` belong to another system: fit none of them again.

        The segment then grows from ``first`` as it does after a change of operating point.
        """
        self._cut = first if self._cut is None else max(self._cut, first)

    def prepare(self, starts: tuple = (), cold: bool = False, newest: bool = False) -> RefitJob | None:
        """The due refit as a job (None when none is due or the window is not steady and excited).

        ``starts``: further starts of a cold fit (e.g. the last solution whose estimate was valid: the
        driveline is the same at another operating point); ``cold``: a cold fit, from the current solution
        among the others, even where a warm one would do (see the module notes); ``newest``: fit only the
        newest ``min_window_s`` of a longer segment (the job says so; see :meth:`cut`).
        """
        if not self.due:
            return None
        self.due = False
        if self._count < self.n_min:
            return None
        n_fit, span = self._segment()
        if n_fit == 0:
            if span > self.max_span_rad_s:  # else the window is still filling after a start or a gap
                self.current = False
                self.reason = f"speed not steady ({span * 30 / np.pi:.0f} rpm in the window)"
            return None
        newest = newest and n_fit > self.n_min
        if newest:
            n_fit = self.n_min
        y, u, n, load = self._last(n_fit)
        speed_rpm = float(np.mean(n)) * 30.0 / np.pi
        if float(np.std(u)) < self.min_excitation_nm:
            self.current = False
            self.reason = "torque excitation too low"
            return None
        moved = (not np.isfinite(self.fit_speed_rpm)
                 or abs(speed_rpm - self.fit_speed_rpm) > 0.5 * self.max_span_rad_s * 30.0 / np.pi)
        if self._start is None or moved or not self.current or cold:
            mode, starts = "cold", (tuple(starts) if moved else (self._start, *starts))
        else:
            mode, starts = "warm", (self._start,)
        return RefitJob(y, u, self.orders, mode, starts, float(np.mean(load)), speed_rpm, self._generation,
                        self.warm_iterations, self.warm_tol, first=self._count - n_fit, newest=newest)

    def prepare_verify(self, starts: tuple = (), prefer_last_within: float = 0.0) -> RefitJob | None:
        """A multi-start refit of the current segment as a job (None if there is none or the fit is not current).

        The starts: Hannan-Rissanen, the recursive estimate, the current
        solution and ``starts`` (e.g. the solution the baseline was learned
        with); the fit of lowest loss is adopted by :meth:`complete`, or the
        one from the last of ``starts`` if its loss is within
        ``prefer_last_within`` of it (:func:`fit_two_starts`). Used
        before a baseline cell is learned and before an alarm is raised (see
        :class:`~online_id.monitoring.detection.ChangeDetector`, *confirm*);
        about 0.5 s, rare.
        """
        if self._count < self.n_min or not self.current:
            return None
        n_fit, _span = self._segment()
        if n_fit == 0:
            return None
        y, u, n, load = self._last(n_fit)
        return RefitJob(y, u, self.orders, "verify", (self._start, *starts), float(np.mean(load)),
                        float(np.mean(n)) * 30.0 / np.pi, self._generation, prefer_last_within=prefer_last_within)

    def complete(self, job: RefitJob, fit: ArmaxFit | None, error: str | None = None) -> bool:
        """Adopt the result of ``job`` (from :func:`solve`); returns True when a fit was adopted.

        ``error`` is the description of a failed fit.  A job of a window that
        was cleared since it was prepared is discarded.
        """
        if job.generation != self._generation:
            return False
        failed = error if error is not None else (None if fit is not None and _finite(fit) else "not finite")
        if job.mode == "verify":
            if failed is not None:
                return False
            # a multi-start fit of the whole segment supersedes a fit of the newest seconds not judged yet (with the
            # process worker a check can start between a probe's return and the next estimate)
            self.fit_newest, self._before = False, None
            self._adopt(fit, job.load_nm)
            self.n_cold += 1
            return True
        if failed is not None:
            self.n_failed += 1
            self.current = False
            self.reason = f"fit failed: {failed}"
            return False
        if job.mode == "cold":
            self.n_cold += 1
        self._before = (self.fit, self._start, self.fit_load_nm, self.fit_speed_rpm, self.fit_first) \
            if job.newest and self.fit is not None else None
        self._adopt(fit, job.load_nm)
        self.fit_first, self.fit_newest = job.first, job.newest
        self.fit_speed_rpm = job.speed_rpm
        self.current = True
        self.reason = ""
        return True

    def settle_newest(self, cut: bool) -> bool:
        """Judge the current fit of the newest seconds (``prepare(newest=True)``): with ``cut`` (the caller found
        its estimate valid and different) the samples before it are :meth:`cut`; else the fit before it is current
        again. True if it reverted."""
        if not self.fit_newest:
            return False
        self.fit_newest = False
        if cut:
            self.cut(self.fit_first)
            return False
        if self._before is None:
            return False
        self.fit, self._start, self.fit_load_nm, self.fit_speed_rpm, self.fit_first = self._before
        self._before = None
        self.n_fits += 1  # another current fit: its poles are computed again
        return True

    def _run(self, job: RefitJob | None) -> bool:
        """Solve and complete ``job`` here and now."""
        return False if job is None else self.complete(job, *solve_or_error(job))

    def _adopt(self, fit: ArmaxFit, load_nm: float) -> None:
        """``fit`` of the window whose mean raw torque is ``load_nm`` becomes the current solution."""
        self.fit = fit
        self._start = fit.theta
        self.fit_load_nm = float(load_nm)
        self.n_fits += 1

    # -- persistence --------------------------------------------------------------------------------
    def get_state(self) -> dict:
        """What a restart keeps: the last solution (a start of the first fit after the restart)."""
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
