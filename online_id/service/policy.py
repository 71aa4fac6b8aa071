"""The detection policy of the pipeline: pole tracks, learned baselines per operating point, and the alarms
raised (see :mod:`online_id.monitoring` for the statistics themselves).

:class:`DetectionPolicy` is a part the :class:`~online_id.service.pipeline.Pipeline` owns.  It is handed
each publication's estimate with its stream time, engine speed and the estimator it came from
(:meth:`~DetectionPolicy.assess`), the input samples its backlash test takes (:meth:`~DetectionPolicy.keep_sample`),
the service state (:meth:`~DetectionPolicy.on_state`) and the commands (:meth:`~DetectionPolicy.acknowledge`,
:meth:`~DetectionPolicy.relearn`); it returns the alerts due, writes its events to the event log it is given
and records its alerts through the recorder it is given.  Its slow work (multi-start refits, rechecks,
backlash tests) goes to the worker it is given, whose results come back through the worker's callbacks.

Its parts: the baselines, the detector, the pole tracks and the engaged flank (:mod:`online_id.monitoring`);
what an estimate is compared with and the visits of operating points (:mod:`online_id.service.comparison`); the
backlash tests' samples and schedule (:mod:`online_id.service.backlash`); the checks before a drift alarm stands
and the reference solutions and windows they compare with (:mod:`online_id.service.confirmation`).  It saves and
restores them (:meth:`~DetectionPolicy.to_dict`, :meth:`~DetectionPolicy.load`)."""

from __future__ import annotations

import dataclasses
import math
from collections import deque
from typing import Callable

from online_id.diagnose.linearity import BacklashTest
from online_id.config import Settings
from online_id.monitoring.baseline import Baseline
from online_id.monitoring.cells import BandStats
from online_id.monitoring.detection import Alarm, ChangeDetector, correlation_for_window
from online_id.monitoring.engaged import EngagedChange, EngagedFlank, EngagedReading
from online_id.monitoring.tracks import PoleTracker
from online_id.estimation.online import OnlineDriveline, OnlineEstimate
from online_id.service.backlash import BacklashTests, engaged_alarm
from online_id.service.comparison import Comparison, against_text, is_own, versus_text
from online_id.service.confirmation import PENDING, AlarmChecks
from online_id.service.events import Event
from online_id.records import (
    AlertKind,
    AlertOut,
    Publication,
    ServiceState,
)


STEADY_S = 5.0  # learning needs the estimates this long ago within the dead bands (or 3 own stds), see _steady
SPREAD_RATIO_REPORTED = 5.0  # a learned spread this many times the estimator's own uncertainty is reported


