"""Samples in -> estimates, health and alerts out.  No I/O.

One :class:`Pipeline` serves the live service, the replay of logs, the demo
and the tests: it is fed decoded signal values (:class:`SignalSample`),
frame faults and commands, with the stream's own timestamps, and returns the
publications due (:mod:`online_id.records`).  Time is always the stream's:
frame timestamps in the service, log timestamps in a replay.

Health states (published in the status frame):

* ``STARTING``: no complete sample yet;
* ``LEARNING``: samples flow, the estimate is not yet valid;
* ``TRACKING``: the estimate is valid;
* ``NO_EXCITATION``: the torque does not excite the driveline, adaptation is
  frozen (the estimate is held);
* ``INPUT_TIMEOUT``: an input role is silent for longer than the timeout (the
  estimator holds and resumes cleanly when frames come back);
* ``FAULT``: the estimator had to reset repeatedly (numerical failure).
"""

from __future__ import annotations

import dataclasses
import itertools
import math
from collections import deque
from dataclasses import dataclass, field

import numpy as np

from online_id.service.assembly import AssembledSample, SampleAssembler
from online_id.config import Settings
from online_id.diagnose.bench_data import DEFAULT_PULSES_PER_REV
from online_id.diagnose.linearity import BacklashTest, backlash_test
from online_id.monitoring.baseline import Baseline
from online_id.monitoring.cells import BandStats
from online_id.monitoring.detection import (DAMPING, FREQUENCY, Alarm, ChangeDetector, alarm_message,
                                            correlation_for_window, when_text)
from online_id.monitoring import engaged as engaged_flank
from online_id.monitoring.engaged import EngagedChange, EngagedFlank, EngagedReading
from online_id.estimation.model import ArmaxOrders
from online_id.estimation.online import OnlineDriveline, OnlineEstimate, physical_parameters
from online_id.estimation.reference import ReferenceWindow, judge, refit_each
from online_id.estimation.window import RefitJob, solve
from online_id.analysis.physical import DrivelineParameters
from online_id.monitoring.tracks import PoleTracker
from online_id.monitoring.visit import VisitReference
from online_id.errors import EstimationError
from online_id.analysis.excitation import Excitation
from online_id.service.offload import InlineWorker
from online_id.records import (
    AlertKind,
    AlertOut,
    EstimateOut,
    ExcitationOut,
    FrameFault,
    Publication,
    QualityOut,
    ServiceState,
    SignalSample,
    StatusOut,
)

MAX_EVENTS = 10_000  # state changes kept for reports (bounded: a flapping bench must not grow memory)
COMMAND_ACK = 1
COMMAND_RELEARN = 2
COMMAND_RESET = 3
STATE_VERSION = 1
WINDOW = "window"  # worker lane of the window refits and multi-start checks
PHYSICAL = "physical"  # worker lane of the physical-parameter fit
LINEARITY = "linearity"  # worker lane of the backlash test (see _test_backlash)
BACKLASH_TEST_MAX_S = 30.0  # the backlash test takes at most this much of an operating point's steady samples
PENDING = None  # a multi-start check is running in the worker: decide later
VERIFY_FRESH_S = 5.0  # a multi-start check older than this is not used for a decision
RECHECK_WAIT_S = 10.0  # a recheck of a reference window older than this is dropped (see _confirm)
# the two nearly equal minima of a model that does not fit exactly (backlash) differ by 1-3 % in the resonance
# (see online_id.monitoring.detection): a frequency change a recheck withheld stands only within this
MINIMA_SPREAD_F = 0.03
ACCEPTED_SIGMAS = 3.0  # ... while the estimate moves no farther from the baseline than this many of its own stds
STEADY_S = 5.0  # learning needs the estimates this long ago within the dead bands (or 3 own stds), see _steady
SPREAD_RATIO_REPORTED = 5.0  # a learned spread this many times the estimator's own uncertainty is reported


@dataclass
class Event:
    """A status change or alert kept for reports (times in stream seconds)."""

    t_s: float
    kind: str
    message: str = ""
    data: dict = field(default_factory=dict)


