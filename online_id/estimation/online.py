"""Streaming driveline estimator: one sample in, estimate out (no I/O).

Notes
-----
Per input sample (dyno speed :math:`y`, dyno torque :math:`u`, engine speed
:math:`n`), at the input rate:

1. causal anti-alias FIR and decimation by ``factor`` (the same filter on
   :math:`y` and :math:`u`, so the transfer function :math:`B/A` between them
   is unchanged; only the noise model sees it);
2. a DC blocker :math:`x_{hp} = x - \\bar x`, with :math:`\\bar x` an
   exponential mean of time constant ``dc_tau_s``, on both signals: the
   offsets (friction torque, set speed) vanish as in the seed paper, also
   when the operating point moves;
3. one step of recursive extended least squares ARMAX with forgetting
   (:class:`~online_id.estimation.rels.RecursiveArmax`); adaptation freezes while
   the exponentially weighted torque variance is below
   ``min_excitation_nm**2``;
4. the sample enters a sliding window; every ``refit_s`` seconds the ARMAX
   model is refitted to the window by prediction-error minimisation, started
   from the previous solution (:class:`~online_id.estimation.window.SlidingPem`:
   the seed paper's recursive-start-then-PEM, run continuously). The
   recursive estimate alone wanders by about +-2 % in :math:`f_0` on a bench
   (see that module's notes); the refit is within about 0.05 %. After a
   change of operating point the refit takes the samples since the speed
   became steady, from ``min_window_s`` on (less ``settle_guard_s``, and
   less the DC blocker's decaying transient), growing to ``window_s``; a cold
   refit also starts from the last solution whose estimate was valid, and
   every other refit is cold while the estimate is not valid or its
   resonance has just moved by more than ``MOVED_REL`` (0.5 %). In a steady
   stretch longer than the window, where a valid estimate moved so, the next
   refit takes only the newest ``min_window_s``, and so does every other
   refit after one stopped being valid, until it is valid again; where the
   estimate of such a fit is valid, and differs from a valid estimate of
   the long window by more than ``NEWEST_SIGMAS`` standard deviations, the
   window forgets the samples before it (a change of the driveline: the
   window held two systems), else the fit before it serves on (see
   :mod:`~online_id.estimation.window`).

:meth:`OnlineDriveline.estimate` (called at the publish rate, not per
sample) takes the poles of :math:`A` of the latest refit (of the recursive
model while no current refit exists; such an estimate is never valid),
drops the ones on an engine order line at the current engine speed, and
picks the driveline pair: of the pairs within 15 % of the previous pick
(else of the lowest-frequency lightly damped pair in the band), the one
with the largest residue in :math:`B/A`
(:func:`~online_id.analysis.poles.modal_residue`). It is valid when the refit is
current (steady speed, enough torque excitation), the pole's own standard
deviations (from the fit's covariance) are small and no second pair lies
within 5 % of it (a split mode, seen with backlash: neither pole is the
resonance).
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from scipy.signal import firwin

from online_id.estimation.model import ArmaxOrders
from online_id.estimation.pem import fpe_criterion
from online_id.analysis.physical import (
    DrivelineParameters,
    fit_response,
    frequency_response,
    parameters,
    response_grid,
)
from online_id.analysis.poles import Pole, modal_residue, order_of, pole_std, poles_of_roots, polynomial_roots
from online_id.estimation.rels import RecursiveArmax
from online_id.estimation.window import RefitJob, SlidingPem, solve_or_error
from online_id.errors import EstimationError


MOVED_REL = 0.005  # a resonance that moved this much between refits makes the next refit cold (see refit_job)
NEWEST_SIGMAS = 3.0
"""A fit of the newest seconds cuts a window whose estimate was valid only where its resonance differs from that
estimate's by more than this many standard deviations of the difference (both estimates' own, combined). Traced
on a simulated shaft with backlash: its 10 s fits hop between minima 1-2 %
apart, each hop probed the newest 5 s, and the probes, valid and within one standard deviation of the long fit,
cut the window seven times in 35 s; the 5 s windows then sat 2.3 % low and raised two false warnings. A
stiffness loss entering the window differed by 3-10 standard deviations on the simulated benches."""


class StreamDecimator:
    """Causal FIR low-pass and decimation of several channels, sample by sample.

    The channels' samples are written into a long buffer, one column per sample: the filter's input is the view
    of its newest ``taps`` columns (oldest first), and only every ``_SPAN``-th sample moves the newest columns back
    to the buffer's start (one copy in place of a shift of the whole filter per sample)."""

    _SPAN = 1024  # samples written between two moves of the buffer

    def __init__(self, factor: int, n_channels: int, taps_per_factor: int = 8) -> None:
        self.factor = int(factor)
        if self.factor > 1:
            n = taps_per_factor * self.factor + 1
            self.h = firwin(n, 0.8 / self.factor)[::-1].copy()  # reversed: dot with oldest-first buffer
        else:
            n = 1
            self.h = np.ones(1)
        self.taps = n
        self._long = np.zeros((n_channels, n + self._SPAN))
        self._end = n  # the newest ``taps`` samples are columns end - taps .. end - 1
        self.phase = 0
        self._empty = True

    @property
    def buf(self) -> np.ndarray:
        """The filter's input: the newest ``taps`` samples of every channel, oldest first (a view)."""
        return self._long[:, self._end - self.taps:self._end]

    def push(self, values) -> np.ndarray | None:
        """Add one sample of every channel; every ``factor``-th call returns the filtered sample."""
        col = self._column()
        if self._empty:
            self.buf[:] = np.asarray(values, dtype=float)[:, None]  # start as if constant before: no transient
            self._empty = False
        self._long[:, col] = values
        return self._output()

    def push3(self, a: float, b: float, c: float) -> np.ndarray | None:
        """:meth:`push` of one sample of three channels, given as floats (the estimator's per-sample call, with
        :meth:`_column` and :meth:`_output` written out)."""
        end, n, long = self._end, self.taps, self._long
        if end == long.shape[1]:
            long[:, :n - 1] = long[:, end - n + 1:end]
            end = n - 1
        self._end = end + 1
        if self._empty:
            long[:, end + 1 - n:end + 1] = np.array(((a,), (b,), (c,)), dtype=float)  # (see push)
            self._empty = False
        long[0, end] = a
        long[1, end] = b
        long[2, end] = c
        phase = self.phase + 1
        if phase < self.factor:
            self.phase = phase
            return None
        self.phase = 0
        return long[:, end + 1 - n:end + 1].dot(self.h)  # (ndarray.dot: the same product as @, called faster)

    def _column(self) -> int:
        """The column of the next sample, the buffer moved first where it is full."""
        end, n, long = self._end, self.taps, self._long
        if end == long.shape[1]:
            long[:, :n - 1] = long[:, end - n + 1:end]
            end = n - 1
        self._end = end + 1
        return end

    def _output(self) -> np.ndarray | None:
        self.phase += 1
        if self.phase < self.factor:
            return None
        self.phase = 0
        return self.buf.dot(self.h)

    def reset(self) -> None:
        self._long[:] = 0.0
        self._end = self.taps
        self.phase = 0
        self._empty = True