class DetectionPolicy:
    """Detection on the estimates of a :class:`~online_id.service.pipeline.Pipeline` (see module notes).

    Parameters
    ----------
    settings
        The settings in force (``detection`` above all; the model's speed span and pulses per revolution,
        the input sample rate).
    dt
        The estimator's sample period [s] (the pole tracks' time base).
    worker
        Where slow work runs (:mod:`online_id.service.offload`): ``submit(lane, fn, args, done)`` and
        ``busy(lane)``.
    submit_window
        ``submit_window(fn, args, done)``: a multi-start refit to the worker's window lane, counted in the
        pipeline's lag of slow work.
    clock
        The stream time now (an alert raised when a backlash test comes back repeats from then).
    events
        The event log the policy appends to.
    record
        ``record(alert, out, data)``: keep, count and publish an alert (into ``out``).
    """

    def __init__(self, settings: Settings, dt: float, worker, submit_window: Callable, clock: Callable[[], float],
                 events: deque[Event], record: Callable) -> None:
        self.settings = settings
        self.worker = worker
        self._clock = clock
        self.events = events
        self._record = record
        d = settings.detection
        self.tracker = PoleTracker(dt=dt, pulses_per_rev=settings.model.pulses_per_rev)
        self.baseline = Baseline(band_rpm=d.band_rpm, min_count=d.min_count, load_band_nm=d.load_band_nm,
                                 pool_tolerance_f=d.pool_tolerance_pct / 100.0)
        self.run_label = ""  # the run learned cells are marked with (replay: the log's name)
        self.reference_run = False  # cells learned now are a reference (relearn --from LOG)
        self.detector = ChangeDetector(k=d.k, h_warning=d.h_warning, h_fault=d.h_fault,
                                       correlation_s=correlation_for_window(settings.model.window_s),
                                       min_change_f=d.min_freq_change_pct / 100.0,
                                       min_change_zeta=d.min_damping_change_pct / 100.0)
        # the engaged flank's readings on a shaft that showed backlash (see _test_backlash)
        self.engaged = EngagedFlank(dead_band_zeta=d.min_damping_change_pct / 100.0)
        self._state = ServiceState.STARTING  # the service state, as the pipeline last told (on_state)
        self._estimate: OnlineEstimate | None = None  # the estimate being judged (a learning refit replaces it)
        self._engaged_out: list[Publication] = []  # its alerts, published with the next detection
        self._healthy_since: float | None = None  # start of the current healthy stretch (settle_s)
        self._recent: deque[tuple[float, float, float]] = deque()  # (t_s, f0, zeta) of the healthy stretch
        self._healthy_rpm: float | None = None  # engine speed of the last healthy estimate
        # what an estimate is compared with; the visits of operating points and the first estimates of one
        self.comparison = Comparison(d)
        # the backlash tests: their input samples, their schedule, the tests done
        self.backlash = BacklashTests(d, settings.input.sample_rate_hz, settings.model.pulses_per_rev, worker)
        # the checks before a drift alarm stands, and the reference solutions and windows they compare with
        self.checks = AlarmChecks(d, worker, submit_window, events)
        self._next_learn: float | None = None
        self._next_alarm_repeat = 0.0
        self._stats: BandStats | None = None  # the baseline the latest estimate was compared with
        self._rejected = 0  # learning estimates not learned (they disagreed with the baselines)
        self._next_reject_event = 0.0

    # -- the interface ---------------------------------------------------------------------------
    def assess(self, est: OnlineEstimate, t_s: float, speed_rpm: float, model: OnlineDriveline) -> list[Publication]:
        """Pole tracks, baseline learning and change detection on the estimate ``est`` of a publication at
        stream time ``t_s`` and engine speed ``speed_rpm``, made by ``model`` (whose window the checks refit):
        the alerts due.  :attr:`estimate` is then ``est``, or the multi-start refit a new cell learned from."""
        self._estimate = est
        out: list[Publication] = []
        self._track_and_detect(est, t_s, speed_rpm, model, out)
        return out

    @property
    def estimate(self) -> OnlineEstimate | None:
        """The estimate last judged (a new cell's multi-start refit where one replaced the publication's)."""
        return self._estimate

    def keep_sample(self, t_s: float, dyno_speed: float, engine_speed: float, dyno_torque: float,
                    restart: bool = False) -> None:
        """An input sample, kept while a backlash test may run; ``restart``: the stream broke before it (the
        samples kept so far are dropped)."""
        wanted = self.baseline.backlash is None or self.settings.detection.engaged_flank
        self.backlash.keep(t_s, dyno_speed, engine_speed, dyno_torque, restart, wanted)

    def on_state(self, state: ServiceState) -> None:
        """The service state changed (detection and learning run on a tracking estimate only)."""
        self._state = state

    def on_time_jump(self) -> None:
        """The stream clock jumped: the schedules start again, and the estimate settles again before learning
        or detecting."""
        self._next_learn = None
        self._next_alarm_repeat = -math.inf
        self.backlash.on_time_jump()
        self.comparison.on_time_jump()
        self._next_reject_event = -math.inf
        self._healthy_since = None
        self._recent.clear()

    def acknowledge(self) -> None:
        """The operator acknowledged the alerts: latched alarms (the engaged flank's too) are released."""
        self.detector.acknowledge()
        self.engaged.acknowledge()

    def relearn(self) -> None:
        """Forget the baselines, their reference solutions and windows, the engaged flank and latched alarms
        (the RELEARN command, and ``relearn --from`` before its reference run)."""
        self.baseline.reset()
        self.checks.forget()
        self.comparison.visit_ref = None
        self.detector.reset()
        self.engaged.reset()

    @property
    def backlash_tests(self) -> int:
        """The backlash tests that came back."""
        return self.backlash.count

    @property
    def last_backlash_test(self) -> BacklashTest | None:
        """The last backlash test done."""
        return self.backlash.last

    @property
    def rejected(self) -> int:
        """Learning estimates not learned: they disagreed with the baselines."""
        return self._rejected

    def to_dict(self) -> dict:
        """What a restart keeps: baselines, detector (latched alarms), tracks, the engaged flank, the reference
        solutions and windows (the items of the state document, :mod:`online_id.service.persistence`)."""
        return {"baseline": self.baseline.to_dict(), "detector": self.detector.to_dict(),
                "tracker": self.tracker.to_dict(), "healthy_rpm": self._healthy_rpm,
                "engaged": self.engaged.to_dict(),
                **self.checks.to_dict()}

    def load(self, state: dict, n_params: int, new_run: bool = False) -> None:
        """Restore the items of :meth:`to_dict` from the state document ``state`` (solutions of ``n_params``
        model parameters).  ``new_run``: the state comes from an earlier run: the baselines, reference
        solutions and windows, the engaged flank and the detector's statistics and latched alarms are
        restored, the pole tracks and the detector's stream start afresh."""
        if "baseline" in state:
            self.baseline = Baseline.from_dict(state["baseline"])
        if "detector" in state:
            # statistics and latched alarms from the state, levels and dead bands from the config in force
            self.detector = ChangeDetector.from_dict({**state["detector"], "params": self.detector.params()})
            if new_run:
                self.detector.new_stream()
        if "tracker" in state and not new_run:
            self.tracker = PoleTracker.from_dict(state["tracker"])
        self.checks.load(state, n_params)
        self.engaged.load(state.get("engaged"))
        rpm = state.get("healthy_rpm")
        self._healthy_rpm = float(rpm) if isinstance(rpm, (int, float)) and not new_run else None

    # -- the policy ------------------------------------------------------------------------------
    def _track_and_detect(self, est: OnlineEstimate, t_s: float, speed: float, model: OnlineDriveline,
                          out: list[Publication]) -> None:
        """Pole tracks, baseline learning (1 Hz) and change detection, at the publish rate.

        ``est``, ``t_s`` and ``speed`` are those of the publication (it runs on the sample after it).
        """
        d = self.settings.detection
        load = est.load_nm
        self.tracker.update(t_s=t_s, speed_rpm=speed, poles=est.poles)
        healthy = (est.valid and not est.frozen and self._state == ServiceState.TRACKING
                   and est.excitation_nm >= d.min_excitation_nm)
        learnable = False
        settling = False
        # the first fits at a new operating point start cold and, where the model does not fit exactly
        # (backlash), may sit for a while in another local minimum: learning and detection wait settle_s
        # after the estimate becomes healthy at another speed than it last was
        if not healthy:
            self._healthy_since = None
            self._recent.clear()
        else:
            self._recent.append((t_s, est.f0_hz, est.zeta))
            while self._recent and self._recent[0][0] < t_s - STEADY_S - 1.0:
                self._recent.popleft()
            if self._healthy_since is None or t_s < self._healthy_since:
                same = (self._healthy_rpm is not None
                        and abs(speed - self._healthy_rpm) <= self.settings.model.max_speed_span_rpm)
                self._healthy_since = t_s - (d.settle_s if same else 0.0)
                if not same:
                    self.comparison.visit += 1
            self._healthy_rpm = speed
            # full detection resumes settle_detect_s after the estimate is healthy at the new point (the refit
            # window holds only the new point from its first fit on: what the wait covers is the first cold
            # refits); a deviation it sees then is confirmed by a multi-start refit before it is raised.
            # Before, only a change of the frequency beyond settle_min_freq_change_pct is detected (what a
            # local minimum does not do; a fault just before a change of point is then not held back by the
            # settle time); the damping waits. Learning waits the longer settle_s: a baseline must not hold a
            # transient, and a change that comes with the new point meets the detector first
            settled = t_s - self._healthy_since >= d.settle_detect_s
            settling = not settled
            learnable = t_s - self._healthy_since >= d.settle_s
        if self._next_learn is None or t_s < self._next_learn - 10.0:
            self._next_learn = t_s
        if (healthy and learnable and self.detector.active is None and t_s >= self._next_learn
                and self._steady(est, t_s)):
            self._next_learn = t_s + 1.0  # about one independent-ish estimate per second
            est = self._learn(est, t_s, speed, load, model)
            load = est.load_nm
        window_s = self.backlash.due(t_s, self.comparison.visit, self.baseline.nonlinear) if healthy else None
        if window_s is not None:
            self._test_backlash(t_s, speed, load, model, window_s)
        stats = self._baseline_for(speed, load)
        note = self.comparison.not_compared(self.baseline, t_s, speed, load) if stats is None and healthy else None
        if note is not None:
            self.events.append(note)
        if self.comparison.visit_serves(stats, self.baseline.nonlinear):
            self.comparison.sample_visit(est, t_s, speed, load, healthy and not settling, stats, model, self.baseline,
                                         self.detector)
            stats = self._with_visit(stats, load)
        self._stats = stats
        alarm = self.detector.update(
            t_s=t_s, speed_rpm=speed, f0_hz=est.f0_hz, zeta=est.zeta, f0_std_hz=est.f0_std_hz,
            zeta_std=est.zeta_std, baseline=stats, suppressed=not healthy,
            confirm=lambda kind: self._confirm(kind, stats, t_s, model),
            frequency_only_beyond=d.settle_min_freq_change_pct / 100.0 if settling else None,
        )
        if alarm is not None:
            self._raise(alarm, out)
            self._next_alarm_repeat = t_s + 1.0
        elif self.detector.active is not None and t_s >= self._next_alarm_repeat and not self._engaged_out:
            # a latched alarm is repeated on CAN once a second until acknowledged (not logged again)
            self._next_alarm_repeat = t_s + 1.0
            out.append(self._alert_out(self.detector.active, t_s))
        if self._engaged_out:  # an engaged-flank change (raised when its backlash test came back)
            out.extend(self._engaged_out)
            self._engaged_out.clear()

    def _test_backlash(self, t_s: float, speed: float, load: float, model: OnlineDriveline, window_s: float) -> None:
        """The backlash test (:mod:`online_id.diagnose.linearity`) on this operating point's steady samples, in the
        worker, once the speed has been steady for ``detection.backlash_test_s`` (at most the last ``window_s``);
        on a shaft that showed backlash, with ``detection.engaged_flank``, its engaged flank's resonance and
        damping go to :attr:`engaged` (:mod:`online_id.monitoring.engaged`)."""
        visit = self.comparison.visit

        def done(test: BacklashTest | None, error: str | None) -> None:
            if test is None:
                self.events.append(Event(t_s, "backlash_test", f"backlash test at {speed:.0f} rpm not done: {error}",
                                         {"error": error}))
                return
            if test.shows_backlash(self.settings.detection.backlash_gain_pct / 100.0) and not self.baseline.nonlinear:
                self.baseline.backlash = {**test.as_dict(), "source": self.run_label}
                if not self.settings.detection.engaged_flank:
                    self.backlash.samples.clear()  # no test runs any more
                # a cell held for disagreeing with another point's baseline: that baseline predicts nothing here
                n = self.baseline.release()
                self.events.append(Event(t_s, "backlash", f"the shaft shows backlash at {test.speed_rpm:.0f} rpm: a "
                                         f"dead zone of the twist removes {100 * test.gain:.0f} % of the one-step "
                                         f"error (t = {test.t_stat:.1f}); other operating points' baselines are no "
                                         f"longer compared with" + (f", {n} held cell(s) released" if n else ""),
                                         test.as_dict() | {"released": n}))
            if self.baseline.nonlinear and self.settings.detection.engaged_flank:
                reading = EngagedReading(t_s, visit, speed, load, test.engaged_f0_hz, test.engaged_zeta, self.run_label)
                learn = self.detector.active is None and self._state == ServiceState.TRACKING
                for change in self.engaged.offer(reading, learn=learn):
                    self._raise_engaged(change)

        self.backlash.start(t_s, visit, model.window.steady_s, window_s, done)

    def _raise_engaged(self, change: EngagedChange) -> None:
        """A change of the engaged flank: latched by the detector (acknowledged as its own alarms are), raised
        unless an alarm of its kind of the same or a higher level is latched (an escalation keeps its onset)."""
        alarm = engaged_alarm(change, next((a for a in self.detector.alarms if a.kind == change.kind), None))
        if not self.detector.latch(alarm):
            return
        self._record(self._alert_out(alarm, alarm.detected_t_s), self._engaged_out,
                     alarm.as_dict() | {"baseline_kind": "engaged", "baseline_source": change.source,
                                        "threshold_pct": 100 * change.threshold})
        self._next_alarm_repeat = self._clock() + 1.0

    def _steady(self, est: OnlineEstimate, t_s: float) -> bool:
        """Whether the estimate stood still over the last ``STEADY_S``: its frequency within the dead band
        (or three of its own standard deviations) of the estimate then, its damping within half the damping
        dead band (or three of its own standard deviations). A baseline is learned from steady estimates
        only: a change of the driveline shows first as estimates that move while the fit window takes it in
        (for about the window's length), and a cell that learns them takes in the change (a +50 % damping
        change came into a cell learning at the time as +32 %: the damping moves through its
        20 % dead band within the 5 s)."""
        then = next(((f, z) for t, f, z in self._recent if t >= t_s - STEADY_S - 1e-6), None)
        if then is None or self._recent[0][0] > t_s - STEADY_S + 0.5:
            return False  # not yet STEADY_S of healthy estimates
        std_f = est.f0_std_hz if math.isfinite(est.f0_std_hz) else 0.0
        std_z = est.zeta_std if math.isfinite(est.zeta_std) else 0.0
        return (abs(est.f0_hz - then[0]) <= max(self.detector.min_change_f * abs(then[0]), 3.0 * std_f)
                and abs(est.zeta - then[1]) <= max(0.5 * self.detector.min_change_zeta * abs(then[1]), 3.0 * std_z))

    def _baseline_for(self, speed: float, load: float, learning: bool = False) -> BandStats | None:
        """What an estimate at ``speed`` and ``load`` is compared with (:meth:`Comparison.baseline_for`)."""
        return self.comparison.baseline_for(self.baseline, speed, load, learning)

    def _with_visit(self, stats: BandStats | None, load: float) -> BandStats | None:
        """``stats``, or the first estimates of this visit where they serve (:meth:`Comparison.with_visit`)."""
        return self.comparison.with_visit(stats, load, self.baseline.nonlinear)

    def _learn(self, est: OnlineEstimate, t_s: float, speed: float, load: float,
               model: OnlineDriveline) -> OnlineEstimate:
        """One estimate into the baseline of its cell, unless the cell is learned or the estimate disagrees.

        A cell still learning compares each estimate with what serves it
        (:meth:`_baseline_for`: a learned cell, the pooled baseline, or its
        own first estimates). Where that is the cell's own baseline, an
        estimate that deviates beyond the dead band plus three spreads is not
        learned (a change during learning must not be absorbed into the
        baseline): it only feeds the detector. Where it is another operating
        point's (the pool, another band or load), the disagreement is
        ambiguous and the estimate is learned into a *held* cell, which is no
        baseline of another point until an estimate at an established cell
        agrees with that cell's own baseline (:meth:`Baseline.release`, see
        :mod:`~online_id.monitoring.baseline`). On a shaft that showed
        backlash the bounds the learned cells of other loads set serve
        (:meth:`_baseline_for`, :meth:`Baseline.bracketed`): an estimate
        outside them is learned into a held cell; where nothing bounds the
        point from below, the first estimates of the visit serve
        (:mod:`~online_id.monitoring.visit`): an estimate
        that disagrees with them is learned into a held cell too.
        """
        d = self.settings.detection
        cell = self.baseline.cell(speed, load)
        learned = cell is not None and cell.count >= d.min_count
        # a new cell is learned from the best of several starts, not from whichever of the nearly equal
        # minima of a mismatched model (backlash) the warm-started refits happen to follow
        verified = self.checks.verify("learn", t_s, model) if cell is None else False
        if verified is PENDING:
            return est
        if verified:
            est = model.estimate()
            self._estimate = est
            load = est.load_nm
        if not (est.valid and math.isfinite(load) and math.isfinite(est.f0_hz) and est.zeta > 0):
            return est
        # where nothing else bounds the point, an estimate that disagrees with the visit's first ones is held
        ref = self._with_visit(self._baseline_for(speed, load, learning=True), load)
        # the damping with half its dead band (see BandStats.disagrees): a change on its way in must not be learned
        why = (ref.disagrees(est.f0_hz, est.zeta, self.detector.min_change_f, 0.5 * self.detector.min_change_zeta)
               if ref is not None else None)
        own = ref is not None and is_own(ref, speed, load, self.baseline.load_band_nm)
        n = self.baseline.release() if why is None and own else 0  # held cells: the driveline did not change
        if n:
            self.events.append(Event(t_s, "released", f"{n} held cell(s) released: at {speed:.0f} rpm, "
                                     f"{load:.1f} Nm the estimate agrees with the cell's own {ref.kind} baseline "
                                     f"({est.f0_hz:.3f} Hz against {ref.mean_f:.3f} Hz), so the driveline did "
                                     f"not change since", {"cells": n}))
        if learned:
            return est  # a learned cell stays fixed until re-learned
        versus = versus_text(why, est, ref) if why is not None else ""
        if why is not None and own:
            self.baseline.reject(speed_rpm=speed, load_nm=load)
            self._rejected += 1
            if t_s >= self._next_reject_event:
                self._next_reject_event = t_s + 60.0
                self.events.append(Event(t_s, "not_learned", f"{why} estimate not learned at {speed:.0f} rpm, "
                                         f"{load:.1f} Nm: it disagrees with the {ref.kind} baseline ({versus})",
                                         {"kind": why, "baseline": ref.kind}))
            return est
        if why is not None and not self.baseline.is_held(speed, load):
            self.events.append(Event(t_s, "held", f"cell {speed:.0f} rpm, {load:.1f} Nm held: its {why} estimate "
                                     f"disagrees with the {ref.kind} baseline ({versus}); it serves no point until "
                                     f"an established cell agrees with its own", {"kind": why, "baseline": ref.kind}))
        self.baseline.learn(speed_rpm=speed, f0_hz=est.f0_hz, zeta=est.zeta, load_nm=load,
                            f0_std_hz=est.f0_std_hz, zeta_std=est.zeta_std, source=self.run_label,
                            reference=self.reference_run, held=why is not None)
        solution = model.solution
        if solution is not None:
            self.checks.references[self.baseline.key(speed)] = solution
        done = self.baseline.cell(speed, load)
        if why is None and solution is not None and done is not None:
            self.checks.keep_window(done, speed, load, t_s, solution, model, self.baseline)
        if done is not None and done.count == d.min_count:
            ratio = done.spread_ratio
            self.events.append(Event(t_s, "learned", f"cell {speed:.0f} rpm, {load:.1f} Nm learned: f0 "
                                     f"{done.mean_f:.3f} +- {done.std_f:.3f} Hz, zeta {done.mean_zeta:.4f}"
                                     + (" (held: no baseline until released)" if done.kind == "held" else ""),
                                     done.as_dict()))
            if math.isfinite(ratio) and ratio > SPREAD_RATIO_REPORTED:
                self.events.append(Event(t_s, "wide_baseline", f"baseline at {speed:.0f} rpm, {load:.1f} Nm: "
                                         f"spread {done.std_f:.3f} Hz is {ratio:.0f} times the estimator's own "
                                         f"uncertainty ({done.uncertainty_f:.4f} Hz): the driveline moved "
                                         f"while it was learned", done.as_dict()))
        return est

    def _confirm(self, kind: str, stats: BandStats, t_s: float, model: OnlineDriveline) -> bool | None:
        """Before a new drift alarm: the checks it must pass (:meth:`AlarmChecks.confirm`). True: raise it;
        False: withhold it; None: a check runs in the worker (the detector asks again at its next interval)."""
        return self.checks.confirm(kind, stats, t_s, model, self._estimate, self.baseline, self.detector,
                                   self.comparison.visit, self.comparison.visit_ref)

    def _alert_out(self, alarm: Alarm, t_s: float) -> AlertOut:
        kind = AlertKind.FREQ_DRIFT if alarm.kind == "frequency" else AlertKind.DAMPING_DRIFT
        return AlertOut(t_s, kind, alarm.level, alarm.change_pct, alarm.speed_rpm, alarm.message)

    def _raise(self, alarm: Alarm, out: list[Publication]) -> None:
        stats = self._stats
        data = alarm.as_dict()
        if stats is not None:
            load = self._estimate.load_nm if self._estimate is not None else float("nan")
            cell = f"cell {alarm.speed_rpm:.0f} rpm" + (f", {load:.0f} Nm" if math.isfinite(load) else "")
            alarm = dataclasses.replace(alarm, message=f"{alarm.message} ({cell}, against {against_text(stats)})")
            data |= {"message": alarm.message, "baseline_kind": stats.kind, "baseline_source": stats.source}
        self._record(self._alert_out(alarm, alarm.detected_t_s), out, data)