class Pipeline:
    """The streaming pipeline (see module notes)."""

    def __init__(self, settings: Settings, worker=None) -> None:
        self.settings = settings
        s = settings
        # slow work (window refits, multi-start checks, physical fits): at once in replay, in a worker process
        # in the live service (see online_id.service.offload)
        self.worker = worker if worker is not None else InlineWorker()
        self._verify_results: dict = {}  # purpose -> (t_s submitted, adopted) of finished multi-start checks
        self._verify_running: set = set()
        self.assembler = SampleAssembler(s.input.sample_rate_hz, s.input.timeout_s, s.input.slow_roles,
                                         max_jump_s=s.input.max_time_jump_s)
        self.estimator = self._new_estimator()
        self.excitation = Excitation(s)
        d = s.detection
        self.tracker = PoleTracker(dt=self.estimator.dt, pulses_per_rev=s.model.pulses_per_rev)
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
        self._next_engaged = -math.inf  # stream time of the next engaged-flank reading in this visit
        self._engaged_out: list[Publication] = []  # its alerts, published with the next detection
        self._healthy_since: float | None = None  # start of the current healthy stretch (settle_s)
        self._recent: deque[tuple[float, float, float]] = deque()  # (t_s, f0, zeta) of the healthy stretch
        self._healthy_rpm: float | None = None  # engine speed of the last healthy estimate
        # the input samples of the last BACKLASH_TEST_MAX_S (t, dyno speed, engine speed, torque): the backlash test
        self._raw: deque[tuple[float, float, float, float]] = deque(
            maxlen=max(1, int(BACKLASH_TEST_MAX_S * s.input.sample_rate_hz)))
        self._visit = 0  # counts the arrivals of healthy estimates at another operating point
        self._visit_tested = -1  # the visit whose samples the backlash test took
        self._visit_not_compared = -1  # the visit where another point's baseline was last not compared with
        self._visit_ref: VisitReference | None = None  # a visit's first estimates, where no learned cell bounds it
        self._next_visit_sample = 0.0
        self.backlash_tests = 0
        self.last_backlash_test: BacklashTest | None = None
        self._references: dict[int, np.ndarray] = {}  # per baseline band: a window solution it was learned from
        # per baseline band, one per cell (load): the window of the cell's first estimates, see _keep_window
        self._windows: dict[int, list[ReferenceWindow]] = {}
        self._rechecks: dict[str, dict] = {}  # per alarm kind: a recheck of a reference window under way
        self._accepted: dict | None = None  # the frequency a recheck found the cell's own data give (_still_accepted)
        self._next_learn: float | None = None
        self._next_alarm_repeat = 0.0
        self._stats: BandStats | None = None  # the baseline the latest estimate was compared with
        self._rejected = 0  # learning estimates not learned (they disagreed with the baselines)
        self._next_reject_event = 0.0
        self.state = ServiceState.STARTING
        self.t_s = float("nan")
        self.t_first: float | None = None
        self._next_publish: float | None = None
        self._poll_deferred = False  # the worker was not polled on the last sample (it published)
        self._window_since: float | None = None  # stream time the last window job was submitted
        self._next_physical: float | None = None
        self._physical: DrivelineParameters | None = None
        self._refit_pending = False
        self._detect_pending: tuple[OnlineEstimate, float, float] | None = None  # see _publish
        self._estimate: OnlineEstimate | None = None
        self._resets_seen = 0
        self._reset_times: list[float] = []
        self.events: deque[Event] = deque(maxlen=MAX_EVENTS)
        self.alerts: list[AlertOut] = []
        self.alerts_total = 0  # alerts raised since start (the list keeps the last MAX_EVENTS)
        self.commands = 0
        self.dropped_frames = 0  # frames the kernel dropped (full receive buffer), reported by the service

    def _new_estimator(self) -> OnlineDriveline:
        m = self.settings.model
        return OnlineDriveline(
            ArmaxOrders(m.na, m.nb, m.nc, m.nk),
            input_rate_hz=self.settings.input.sample_rate_hz,
            model_rate_hz=m.sample_rate_hz,
            forgetting=m.forgetting,
            p0=m.p0,
            min_excitation_nm=m.min_excitation_nm,
            learning_s=m.learning_s,
            pulses_per_rev=m.pulses_per_rev,
            band_hz=m.band_hz,
            window_s=m.window_s,
            min_window_s=m.min_window_s,
            settle_guard_s=m.settle_guard_s,
            refit_s=m.refit_s,
            max_speed_span_rpm=m.max_speed_span_rpm,
            auto_refit=False,  # run by _consume on a sample that publishes nothing
        )

    def warm_up(self) -> None:
        """Load the compiled code (numba) and the estimator's code paths before the first frame.

        A scratch estimator of the same orders runs a few seconds of noise and
        one estimate; the live service calls this before it opens the bus, so
        the first frames do not wait for compilation or cache loading.
        """
        scratch = self._new_estimator()
        rng = np.random.default_rng(0)
        n = int(2.0 * self.settings.input.sample_rate_hz)
        for y, u in zip(100.0 + rng.standard_normal(n), rng.standard_normal(n)):
            scratch.update(float(y), 150.0, float(u))
        scratch.estimate()
        if self.worker.asynchronous:
            self._warm_up_worker(scratch.orders, rng)

    def _warm_up_worker(self, orders: ArmaxOrders, rng: np.random.Generator, limit_s: float = 120.0) -> None:
        """A small cold refit in the worker process, waited for (bounded): its first real job then does not
        pay for importing SciPy and loading compiled code (seconds on a busy PC, which the first valid
        estimate would wait for)."""
        n = 20 * orders.n_params
        job = RefitJob(rng.standard_normal(n), rng.standard_normal(n), orders, "cold", (), 0.0, 0.0, -1)
        self.worker.submit(WINDOW, solve, (job,), lambda _fit, _err: None)
        self.worker.wait(limit_s)

    @property
    def last_estimate(self) -> OnlineEstimate | None:
        """The estimate of the latest publication (None before the first)."""
        return self._estimate

    # -- counters --------------------------------------------------------------------------------
    @property
    def counters(self):
        return self.assembler.counters

    @property
    def estimate(self) -> OnlineEstimate | None:
        """The estimate of the last publication (None before the first)."""
        return self._estimate

    def on_dropped(self, n: int) -> None:
        """``n`` frames the kernel dropped before they reached us (receive buffer full)."""
        self.dropped_frames += n
        self.events.append(Event(self.t_s, "dropped", f"{n} frames dropped by the kernel", {"n": n}))

    def on_fault(self, fault: FrameFault) -> None:
        """A frame that could not be used (counted, reported in the status frame)."""
        self.assembler.counters.count(fault)

    # -- input -----------------------------------------------------------------------------------
    def on_signal(self, sample: SignalSample) -> list[Publication]:
        """One decoded value from a frame."""
        samples = self.assembler.push(sample)  # checks the timestamp (see online_id.service.assembly)
        if samples:
            if self.t_first is None:
                self.t_first = samples[0].t_s
            publishes = self._next_publish is not None and samples[-1].t_s >= self._next_publish
            if not publishes or self._poll_deferred:
                # adopt finished slow work before the samples use the model; not on a sample that publishes
                # (adopting a window fit takes up to a millisecond): its estimate goes out first, the result
                # is adopted on the next sample (an inline worker, as replay's, has nothing to adopt here)
                self.worker.poll()
            self._poll_deferred = publishes and not self._poll_deferred
        return self._consume(samples, self.assembler.now_s)

    def tick(self, now_s: float) -> list[Publication]:
        """The stream clock moved without a frame (silence on the bus, the end of a log)."""
        self.worker.poll()  # adopt finished slow work (also before the samples this may complete)
        out = self._consume(self.assembler.poll(now_s), self.assembler.now_s)
        if self._detect_pending is not None:  # the last publication's detection, when no sample followed it
            self._run_pending_detection(out)
        return out

    @property
    def detection_pending(self) -> bool:
        """The last publication's tracking and detection have not run yet (they run on the next sample)."""
        return self._detect_pending is not None

    def _run_pending_detection(self, out: list[Publication]) -> None:
        est, t_s, speed = self._detect_pending
        self._detect_pending = None
        self._track_and_detect(est, t_s, speed, out)

    def on_command(self, command: int, t_s: float) -> list[Publication]:
        """A command frame: acknowledge alerts, re-learn, reset the estimator."""
        self.commands += 1
        out: list[Publication] = []
        if command == COMMAND_RESET:
            self.estimator = self._new_estimator()
            self._estimate = None
            self._physical = None
            self._detect_pending = None
            self.events.append(Event(t_s, "command", "estimator reset on command"))
        elif command == COMMAND_ACK:
            self.detector.acknowledge()
            self.engaged.acknowledge()
            self.events.append(Event(t_s, "command", "alerts acknowledged"))
            out.append(AlertOut(t_s, AlertKind.NONE, 0, 0.0, self.estimator.speed_rpm, "alerts acknowledged"))
        elif command == COMMAND_RELEARN:
            self.baseline.reset()
            self._references.clear()
            self._windows.clear()
            self._rechecks.clear()
            self._accepted = None
            self._visit_ref = None
            self.detector.reset()
            self.engaged.reset()
            self.events.append(Event(t_s, "command", "baselines forgotten: learning anew"))
            out.append(AlertOut(t_s, AlertKind.NONE, 0, 0.0, self.estimator.speed_rpm, "baselines re-learned"))
        return out

    def process(self, a: AssembledSample) -> None:
        """Feed one assembled sample to the estimator (also used by offline runs)."""
        if a.discontinuity and self.counters.samples > 1:
            self.estimator.restart_history()
            self._raw.clear()
        if self.settings.detection.backlash_test_s > 0 and (self.baseline.backlash is None
                                                             or self.settings.detection.engaged_flank):
            # the backlash test's samples, kept only while a test may run
            self._raw.append((a.t_s, a.dyno_speed, a.engine_speed, a.dyno_torque))
        self.estimator.update(a.dyno_speed, a.engine_speed, a.dyno_torque)

    def _consume(self, samples: list[AssembledSample], now_s: float) -> list[Publication]:
        out: list[Publication] = []
        self.t_s = now_s
        jump = self.assembler.take_time_jump()
        if jump is not None:
            self._time_jumped(jump, now_s, out)
        if self.assembler.timed_out:
            stop = self.excitation.stop(now_s)
            if stop:
                out.append(stop)
            self._set_state(ServiceState.INPUT_TIMEOUT, now_s, out,
                            f"input timeout: {', '.join(self.assembler.timed_out_roles)} silent")
        for a in samples:
            self.process(a)
            self.t_s = a.t_s
            rels = self.estimator.rels
            if rels.n_resets != self._resets_seen:
                self._resets_seen = rels.n_resets
                self._reset_times.append(a.t_s)
                self._alert(out, a.t_s, AlertKind.ESTIMATOR_RESET, 2, 0.0,
                            f"estimator reset after a numerical failure (resets: {rels.n_resets})")
            healthy = self.state in (ServiceState.LEARNING, ServiceState.TRACKING)
            exc = self.excitation.step(a.t_s, healthy, self.estimator.speed_rpm)
            if exc:
                out.append(exc)
            if self._next_publish is None:
                self._next_publish = a.t_s
                self._next_physical = a.t_s
                self._set_state(ServiceState.LEARNING, a.t_s, out)
            if a.t_s >= self._next_publish:
                self._next_publish += 1.0 / self.settings.publish.rate_hz
                if self._next_publish <= a.t_s:  # after a gap: no burst of publications
                    self._next_publish = a.t_s + 1.0 / self.settings.publish.rate_hz
                out.extend(self._publish(a.t_s))
            elif self._detect_pending is not None:
                self._run_pending_detection(out)
            # slow work starts on a sample that publishes nothing, so it never delays an estimate; with the
            # process worker it runs beside the stream and is adopted when it is back (``worker.poll``)
            elif self.estimator.refit_due and not self.worker.busy(WINDOW):
                self._submit_refit()
            elif self._refit_pending and not self.worker.busy(PHYSICAL):
                self._submit_physical()
        return out

    def poll_worker(self) -> int:
        """Adopt the results of finished slow work (also done before every sample)."""
        return self.worker.poll()

    @property
    def slow_work_lag_s(self) -> float:
        """Stream seconds since the window job in flight (a refit or check) was submitted, 0 when none is: how
        far the stream has run ahead of the slow work (on a bench, well under a second; a stream fed faster
        than real time, as the demo and the soak feed it, can outrun a worker the machine starves)."""
        if self._window_since is None or not self.worker.busy(WINDOW):
            return 0.0
        return max(0.0, self.t_s - self._window_since)

    def _submit_refit(self) -> None:
        """The due window refit (10-20 ms, a cold one about 0.5 s) to the worker."""
        estimator = self.estimator
        job = estimator.refit_job()
        if job is not None:
            self._window_since = self.t_s
            self.worker.submit(WINDOW, solve, (job,), lambda fit, err: estimator.complete(job, fit, err))

    def _submit_physical(self) -> None:
        """Physical parameters of the latest estimate (a least-squares fit, ~10 ms) to the worker."""
        self._refit_pending = False
        est = self._estimate
        if est is None or not est.valid:
            return
        inert = self.settings.inertias
        args = self.estimator.physical_job(est, inert.J1, inert.J2, inert.J_total)
        if args is None:
            self._physical = None
            return
        self.worker.submit(PHYSICAL, physical_parameters, args, self._physical_done)

    def _physical_done(self, phys: DrivelineParameters | None, error: str | None) -> None:
        self._physical = phys if error is None else None

    def _verify(self, purpose, t_s: float, starts: tuple = (), prefer_last_within: float = 0.0) -> bool | None:
        """A multi-start refit of the window for ``purpose``: True/False (a fit adopted or not), or PENDING.

        With the inline worker the check runs at once; with the process
        worker the first call starts it and returns PENDING, and a later call
        (within ``VERIFY_FRESH_S``) gets its outcome.
        """
        done = self._verify_results.pop(purpose, None)
        if done is not None and 0.0 <= t_s - done[0] <= VERIFY_FRESH_S:
            return done[1]
        if purpose in self._verify_running or self.worker.busy(WINDOW):
            return PENDING
        estimator = self.estimator
        job = estimator.verify_job(starts, prefer_last_within)
        if job is None:
            return False

        def finished(fit, error: str | None) -> None:
            self._verify_running.discard(purpose)
            self._verify_results[purpose] = (t_s, estimator.complete(job, fit, error))

        self._verify_running.add(purpose)
        self._window_since = self.t_s
        self.worker.submit(WINDOW, solve, (job,), finished)
        done = self._verify_results.pop(purpose, None)
        return PENDING if done is None else done[1]

    # -- outputs ---------------------------------------------------------------------------------
    def _alert(self, out: list[Publication], t_s: float, kind: AlertKind, severity: int, value_pct: float,
               message: str) -> None:
        self._record(AlertOut(t_s, kind, severity, value_pct, self.estimator.speed_rpm, message), out)

    def _record(self, alert: AlertOut, out: list[Publication], data: dict | None = None) -> None:
        """Keep (bounded), count and publish one new alert."""
        self.alerts.append(alert)
        self.alerts_total += 1
        if len(self.alerts) > MAX_EVENTS:
            del self.alerts[: len(self.alerts) - MAX_EVENTS]
        self.events.append(Event(alert.t_s, "alert", alert.message, {"kind": alert.kind.name, **(data or {})}))
        out.append(alert)

    def _set_state(self, state: ServiceState, t_s: float, out: list[Publication], why: str = "") -> None:
        if state == self.state:
            return
        self.state = state
        self.events.append(Event(t_s, "state", why or state.name, {"state": state.name}))
        if state in (ServiceState.INPUT_TIMEOUT, ServiceState.FAULT):
            stop = self.excitation.stop(t_s)
            if stop:
                out.append(stop)
            if state == ServiceState.INPUT_TIMEOUT:
                self._alert(out, t_s, AlertKind.INPUT_FAULT, 1, 0.0, why or "input timeout")
        out.append(self.status(t_s))

    def _time_jumped(self, message: str, t_s: float, out: list[Publication]) -> None:
        """The stream clock jumped and the assembler re-anchored its grid: so do the schedules here."""
        self._next_publish = -math.inf if self._next_publish is not None else None  # publish with the next sample
        self._next_physical = -math.inf
        self._next_learn = None
        self._next_alarm_repeat = -math.inf
        self._next_engaged = -math.inf
        self._next_visit_sample = -math.inf
        self._next_reject_event = -math.inf
        self._healthy_since = None  # settle again before learning or detecting
        self._recent.clear()
        self.events.append(Event(t_s, "time", message, {"time_jumps": self.counters.time_jumps}))
        out.append(self.status(t_s))

    def _judge(self, est: OnlineEstimate, t_s: float) -> ServiceState:
        recent = [t for t in self._reset_times if t_s - t < 10.0]
        if len(recent) >= 3:
            return ServiceState.FAULT
        if est.frozen:
            return ServiceState.NO_EXCITATION
        return ServiceState.TRACKING if est.valid else ServiceState.LEARNING

    def _publish(self, t_s: float) -> list[Publication]:
        out: list[Publication] = []
        est = self.estimator.estimate()
        self._estimate = est
        state = self._judge(est, t_s)
        self._set_state(state, t_s, out, est.why if state == ServiceState.LEARNING else "")
        if est.valid and (self._physical is None or t_s >= self._next_physical):
            # the refit of the physical parameters (a least-squares fit, ~10 ms) runs on the next sample
            # that publishes nothing, so it never delays an estimate; c_s and d_s lag by one publication
            self._next_physical = t_s + self.settings.publish.physical_interval_s
            self._refit_pending = True
        if self.settings.detection.enabled:
            # pole tracking, learning and detection (about 1 ms) run on the next sample, after this
            # publication has gone out: an estimate never waits for them, an alert comes 1 sample later
            self._detect_pending = (est, t_s, self.estimator.speed_rpm)
        phys = self._physical
        nan = float("nan")
        # the estimate first: its frame goes out before the others of this publication
        out.insert(0, EstimateOut(t_s, est.f0_hz, est.zeta, phys.c_s if phys and phys.c_s else nan,
                                  phys.d_s if phys and phys.d_s else nan, est.valid))
        out.append(QualityOut(t_s, est.residual_rms, est.fpe, est.excitation_nm, est.samples_used))
        out.append(self.status(t_s))
        return out

    # -- wear and fault detection ------------------------------------------------------------------
    def _track_and_detect(self, est: OnlineEstimate, t_s: float, speed: float, out: list[Publication]) -> None:
        """Pole tracks, baseline learning (1 Hz) and change detection, at the publish rate.

        ``est``, ``t_s`` and ``speed`` are those of the publication (it runs on the sample after it).
        """
        d = self.settings.detection
        load = est.load_nm
        self.tracker.update(t_s=t_s, speed_rpm=speed, poles=est.poles)
        healthy = (est.valid and not est.frozen and self.state == ServiceState.TRACKING
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
                    self._visit += 1
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
            est = self._learn(est, t_s, speed, load)
            load = est.load_nm
        if healthy and d.backlash_test_s > 0 and not self.worker.busy(LINEARITY):
            if not self.baseline.nonlinear and self._visit_tested != self._visit:
                self._test_backlash(t_s, speed, load)
            elif self.baseline.nonlinear and d.engaged_flank and (self._visit_tested != self._visit
                                                                  or t_s >= self._next_engaged):
                self._test_backlash(t_s, speed, load, engaged_flank.WINDOW_S)
        stats = self._baseline_for(speed, load)
        if (stats is None and healthy and self.baseline.nonlinear and self._visit_not_compared != self._visit
                and self.baseline.learned_range_rpm is not None):
            # on a shaft with backlash the resonance moves with the operating point (rising with the load's
            # magnitude): where no learned cell bounds it (a load below them all, farther than they span, or
            # no cell yet), the visit's own first settled estimates serve, then the cell's,
            # and a change that comes with the visit shows at the established points (it shows everywhere)
            self._visit_not_compared = self._visit
            self.events.append(Event(t_s, "not_compared", f"at {speed:.0f} rpm, {load:.1f} Nm no learned cell is "
                                     f"compared with: the shaft shows backlash, so its resonance moves with the "
                                     f"load, and no learned cell bounds it here; the estimates are compared with "
                                     f"the first estimates of this visit", {}))
        if self._visit_serves(stats):
            self._visit_sample(est, t_s, speed, load, healthy and not settling, stats)
            stats = self._with_visit(stats, load)
        self._stats = stats
        alarm = self.detector.update(
            t_s=t_s, speed_rpm=speed, f0_hz=est.f0_hz, zeta=est.zeta, f0_std_hz=est.f0_std_hz,
            zeta_std=est.zeta_std, baseline=stats, suppressed=not healthy,
            confirm=lambda kind: self._confirm(kind, stats, t_s),
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

    def _test_backlash(self, t_s: float, speed: float, load: float, window_s: float = BACKLASH_TEST_MAX_S) -> None:
        """The backlash test (:mod:`online_id.diagnose.linearity`) on this operating point's steady samples, in the
        worker, once the speed has been steady for ``detection.backlash_test_s`` (at most the last ``window_s``).

        Until one point shows backlash, once per visit. On a shaft that showed backlash, with
        ``detection.engaged_flank``, every ``EVERY_S`` of a visit on the last ``WINDOW_S`` of steady samples: its
        engaged flank's resonance and damping go to :attr:`engaged` (:mod:`online_id.monitoring.engaged`)."""
        least = self.settings.detection.backlash_test_s
        steady = min(self.estimator.window.steady_s, window_s)
        rate = self.settings.input.sample_rate_hz
        if steady < least or len(self._raw) < least * rate:
            return
        self._visit_tested = self._visit
        self._next_engaged = t_s + engaged_flank.EVERY_S
        n = min(len(self._raw), int(steady * rate))
        rows = np.asarray(list(itertools.islice(self._raw, len(self._raw) - n, None)), dtype=float)
        visit = self._visit

        def done(test: BacklashTest | None, error: str | None) -> None:
            self.backlash_tests += 1
            if test is None:
                self.events.append(Event(t_s, "backlash_test", f"backlash test at {speed:.0f} rpm not done: {error}",
                                         {"error": error}))
                return
            self.last_backlash_test = test
            if test.shows_backlash(self.settings.detection.backlash_gain_pct / 100.0) and not self.baseline.nonlinear:
                self.baseline.backlash = {**test.as_dict(), "source": self.run_label}
                if not self.settings.detection.engaged_flank:
                    self._raw.clear()  # no test runs any more
                # a cell held for disagreeing with another point's baseline: that baseline predicts nothing here
                n = self.baseline.release()
                self.events.append(Event(t_s, "backlash", f"the shaft shows backlash at {test.speed_rpm:.0f} rpm: a "
                                         f"dead zone of the twist removes {100 * test.gain:.0f} % of the one-step "
                                         f"error (t = {test.t_stat:.1f}); other operating points' baselines are no "
                                         f"longer compared with" + (f", {n} held cell(s) released" if n else ""),
                                         test.as_dict() | {"released": n}))
            if self.baseline.nonlinear and self.settings.detection.engaged_flank:
                reading = EngagedReading(t_s, visit, speed, load, test.engaged_f0_hz, test.engaged_zeta, self.run_label)
                learn = self.detector.active is None and self.state == ServiceState.TRACKING
                for change in self.engaged.offer(reading, learn=learn):
                    self._raise_engaged(change)

        # the compression orders the test declares: the model's, else the bench diagnosis's default (a test with
        # none failed on every point of a config without model.pulses_per_rev)
        pulses = self.settings.model.pulses_per_rev or DEFAULT_PULSES_PER_REV
        self.worker.submit(LINEARITY, backlash_test, (rows[:, 0], rows[:, 3], rows[:, 1], rows[:, 2], pulses), done)

    def _raise_engaged(self, change: EngagedChange) -> None:
        """A change of the engaged flank: latched by the detector (acknowledged as its own alarms are), raised
        unless an alarm of its kind of the same or a higher level is latched (an escalation keeps its onset)."""
        latched = next((a for a in self.detector.alarms if a.kind == change.kind), None)
        since = latched.since_t_s if latched is not None else change.since_t_s
        stiff = None if change.stiffness_change is None else 100.0 * change.stiffness_change
        pct = 100.0 * change.change
        frequency = change.kind == FREQUENCY
        ref = f"{change.reference:.2f} Hz" if frequency else f"zeta {change.reference:.4f}"
        message = (alarm_message(change.kind, change.level, pct, stiff, since, change.speed_rpm,
                                 what=f"driveline engaged flank's {'resonance' if frequency else 'damping'}")
                   + f" (cell {change.speed_rpm:.0f} rpm, {change.load_nm:.0f} Nm, against the engaged-flank "
                   f"reference of {change.learned} backlash tests ({ref})"
                   + (f", learned from {change.source}" if change.source else "")
                   + f"; threshold {100 * change.threshold:.1f} %)")
        alarm = Alarm(change.kind, change.level, since, change.detected_t_s, change.speed_rpm, pct, stiff, message)
        if not self.detector.latch(alarm):
            return
        self._record(self._alert_out(alarm, alarm.detected_t_s), self._engaged_out,
                     alarm.as_dict() | {"baseline_kind": "engaged", "baseline_source": change.source,
                                        "threshold_pct": 100 * change.threshold})
        self._next_alarm_repeat = self.t_s + 1.0

    def _steady(self, est: OnlineEstimate, t_s: float) -> bool:
        """Whether the estimate stood still over the last ``STEADY_S``: its frequency within the dead band
        (or three of its own standard deviations) of the estimate then, its damping within half the damping
        dead band (or three of its own standard deviations). A baseline is learned from steady estimates
        only: a change of the driveline shows first as estimates that move while the fit window takes it in
        (for about the window's length), and a cell that learns them takes in the change (a +50 % damping
        change came into a cell learning at the time as +32 % on plant 11703: the damping moves through its
        20 % dead band within the 5 s)."""
        then = next(((f, z) for t, f, z in self._recent if t >= t_s - STEADY_S - 1e-6), None)
        if then is None or self._recent[0][0] > t_s - STEADY_S + 0.5:
            return False  # not yet STEADY_S of healthy estimates
        std_f = est.f0_std_hz if math.isfinite(est.f0_std_hz) else 0.0
        std_z = est.zeta_std if math.isfinite(est.zeta_std) else 0.0
        return (abs(est.f0_hz - then[0]) <= max(self.detector.min_change_f * abs(then[0]), 3.0 * std_f)
                and abs(est.zeta - then[1]) <= max(0.5 * self.detector.min_change_zeta * abs(then[1]), 3.0 * std_z))

    def _baseline_for(self, speed: float, load: float, learning: bool = False) -> BandStats | None:
        """What an estimate is compared with: its own cell, learned, or still learning (not held) with its first
        estimates (frozen: ``provisional_count`` of them, then ``freeze_count``) once it holds them (the same
        operating point: a learned cell at another load of the band differs by 0.1-0.5 % per Nm with backlash);
        else a learned cell of the band at another load or of an adjacent band (:meth:`Baseline.lookup`); else
        the pooled baseline (for detection the pool's spread is doubled, for the learning check,
        ``learning``, it is not). On a shaft that showed backlash (:attr:`Baseline.nonlinear`) no other single
        point serves: the learned cells of smaller and larger loads bound the resonance
        (:meth:`Baseline.bracketed`, its bounds widened by the order's slack; None where none does)."""
        n = self.baseline.provisional_count
        own = self.baseline.cell(speed, load, frozen=True)
        if own is not None and own.count >= n:
            return own  # as it is: its spread is widened while it holds fewer than freeze_count estimates
        stats = self.baseline.lookup(speed, load)
        nonlinear = self.baseline.nonlinear
        if stats is not None and (not nonlinear or self._own(stats, speed, load)):
            return stats
        if nonlinear:
            # a shaft with backlash: its resonance moves with the operating point, but rises with the magnitude of
            # the load; the learned cells of smaller and larger loads bound it (None where nothing does)
            pool = self.baseline.bracketed(speed, load)
        else:
            pool = self.baseline.pooled(speed, load, min_n=n)
        if pool is not None and not learning and pool.kind == "pooled":
            # for detection, doubled: it stands for a point it has not seen (a bracket's bounds hold the slack)
            pool = dataclasses.replace(pool, std_f=2.0 * pool.std_f, std_zeta=2.0 * pool.std_zeta)
        return pool

    def _visit_serves(self, stats: BandStats | None) -> bool:
        """Whether the first estimates of the visit serve where ``stats`` (what :meth:`_baseline_for` gives)
        does: on a shaft with backlash, where no learned cell of this point serves (its damping; its frequency
        too where no learned cell bounds the point, or bounds it on one side only)."""
        return self.baseline.nonlinear and (stats is None or stats.kind == "bracketed")

    def _visit_sample(self, est: OnlineEstimate, t_s: float, speed: float, load: float, settled: bool,
                      bounds: BandStats | None) -> None:
        """Offer a settled estimate (about one a second) to the first estimates of this visit
        (:mod:`~online_id.monitoring.visit`); one that the detector would count as outside the one-sided ``bounds``
        (beyond the dead band) does not join, so that there the bound goes on serving."""
        d = self.settings.detection
        ref = self._visit_ref
        if ref is not None and not ref.matches(self._visit, load, d.load_band_nm):
            ref = self._visit_ref = None  # another visit, or the load moved: another operating point
        if not settled:
            return
        if bounds is not None and bounds.outside_f(est.f0_hz, self.detector.min_change_f, 0.0):
            return  # beyond the dead band of the bound the learned cells set: a change must not become the reference
        if ref is None:
            ref = self._visit_ref = VisitReference(self._visit, load, self.baseline.band_of(speed),
                                                   min_count=self.baseline.provisional_count,
                                                   size=self.baseline.freeze_count,
                                                   min_rel_std_f=self.baseline.min_rel_std_f,
                                                   min_rel_std_zeta=self.baseline.min_rel_std_zeta)
            self._next_visit_sample = t_s
        if t_s >= self._next_visit_sample:
            self._next_visit_sample = t_s + 1.0  # about one independent-ish estimate per second
            solution = self.estimator.solution
            if (ref.add(t_s, est.f0_hz, est.zeta, load, self.detector.min_change_f, solution,
                        self.detector.min_change_zeta) and len(ref.f) <= ref.min_count and solution is not None):
                job = self.estimator.verify_job()  # the data of the frozen first estimates, for a recheck
                if job is not None:
                    ref.window = ReferenceWindow(job.y, job.u, solution, speed, load, t_s)

    def _with_visit(self, stats: BandStats | None, load: float) -> BandStats | None:
        """``stats``, or the first estimates of this visit where they serve (:meth:`_visit_serves`) and hold
        ``provisional_count`` estimates: their frequency where nothing or one side bounds the point; their damping
        where the learned cells do not measure how far it moves between points (fewer than
        ``MIN_CELLS_DAMPING``, :meth:`Baseline.bracketed`: it moves 3-57 % between points with backlash, and
        was not compared at all), in a two-sided bracket too (:attr:`BandStats.zeta_visit`)."""
        ref = self._visit_ref
        if not self._visit_serves(stats) or ref is None or not ref.matches(self._visit, load,
                                                                           self.settings.detection.load_band_nm):
            return stats
        visit = ref.stats()
        if visit is None or stats is None:
            return visit or stats
        measured = math.isfinite(stats.std_zeta)  # the learned cells measure how far the damping moves between points
        if not math.isfinite(stats.above_f + stats.below_f):  # bounded on one side only: the visit's frequency
            return visit if not measured else dataclasses.replace(
                visit, mean_zeta=stats.mean_zeta, std_zeta=stats.std_zeta, tolerance_zeta=stats.tolerance_zeta,
                between_zeta=stats.between_zeta, zeta_visit=False)
        return stats if measured else dataclasses.replace(
            stats, mean_zeta=visit.mean_zeta, std_zeta=visit.std_zeta, tolerance_zeta=0.0, between_zeta=math.nan,
            widen=visit.widen, zeta_visit=True)

    @staticmethod
    def _of_visit(stats: BandStats, kind: str) -> bool:
        """Whether an alarm of ``kind`` against ``stats`` is checked against the visit's first estimates (their
        solution and window): of the visit's own baseline (kind ``"visit"``), or of a bracket's damping that is
        the visit's (:attr:`BandStats.zeta_visit`)."""
        return stats.kind == "visit" or (kind == DAMPING and stats.zeta_visit)

    def _own(self, stats: BandStats, speed: float, load: float) -> bool:
        """Whether ``stats`` is the baseline of the cell of ``speed`` and ``load`` itself (not the pool's or
        another band's or load's)."""
        if stats.kind == "learning":
            return True  # only a cell's own first estimates serve it while it learns
        return stats.kind in ("learned", "reference") and self._at(stats, speed, load)

    def _at(self, stats: BandStats, speed: float, load: float) -> bool:
        """Whether ``speed`` and ``load`` fall in the band and load cell of ``stats`` (any load if it has none)."""
        return (stats.band[0] <= speed < stats.band[1]
                and not abs(stats.load_nm - load) > 0.5 * self.baseline.load_band_nm)

    def _learn(self, est: OnlineEstimate, t_s: float, speed: float, load: float) -> OnlineEstimate:
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
        verified = self._verify("learn", t_s) if cell is None else False
        if verified is PENDING:
            return est
        if verified:
            est = self.estimator.estimate()
            self._estimate = est
            load = est.load_nm
        if not (est.valid and math.isfinite(load) and math.isfinite(est.f0_hz) and est.zeta > 0):
            return est
        # where nothing else bounds the point, an estimate that disagrees with the visit's first ones is held
        ref = self._with_visit(self._baseline_for(speed, load, learning=True), load)
        # the damping with half its dead band (see BandStats.disagrees): a change on its way in must not be learned
        why = (ref.disagrees(est.f0_hz, est.zeta, self.detector.min_change_f, 0.5 * self.detector.min_change_zeta)
               if ref is not None else None)
        own = ref is not None and self._own(ref, speed, load)
        n = self.baseline.release() if why is None and own else 0  # held cells: the driveline did not change
        if n:
            self.events.append(Event(t_s, "released", f"{n} held cell(s) released: at {speed:.0f} rpm, "
                                     f"{load:.1f} Nm the estimate agrees with the cell's own {ref.kind} baseline "
                                     f"({est.f0_hz:.3f} Hz against {ref.mean_f:.3f} Hz), so the driveline did "
                                     f"not change since", {"cells": n}))
        if learned:
            return est  # a learned cell stays fixed until re-learned
        versus = _versus(why, est, ref) if why is not None else ""
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
        solution = self.estimator.solution
        if solution is not None:
            self._references[self.baseline.key(speed)] = solution
        done = self.baseline.cell(speed, load)
        if why is None and solution is not None and done is not None:
            self._keep_window(done, speed, load, t_s, solution)
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

    def _confirm(self, kind: str, stats: BandStats, t_s: float) -> bool | None:
        """Before a new drift alarm: does the change stand a second look at the window, and a recheck of the
        data the baseline was learned from? True: raise it; False: withhold it; None: a check runs in the worker
        (the detector asks again at its next interval)."""
        check = self._rechecks.get(kind)
        if check is not None and (t_s - check["t_s"] > RECHECK_WAIT_S or check["band"] != stats.band):
            del self._rechecks[kind]  # of an alarm the detector no longer asks about: this one starts afresh
            check = None
        if check is None and self._still_accepted(kind, stats, t_s):
            return False
        if check is None:
            verdict = self._second_look(kind, stats, t_s)
            if verdict is not True:
                return verdict
        return self._recheck(kind, stats, t_s)

    def _still_accepted(self, kind: str, stats: BandStats, t_s: float) -> bool:
        """Does a recheck's finding that the cell's own data give the current resonance still stand?

        Each recheck's fits carry their own noise: asking the same question every few tens of seconds until
        one answer differs is how plant 1017 of the fault-free hours raised a warning (withheld at 2031 s,
        the estimate the same 31.08 Hz at 2075 s, a loss 1.6 % against the 1 % tie in the second recheck).
        The finding stands, and the alarm is withheld without another recheck, only where it can be the
        hop between minima it describes, and nothing since says otherwise: a frequency change within
        ``MINIMA_SPREAD_F`` of the baseline, at the same cell in the same visit, with the estimate within
        the recheck's tolerance of the value it accepted and no farther from the baseline than
        ``ACCEPTED_SIGMAS`` of its own standard deviations (over a long visit a healthy estimate wanders by
        more than one). A larger change (plant 13703 of family (a): a recheck withheld a 7.3 % drop after a
        15 % stiffness loss, the next one raised it) or an estimate moving on towards the alarm's side is
        rechecked afresh each time.
        """
        done = self._accepted
        est = self._estimate
        if kind != FREQUENCY or done is None or est is None or not math.isfinite(est.f0_hz):
            return False
        step = est.f0_hz / done["f0_hz"] - 1.0
        own = est.f0_std_hz / est.f0_hz if math.isfinite(est.f0_std_hz) else 0.0
        if (done["band"] != stats.band or done["visit"] != self._visit or abs(step) > done["tolerance"]
                or math.copysign(1.0, done["change"]) * step > ACCEPTED_SIGMAS * own):
            self._accepted = None
            return False
        self.events.append(Event(
            t_s, "withheld", f"{kind} alarm withheld: the estimate is where the recheck at {when_text(done['t_s'])} "
            f"found the cell's own data give it ({100 * step:+.2f} %, within its {100 * done['tolerance']:.1f} % "
            f"tolerance, no farther from the baseline than {ACCEPTED_SIGMAS:.0f} of its own standard deviations)",
            {"kind": kind, "change_pct": 100 * step, "recheck_t_s": done["t_s"]}))
        return True

    def _second_look(self, kind: str, stats: BandStats, t_s: float) -> bool | None:
        """Does a refit of the window from several starts still deviate?

        The starts include the solution the band's baseline was learned from
        (see :class:`~online_id.monitoring.detection.ChangeDetector`, *confirm*).
        None while the refit runs in the worker.
        """
        if self._of_visit(stats, kind) and self._visit_ref is not None:
            ref = self._visit_ref.solution  # the minimum the visit's first estimates sat in
        else:
            key = self.baseline.key(0.5 * (stats.band[0] + stats.band[1]))
            near = sorted(self._references, key=lambda k: abs(k - key))  # a pool: the nearest learned band's
            ref = self._references[near[0]] if near else None
        # where the baseline's own minimum fits the window nearly as well as the best, the data do not tell them
        # apart: a mismatched model (backlash) has nearly equal minima whose damping differs by 30-40 % and whose
        # resonance differs by 1-3 %, and the estimate may sit in either for minutes at a learned operating point
        if self._verify(("confirm", kind), t_s, (ref,), self._tie(kind)) is PENDING:
            return None
        est = self.estimator.estimate()
        if kind == FREQUENCY:  # beyond the bounds of a bracketed baseline
            change, width = stats.excess_f(est.f0_hz) / stats.mean_f, self.detector.min_change_f
        else:
            change, width = est.zeta / stats.mean_zeta - 1.0, self.detector.min_change_zeta
        if not math.isfinite(change) or abs(change) > width:
            return True
        self.events.append(Event(t_s, "withheld", f"{kind} alarm withheld: a refit of the window from other starts "
                                 f"is {100 * change:+.1f} % from the baseline, inside the "
                                 f"{100 * width:.1f} % dead band", {"kind": kind, "change_pct": 100 * change}))
        return False

    def _keep_window(self, cell: BandStats, speed: float, load: float, t_s: float, solution: np.ndarray) -> None:
        """Keep the window of a cell's first estimates, the ones its frozen reference holds (up to
        ``provisional_count``), for :meth:`_recheck`; later estimates do not replace it (one learned after a
        change the learning check let through would make the recheck compare the change with itself)."""
        if cell.count > self.baseline.provisional_count:
            return
        job = self.estimator.verify_job()
        if job is None:
            return
        key = self.baseline.key(speed)
        kept = [w for w in self._windows.get(key, []) if not self._at(cell, w.speed_rpm, w.load_nm)]
        self._windows[key] = kept + [ReferenceWindow(job.y, job.u, solution, speed, load, t_s)]

    def _tie(self, kind: str) -> float:
        """The share of loss within which two minima are not told apart (``detection.*_tie_pct``), for ``kind``."""
        d = self.settings.detection
        return (d.damping_tie_pct if kind == DAMPING else d.frequency_tie_pct) / 100.0

    def _reference_window(self, stats: BandStats, kind: str) -> ReferenceWindow | None:
        """The window of the first estimates of the cell of ``stats``, where ``stats`` is a cell's own baseline
        (learned, learning or from a reference run), or of this visit's (kind ``"visit"``, or the damping of a
        bracket that holds the visit's, :attr:`BandStats.zeta_visit`)."""
        if self._of_visit(stats, kind):
            ref = self._visit_ref
            return ref.window if ref is not None and ref.visit == self._visit else None
        if stats.kind not in ("learned", "learning", "reference"):
            return None
        windows = self._windows.get(self.baseline.key(0.5 * (stats.band[0] + stats.band[1])), [])
        return next((w for w in windows if self._at(stats, w.speed_rpm, w.load_nm)), None)

    def _recheck(self, kind: str, stats: BandStats, t_s: float) -> bool | None:
        """The data the cell's baseline was learned from, refitted from the current window solution: is the
        change still there within one minimum of the criterion? (:mod:`~online_id.estimation.reference`)

        Withheld where the reference data in the current minimum give the
        current estimate again (within the dead band plus one standard
        deviation of the comparison) and fit there within the second look's
        tie of their own minimum: the estimate moved to another minimum, the
        driveline did not change. Raised where no window serves or a fit
        fails. A recheck the detector has not asked about again within
        ``RECHECK_WAIT_S`` (or asks about at another band) is dropped, and the
        next alarm starts with a second look.
        """
        check = self._rechecks.get(kind)
        if check is None:
            window, solution = self._reference_window(stats, kind), self.estimator.solution
            est = self.estimator.estimate()
            if window is None or solution is None or est is None:
                return True
            # the tolerance: the dead band plus one standard deviation of the difference of two single estimates
            damping = kind == DAMPING
            value, own, spread = ((est.zeta, est.zeta_std, stats.std_zeta) if damping
                                  else (est.f0_hz, est.f0_std_hz, stats.std_f))
            noise = math.hypot(*(x if math.isfinite(x) else 0.0 for x in (own, spread))) / value if value > 0 else 0.0
            width = self.detector.min_change_zeta if damping else self.detector.min_change_f
            check = self._rechecks[kind] = {"t_s": t_s, "band": stats.band, "window": window, "f0_hz": est.f0_hz,
                                            "zeta": est.zeta, "solution": solution, "result": None,
                                            "submitted": False,
                                            "tolerance": width + (noise if math.isfinite(noise) else 0.0)}
        if not check["submitted"]:
            if self.worker.busy(WINDOW):
                return PENDING
            check["submitted"] = True
            window = check["window"]

            def finished(fits, error: str | None) -> None:
                check["result"] = (fits, error)

            self.worker.submit(WINDOW, refit_each, (window.y, window.u, self.estimator.orders,
                                                    (window.solution, check["solution"])), finished)
        if check["result"] is None:
            return PENDING
        del self._rechecks[kind]
        fits, error = check["result"]
        damping, tolerance = kind == DAMPING, check["tolerance"]
        r = judge(fits, self.estimator.dt, check["f0_hz"], check["zeta"], damping, tolerance, self._tie(kind)) \
            if error is None else None
        if r is None or not r.withhold:
            return True
        change = stats.excess_f(check["f0_hz"]) / stats.mean_f if stats.mean_f > 0 else math.nan
        if not damping and 0.0 < abs(change) <= MINIMA_SPREAD_F:
            self._accepted = {"band": stats.band, "visit": self._visit, "t_s": t_s, "tolerance": tolerance,
                              "f0_hz": check["f0_hz"], "change": change}
        window = check["window"]
        what = f"{r.zeta:.4f}" if damping else f"{r.f0_hz:.3f} Hz"
        whose = ("of this visit's first estimates" if self._of_visit(stats, kind) else
                 f"cell {window.speed_rpm:.0f} rpm, {window.load_nm:.1f} Nm was learned from")
        self.events.append(Event(
            t_s, "withheld", f"{kind} alarm withheld: the data {whose} ({when_text(window.t_s)}), refitted from "
            f"the current window solution, give {what}, {100 * r.change:+.1f} % from the current estimate, within the "
            f"{100 * tolerance:.1f} % tolerance (dead band and the comparison's noise; loss "
            f"{100 * r.loss_ratio:+.1f} % against their own solution): the estimate moved to another minimum "
            f"of the criterion, not the driveline",
            {"kind": kind, "change_pct": 100 * r.change, "tolerance_pct": 100 * tolerance,
             "loss_ratio_pct": 100 * r.loss_ratio, "reference_t_s": window.t_s}))
        return False

    def _alert_out(self, alarm: Alarm, t_s: float) -> AlertOut:
        kind = AlertKind.FREQ_DRIFT if alarm.kind == "frequency" else AlertKind.DAMPING_DRIFT
        return AlertOut(t_s, kind, alarm.level, alarm.change_pct, alarm.speed_rpm, alarm.message)

    def _raise(self, alarm: Alarm, out: list[Publication]) -> None:
        stats = self._stats
        data = alarm.as_dict()
        if stats is not None:
            load = self._estimate.load_nm if self._estimate is not None else float("nan")
            cell = f"cell {alarm.speed_rpm:.0f} rpm" + (f", {load:.0f} Nm" if math.isfinite(load) else "")
            alarm = dataclasses.replace(alarm, message=f"{alarm.message} ({cell}, against {_against(stats)})")
            data |= {"message": alarm.message, "baseline_kind": stats.kind, "baseline_source": stats.source}
        self._record(self._alert_out(alarm, alarm.detected_t_s), out, data)

    def status(self, t_s: float) -> StatusOut:
        c = self.counters
        # both counts are lower bounds of the frames lost (alive counters see losses anywhere upstream, the kernel
        # its own drops, which the counters see too): the status frame carries the larger
        return StatusOut(t_s, self.state, c.bad_frames, max(c.missing_frames, self.dropped_frames))

    # -- results ---------------------------------------------------------------------------------
    def result(self) -> dict:
        """The final estimate and the history of states and alerts (times from the stream start)."""
        est = self._estimate or self.estimator.estimate()
        inert = self.settings.inertias
        phys = None
        if np.isfinite(est.f0_hz):
            try:
                phys = self.estimator.physical(est, inert.J1, inert.J2, inert.J_total)
            except (EstimationError, FloatingPointError, ValueError):
                phys = None
        t0 = self.t_first or 0.0

        def fin(x):
            return float(x) if x is not None and math.isfinite(x) else None

        c = self.counters
        return {
            "driveline": {
                "f0_hz": fin(est.f0_hz),
                "zeta": fin(est.zeta),
                "c_s": fin(phys.c_s) if phys else None,
                "d_s": fin(phys.d_s) if phys else None,
                "J1": fin(phys.J1) if phys else None,
                "J2": fin(phys.J2) if phys else None,
                "valid": bool(est.valid),
            },
            "quality": {"residual_rms": fin(est.residual_rms), "fpe": fin(est.fpe),
                        "excitation_nm": fin(est.excitation_nm), "samples_used": est.samples_used},
            "state": self.state.name,
            "active_alarm": self.detector.active.as_dict() if self.detector.active else None,
            "withheld_alarms": dict(self.detector.withheld),
            "baseline": [b.as_dict() for b in self.baseline.bands],
            "baseline_not_learned": self._rejected,  # learning estimates that disagreed with the baselines
            "baseline_notes": [{"t_s": e.t_s - t0, "kind": e.kind, "message": e.message} for e in self.events
                               if e.kind in ("learned", "not_learned", "wide_baseline", "backlash")][-20:],
            "backlash": {"shown": self.baseline.backlash, "tests": self.backlash_tests,
                         "last_test": self.last_backlash_test.as_dict() if self.last_backlash_test else None,
                         "engaged_flank": self.engaged.summary()},
            "tracks": [{"id": t.id, "f_hz": t.f_hz, "zeta": t.zeta, "class": t.cls, "confidence": t.confidence,
                        "order": t.order} for t in self.tracker.tracks],
            "status_changes": [{"t_s": e.t_s - t0, "state": e.data["state"], "why": e.message}
                               for e in self.events if e.kind == "state"],
            "alerts": [{"t_s": a.t_s - t0, "kind": a.kind.name, "severity": a.severity, "message": a.message}
                       for a in self.alerts],
            "counters": {
                "samples": c.samples, "gaps": c.gaps, "timeouts": c.timeouts, "time_jumps": c.time_jumps,
                "bad_frames": c.bad_frames, "missing_frames": c.missing_frames,
                "dropped_frames": self.dropped_frames,
                **{f"frames_{k.name.lower()}": v for k, v in c.faults.items()},
            },
        }

    # -- persistence -----------------------------------------------------------------------------
    def get_state(self) -> dict:
        """Everything a restart must keep: estimator, learned baselines, detector (latched alarm), tracks."""
        return {"version": STATE_VERSION, "estimator": self.estimator.get_state(),
                "baseline": self.baseline.to_dict(), "detector": self.detector.to_dict(),
                "tracker": self.tracker.to_dict(), "healthy_rpm": self._healthy_rpm,
                "engaged": self.engaged.to_dict(),
                "references": {str(k): v.tolist() for k, v in self._references.items()},
                "windows": {str(k): [w.to_dict() for w in ws] for k, ws in self._windows.items()},
                "alerts": [a.__dict__ | {"kind": int(a.kind)} for a in self.alerts[-50:]]}

    def load_state(self, state: dict, new_run: bool = False) -> None:
        """Restore a state saved by :meth:`get_state`.

        ``new_run``: the state comes from an earlier run (another log, another
        day): the baselines, their reference solutions, the detector's
        statistics and latched alarms and the alerts are restored, the
        estimator and the pole tracks start afresh (their history belongs to
        the other run's time base and operating point).
        """
        if not isinstance(state, dict) or state.get("version") != STATE_VERSION:
            got = state.get("version") if isinstance(state, dict) else type(state).__name__
            raise EstimationError(f"state version {got!r} is not {STATE_VERSION}")
        if not new_run:
            self.estimator.load_state(state["estimator"])
        if "baseline" in state:
            self.baseline = Baseline.from_dict(state["baseline"])
        if "detector" in state:
            # statistics and latched alarms from the state, levels and dead bands from the config in force
            self.detector = ChangeDetector.from_dict({**state["detector"], "params": self.detector.params()})
            if new_run:
                self.detector.new_stream()
        if "tracker" in state and not new_run:
            self.tracker = PoleTracker.from_dict(state["tracker"])
        self.alerts = [AlertOut(**(a | {"kind": AlertKind(a["kind"])})) for a in state.get("alerts", [])]
        n = self.estimator.orders.n_params
        self._references = {int(k): np.asarray(v, dtype=float) for k, v in state.get("references", {}).items()
                            if isinstance(v, (list, np.ndarray)) and len(v) == n}
        windows = state.get("windows", {})
        self._windows = {}
        for k, v in windows.items() if isinstance(windows, dict) else ():
            saved = v if isinstance(v, list) and str(k).lstrip("-").isdigit() else []
            kept = [w for w in (ReferenceWindow.from_dict(x, n) for x in saved if isinstance(x, dict)) if w is not None]
            if kept:
                self._windows[int(k)] = kept
        self._rechecks = {}
        self._accepted = None
        self.engaged.load(state.get("engaged"))
        rpm = state.get("healthy_rpm")
        self._healthy_rpm = float(rpm) if isinstance(rpm, (int, float)) and not new_run else None


def _versus(why: str, est: OnlineEstimate, ref: BandStats) -> str:
    """The disagreeing quantity of ``est`` against ``ref`` for an event: "26.412 Hz against 26.583 +- 0.053 Hz"."""
    if why == FREQUENCY and ref.kind == "bracketed":
        return f"{est.f0_hz:.3f} Hz against {_bounds(ref)}, +- {ref.std_f:.3f} Hz"
    if why == FREQUENCY:
        return f"{est.f0_hz:.3f} Hz against {ref.mean_f:.3f} +- {ref.std_f:.3f} Hz"
    return f"zeta {est.zeta:.4f} against {ref.mean_zeta:.4f} +- {ref.std_zeta:.4f}"


def _against(stats: BandStats) -> str:
    """What an alarm was raised against, for people: "the learned baseline of 1500 rpm, 20 Nm (24.10 Hz), learned
    from run 3", "the pooled baseline (...)", "the bounds of the learned cells of other loads (...)", "the first
    estimates of this visit since t = 67.0 s (22.28 Hz)"."""
    if stats.kind == "visit":
        return (f"the first estimates of {stats.source} ({stats.mean_f:.2f} Hz"
                + (f", zeta {stats.mean_zeta:.4f})" if stats.zeta_visit else
                   "), the damping against the learned cells of other loads"))
    what = (f"the pooled baseline ({stats.mean_f:.2f} Hz)" if stats.kind == "pooled" else
            f"the bounds of the learned cells of other loads ({_bounds(stats)})" if stats.kind == "bracketed" else
            f"the {stats.kind} baseline of {0.5 * (stats.band[0] + stats.band[1]):.0f} rpm"
            + (f", {stats.load_nm:.0f} Nm" if math.isfinite(stats.load_nm) else "") + f" ({stats.mean_f:.2f} Hz)")
    return (what + (f", learned from {stats.source}" if stats.source else "")
            + (f", the damping against the first estimates of this visit ({stats.mean_zeta:.4f})"
               if stats.zeta_visit else ""))


def _bounds(stats: BandStats) -> str:
    """A bracketed baseline's bounds for people: ``f0 >= 20.10 Hz``, ``f0 <= ...`` or ``20.10-20.50 Hz``."""
    lo, hi = stats.bounds_f
    if math.isfinite(lo) and math.isfinite(hi):
        return f"{lo:.2f}-{hi:.2f} Hz"
    return f"f0 >= {lo:.2f} Hz" if math.isfinite(lo) else f"f0 <= {hi:.2f} Hz"


def run_bench_data(data, settings: Settings, progress=None, on_output=None, state: dict | None = None,
                   run_label: str = "", worker=None, reference: bool = False) -> Pipeline:
    """Feed bench data (a :class:`~online_id.records.BenchData`) through the pipeline, sample by sample.

    The values go through the same assembler and estimator as decoded frames
    do, in the order a bench sends them (dyno speed, engine speed, torque),
    so a replay of the same data as CAN frames gives the same result.
    ``on_output(pipeline, t_s, publications)`` is called with every non-empty
    list of publications (e.g. to acknowledge alerts as an operator would).
    ``state``: a state of an earlier run to start from (``load_state(state,
    new_run=True)``); ``run_label`` marks the cells learned in this run.
    ``worker``: where slow work runs (default: inline, see :mod:`online_id.service.offload`).
    ``reference``: cells learned now are a reference run's (as ``relearn --from``).
    """
    import dataclasses

    fs = 1.0 / float(np.median(np.diff(data.time_s)))
    if abs(fs - settings.input.sample_rate_hz) > 1e-6 * fs:
        settings = dataclasses.replace(settings, input=dataclasses.replace(settings.input, sample_rate_hz=fs))
    pipe = Pipeline(settings, worker=worker)
    if state is not None:
        pipe.load_state(state, new_run=True)
    pipe.run_label = run_label
    pipe.reference_run = reference
    t = data.time_s
    cols = (("dyno_speed", data.dyno_speed_rad_s), ("engine_speed", data.engine_speed_rad_s),
            ("dyno_torque", data.dyno_torque_nm))
    n = len(data)
    step = max(1, n // 200)
    for k in range(n):
        tk = float(t[k])
        for role, arr in cols:
            out = pipe.on_signal(SignalSample(role, float(arr[k]), tk))
            if out and on_output is not None:
                on_output(pipe, tk, out)
        if progress is not None and k % step == 0:
            progress(k / n, f"t = {tk:.1f} s")
    return pipe