@dataclass(frozen=True)
class OnlineEstimate:
    """What the online estimator knows at one moment."""

    f0_hz: float
    zeta: float
    valid: bool
    f0_std_hz: float
    zeta_std: float
    residual_rms: float
    fpe: float
    excitation_nm: float
    samples_used: int
    frozen: bool
    poles: tuple[Pole, ...]
    source: str = "recursive"  # "window": the sliding-window refit; "recursive": RELS only (never valid)
    why: str = ""  # why the window refit is not current (empty when it is)
    load_nm: float = float("nan")  # mean dyno torque over the fitted window (the load of the operating point)


class OnlineDriveline:
    """The streaming estimator (see module notes)."""

    def __init__(
        self,
        orders: ArmaxOrders,
        *,
        input_rate_hz: float,
        model_rate_hz: float,
        forgetting: float,
        p0: float = 1e3,
        min_excitation_nm: float = 1.0,
        learning_s: float = 10.0,
        pulses_per_rev: float | None = None,
        band_hz: tuple[float, float] = (3.0, 120.0),
        dc_tau_s: float = 1.0,
        window_s: float = 10.0,
        min_window_s: float | None = 5.0,
        settle_guard_s: float = 1.0,
        refit_s: float = 1.0,
        max_speed_span_rpm: float = 40.0,
        auto_refit: bool = True,
    ) -> None:
        factor = max(1, int(np.floor(input_rate_hz / model_rate_hz + 1e-9)))
        self.dt = factor / input_rate_hz
        self.decimator = StreamDecimator(factor, 3)
        self.rels = RecursiveArmax(orders, lam=forgetting, p0=p0, min_excitation=min_excitation_nm**2)
        self.window = SlidingPem(orders, self.dt, window_s=window_s, refit_s=refit_s,
                                 max_speed_span_rpm=max_speed_span_rpm, min_excitation_nm=min_excitation_nm,
                                 auto=False, min_window_s=min_window_s, settle_guard_s=settle_guard_s,
                                 dc_decay=1.0 - self.dt / dc_tau_s)
        self.auto_refit = auto_refit  # refit inside update(); else the owner runs refit_job() (a worker)
        self.orders = orders
        self.forgetting = forgetting
        self.p0 = p0
        self.learning_n = int(round(learning_s / self.dt))
        self.pulses_per_rev = pulses_per_rev
        self.band_hz = (band_hz[0], min(band_hz[1], 0.4 / self.dt))
        self.alpha_dc = self.dt / dc_tau_s
        self.alpha_stat = max(1.0 - forgetting, 1e-4)
        self.alpha_e2 = self.dt / 2.0  # the noise level: a 2 s memory is enough and forgets the start-up
        self._mean_y = self._mean_u = 0.0  # the DC blocker's means of y and u
        self._mean_ready = False
        self._e2 = 0.0
        self._u2 = 0.0
        self._n_used = 0
        self._speed = 0.0
        self._pick: float | None = None
        self._pick_std = float("inf")  # the standard deviation of the picked resonance [Hz]
        self._valid = False
        self._good: np.ndarray | None = None  # the window solution of the last valid estimate
        self._last_cold = False
        self._valid_then = False  # the estimate was valid when the previous refit was prepared
        self._fell = False  # a valid estimate stopped being valid in a long steady stretch (see refit_job)
        self._last_newest = False  # the last refit took the newest seconds only
        self._pick_then: float | None = None  # the resonance picked when the previous refit was prepared
        self._poles_key: tuple | None = None
        self._memo: dict = {}  # per window fit: pole -> residue, std (see _cached)
        self._poles: list[Pole] = []
        self._roots = np.zeros(0, dtype=complex)  # the roots of A those poles come from
        self._std_due: tuple | None = None  # (A, pole, covariance): a deferred standard deviation, see estimate
        self._recursive: tuple | None = None  # (rels, its samples and noise variance, its polynomials()): see there

    # -- per sample ---------------------------------------------------------------------------
    def update(self, dyno_speed: float, engine_speed: float, dyno_torque: float) -> None:
        """One input sample in SI units (rad/s, rad/s, Nm braking positive)."""
        out = self.decimator.push3(dyno_speed, dyno_torque, engine_speed)
        if out is None:
            return
        y, u, n = out.tolist()
        self._speed = n
        if not self._mean_ready:
            self._mean_y, self._mean_u = y, u
            self._mean_ready = True
        alpha = self.alpha_dc
        my = self._mean_y = self._mean_y + alpha * (y - self._mean_y)  # xbar <- xbar + dt/tau (x - xbar)
        mu = self._mean_u = self._mean_u + alpha * (u - self._mean_u)
        y_hp, u_hp = y - my, u - mu
        rels = self.rels
        e = rels.update(y_hp, u_hp)  # a-priori prediction error
        if math.isfinite(e) and not rels.frozen:
            self._n_used += 1
            a = max(self.alpha_e2, 1.0 / self._n_used)  # running mean first, then exponential
            self._e2 += a * (e * e - self._e2)
        self._u2 += self.alpha_stat * (u_hp * u_hp - self._u2)
        if self.window.push(y_hp, u_hp, n, u) and self.auto_refit:
            self._refit_here()

    def restart_history(self) -> None:
        """After a gap in the input: restart filters and regressors, keep theta and P."""
        state = self.rels.get_state()
        for key in ("y_hist", "u_hist", "eps_hist"):
            state[key] = np.zeros_like(state[key])
        self.rels = RecursiveArmax.from_state(state)
        self.decimator.reset()
        self.window.clear()
        self._mean_ready = False

    @property
    def refit_due(self) -> bool:
        """A window refit is due (only without ``auto_refit``; see :meth:`refit_job`)."""
        return self.window.due

    def refit_job(self) -> RefitJob | None:
        """The due window refit as a job for :func:`~online_id.estimation.window.solve` (None: nothing to fit).

        A cold fit also starts from the last solution whose estimate was valid. Every other refit is cold
        while the estimate is not valid or its resonance moved by more than ``MOVED_REL`` since the refit
        before: a warm-started fit can stay for many seconds in a minimum whose resonance is poorly
        determined (seen after a change of operating point), or follow a step of the stiffness only slowly
        (13 s for a 20 % loss on one simulated bench, 10 s with the cold refits)."""
        jumped = (self._pick is not None and self._pick_then is not None
                  and abs(self._pick - self._pick_then) > MOVED_REL * self._pick_then)
        self._pick_then = self._pick
        w = self.window
        # a change of the driveline in a steady stretch longer than the window (not the settling after a change of
        # operating point): the newest seconds, where the estimate moved, and every other refit while not valid
        long = w.current and w.steady_s >= w.window_s
        self._fell = long and not self._valid and (self._fell or self._valid_then)
        self._valid_then = self._valid
        cold = w.current and (not self._valid or jumped) and not self._last_cold
        newest = long and ((self._valid and jumped) or (self._fell and not self._last_newest))
        job = w.prepare(starts=(self._good,), cold=cold, newest=newest)
        if job is not None:
            self._last_cold, self._last_newest = job.mode == "cold", job.newest
        return job

    def _refit_here(self) -> None:
        """The due refit (:meth:`refit_job`), solved and adopted here and now (``auto_refit``)."""
        job = self.refit_job()
        if job is not None:
            self.complete(job, *solve_or_error(job))

    def verify_job(self, starts: tuple = (), prefer_last_within: float = 0.0) -> RefitJob | None:
        """A multi-start refit of the current segment as a job (None: there is none, or the fit is not current)."""
        return self.window.prepare_verify(starts, prefer_last_within)

    def complete(self, job: RefitJob, fit, error: str | None = None) -> bool:
        """Adopt the result of a refit or verify job; True when a fit was adopted.

        A new fit's poles, and each candidate's residue and standard deviations, are computed here, when
        it is adopted (on a sample that publishes nothing), not at the next publication, which the receive
        loop owes the bus within a millisecond; the publications reuse them until the next fit.
        """
        adopted = self.window.complete(job, fit, error)
        if adopted:
            a, b, _c, cov_a, _V, source = self.polynomials()
            if source == "window":
                for p in self._candidates(self._poles_for(a, source)):
                    self._cached("residue", p.z, source, lambda: modal_residue(a, b, p.z, self._roots))
                    self._cached("std", p.z, source, lambda: pole_std(a, p.z, cov_a, self.dt))
        return adopted

    @property
    def solution(self) -> np.ndarray | None:
        """Parameters of the current window fit (None while there is none)."""
        w = self.window
        return w.fit.theta.copy() if w.current and w.fit is not None else None

    # -- at the publish rate --------------------------------------------------------------------
    @property
    def speed_rpm(self) -> float:
        return self._speed * 30.0 / np.pi

    def polynomials(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, float, str]:
        """(A, B, C, covariance of the A coefficients, noise variance, source) of the current model."""
        na = self.orders.na
        w = self.window
        if w.current and w.fit is not None:
            return w.fit.A, w.fit.B, w.fit.C, w.fit.covariance[:na, :na], w.fit.V, "window"
        # the recursive model's, once per model: it changes only where an input sample completes a model sample
        # (``rels.update``, which counts its samples) or the estimator is replaced (restart, a loaded state); the
        # publication's estimate then finds those of the sample before it (see prepare_estimate)
        rels, e2 = self.rels, self._e2
        key = (rels.n_samples, e2)
        memo = self._recursive
        if memo is None or memo[0] is not rels or memo[1] != key:
            a, b, c = rels.polynomials()
            memo = self._recursive = (rels, key, (a, b, c, e2 * rels.P[:na, :na], e2, "recursive"))
        return memo[2]

    def _poles_for(self, a: np.ndarray, source: str) -> list[Pole]:
        """Poles of ``a``; a window refit's are computed once (refits come once a second, estimates at 10 Hz), the
        recursive model's once per model (it changes at the model rate, not at every input sample, and not while
        adaptation is frozen: see :meth:`prepare_estimate`)."""
        key = (source, self.window.n_fits) if source == "window" else (source, a.tobytes())
        if self._poles_key != key:
            finite = bool(np.all(np.isfinite(a)))
            self._roots = polynomial_roots(a) if finite else np.zeros(0, dtype=complex)
            self._poles = poles_of_roots(self._roots, self.dt) if finite else []
            self._poles_key = key
            self._memo = {}
        return self._poles

    def prepare_estimate(self) -> None:
        """The current model's poles, computed now for an estimate due before the model changes.

        The live service calls it on the sample before a publication: a publication's estimate is of the
        model as its sample finds it (the pipeline updates the model with that sample after the estimate),
        so it finds its poles done (:meth:`_poles_for`).  Nothing else changes: the estimate is the same
        with or without it.
        """
        a, _b, _c, _cov, _V, source = self.polynomials()
        self._poles_for(a, source)

    def estimate_ahead(self) -> tuple[OnlineEstimate, Callable[[], None]] | None:
        """The next estimate (:meth:`estimate` with ``defer_std``), made now, and the undo that puts the estimator
        back as if it had not been made; None where no undo is possible (a fit of the newest seconds, whose
        estimate settles the window), after :meth:`prepare_estimate`.

        The live service makes a publication's estimate on the sample before it, after that sample's update:
        the model the publication's sample finds.  The publication then takes it, if nothing touched the
        estimator since, or calls the undo and :meth:`estimate` afresh: the estimate is the same either way.
        """
        if self.window.fit_newest:
            self.prepare_estimate()
            return None
        kept = (self._pick, self._pick_std, self._valid, self._good, self._std_due)  # what estimate() changes

        def undo() -> None:
            self._pick, self._pick_std, self._valid, self._good, self._std_due = kept

        return self.estimate(defer_std=True), undo

    def _cached(self, what: str, z: complex, source: str, compute):
        """``compute()`` once per window fit and pole (``what``: residue, std); every time for the recursive model.

        A window fit's polynomials and covariance stay the same until the next refit (once a second) while
        estimates are published at 10 Hz: the publication, which the receive loop owes the bus within a
        millisecond, reuses them.
        """
        if source != "window":
            return compute()
        k = (what, z)
        if k not in self._memo:
            self._memo[k] = compute()
        return self._memo[k]

    def _candidates(self, poles: list[Pole]) -> list[Pole]:
        rpm = self.speed_rpm
        out = []
        for p in poles:
            if p.kind != "complex" or not (self.band_hz[0] <= p.f_hz <= self.band_hz[1]) or not (0.0 < p.zeta < 0.4):
                continue
            order = order_of(p.f_hz, rpm) if p.zeta < 0.05 else None
            if order is not None and (self.pulses_per_rev is None or abs(order - self.pulses_per_rev) < 1e-9
                                      or p.zeta < 0.01):
                continue  # on an engine order line: a speed-dependent pole
            out.append(p)
        return out

    def estimate(self, defer_std: bool = False) -> OnlineEstimate:
        """The current driveline estimate (see module notes).

        ``defer_std``: an estimate of the recursive model (never valid, so its pole's standard deviations
        decide nothing) comes without them (inf) until :meth:`complete_estimate` is given it: the receive loop sends the
        estimate's frame first (a window fit's are computed once per fit and come at once).
        """
        if self._std_due is not None:
            self._std_done()
        if not self.window.fit_newest:
            return self._estimate(defer_std)
        # a fit of the newest seconds: where its estimate is valid, and differs from the long window's valid estimate
        # by more than both their uncertainties allow, the window forgets the older samples, else the fit before it
        # serves again, as if it had not run (see SlidingPem.settle_newest and NEWEST_SIGMAS)
        pick, std, valid, good = self._pick, self._pick_std, self._valid, self._good
        est = self._estimate()
        cut = est.valid and (not valid or pick is None or abs(est.f0_hz - pick) > NEWEST_SIGMAS * float(
            np.hypot(est.f0_std_hz, std)))
        if self.window.settle_newest(cut):
            self._pick, self._pick_std, self._valid, self._good = pick, std, valid, good
            est = self._estimate()
        return est

    def complete_estimate(self, est: OnlineEstimate) -> OnlineEstimate:
        """``est`` (of :meth:`estimate` with ``defer_std``) with its standard deviations, as :meth:`estimate`
        gives it without (call before the next sample)."""
        if self._std_due is None:
            return est
        std_f, std_z = self._std_done()
        return dataclasses.replace(est, f0_std_hz=std_f, zeta_std=std_z)

    def _std_done(self) -> tuple[float, float]:
        a, z, cov_a = self._std_due
        self._std_due = None
        std_f, std_z = pole_std(a, z, cov_a, self.dt)
        self._pick_std = std_f
        return std_f, std_z

    def _estimate(self, defer_std: bool = False) -> OnlineEstimate:
        a, b, _c, cov_a, V, source = self.polynomials()
        poles = self._poles_for(a, source)
        cands = self._candidates(poles)
        pick = None
        if cands:
            # the pairs within 15 % of the previous pick (else of the lowest pair); of these the dominant
            # mode, the one with the largest residue in B/A: a mismatched model (backlash) can split the
            # resonance into the mode and a lightly damped pole nearly cancelled by a zero beside it
            ref = self._pick
            near = [p for p in cands if ref is not None and abs(p.f_hz - ref) <= 0.15 * ref]
            if not near:
                ref = min(p.f_hz for p in cands)
                near = [p for p in cands if p.f_hz <= 1.15 * ref]
            pick = near[0] if len(near) == 1 else max(
                near, key=lambda p: self._cached("residue", p.z, source, lambda: modal_residue(a, b, p.z, self._roots)))
        # two pairs within 5 % of each other at the resonance: the model splits the mode, neither is it
        split = pick is not None and any(p is not pick and abs(p.f_hz - pick.f_hz) < 0.05 * pick.f_hz for p in cands)
        d = self.orders.n_params
        if source == "window":
            fpe = self.window.fit.fpe
        else:
            n_eff = min(self._n_used, int(1.0 / max(1.0 - self.forgetting, 1e-9)))
            fpe = fpe_criterion(V, n_eff, d) if n_eff > d else float("nan")
        std_f = std_z = float("inf")
        if pick is not None:
            self._pick = pick.f_hz
            if defer_std and source != "window":
                self._std_due = (a, pick.z, cov_a)  # not valid whatever they are (see the condition below)
            else:
                std_f, std_z = self._cached("std", pick.z, source, lambda: pole_std(a, pick.z, cov_a, self.dt))
                self._pick_std = std_f
        # valid when the model's own uncertainty is small; leaving needs twice the uncertainty (hysteresis)
        k = 2.0 if self._valid else 1.0
        self._valid = (
            pick is not None
            and source == "window"
            and self._n_used >= self.learning_n
            and not self.rels.frozen
            and not split
            and std_f <= k * 0.005 * pick.f_hz
            and std_z <= k * 0.15 * pick.zeta
        )
        if self._valid:
            self._good = self.window.fit.theta
        return OnlineEstimate(
            pick.f_hz if pick else float("nan"),
            pick.zeta if pick else float("nan"),
            self._valid,
            std_f,
            std_z,
            float(np.sqrt(V)),
            float(fpe),
            float(np.sqrt(self._u2)),
            self._n_used,
            self.rels.frozen,
            tuple(poles),
            source,
            "two poles at the resonance (mode split)" if split and not self.window.reason else self.window.reason,
            self.window.fit_load_nm if source == "window" else self._mean_u,
        )

    def physical_job(self, est: OnlineEstimate, J1: float | None, J2: float | None,
                     J_total: float | None) -> tuple | None:
        """Arguments of :func:`physical_parameters` for the current estimate (None without a resonance)."""
        if not np.isfinite(est.f0_hz):
            return None
        a, b = self.polynomials()[:2]
        others = tuple(p for p in est.poles if abs(p.f_hz - est.f0_hz) > 1e-9)
        return (np.array(a), np.array(b), self.dt, est.f0_hz, est.zeta, others, J1, J2, J_total)

    def physical(self, est: OnlineEstimate, J1: float | None, J2: float | None,
                 J_total: float | None) -> DrivelineParameters | None:
        """Physical parameters of the current estimate, here and now (see :func:`physical_parameters`)."""
        job = self.physical_job(est, J1, J2, J_total)
        return None if job is None else physical_parameters(*job)

    # -- persistence ----------------------------------------------------------------------------
    def get_state(self) -> dict:
        return {
            "rels": self.rels.get_state(),
            "pick": self._pick,
            "valid": self._valid,
            "e2": self._e2,
            "u2": self._u2,
            "n_used": self._n_used,
            "window": self.window.get_state(),
        }

    def load_state(self, state: dict) -> None:
        rels = RecursiveArmax.from_state(state["rels"])
        if rels.orders != self.orders:
            raise EstimationError(f"saved model orders {rels.orders} differ from the configured {self.orders}")
        self.rels = rels
        self._pick = state.get("pick")
        self._valid = bool(state.get("valid", False))
        self._e2 = float(state.get("e2", 0.0))
        self._u2 = float(state.get("u2", 0.0))
        self._n_used = int(state.get("n_used", 0))
        self.window.load_state(state.get("window", {}))
        self.decimator.reset()
        self._mean_ready = False


def physical_parameters(a: np.ndarray, b: np.ndarray, dt: float, f0_hz: float, zeta: float,
                        other_poles: tuple[Pole, ...], J1: float | None, J2: float | None,
                        J_total: float | None) -> DrivelineParameters | None:
    """Physical parameters from the resonance and the model ``B/A`` (pure: runs in a worker process too).

    With ``J1`` and ``J2`` given, only the resonance is used; otherwise the
    anti-resonance and gain are fitted to the model's frequency response
    around the resonance (``other_poles`` are kept off the fitted grid).
    None when the fit fails.
    """
    if J1 is not None and J2 is not None:
        return parameters(f0_hz, zeta, None, None, J1=J1, J2=J2)
    f = response_grid(f0_hz, 0.5 / dt, list(other_poles))
    try:
        fit = fit_response(f, frequency_response(b, a, f, dt), f0_hz, zeta)
    except EstimationError:
        return None
    return parameters(f0_hz, zeta, fit.fa_hz, fit.gain, J1=J1, J2=J2, J_total=J_total)
