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

Its parts: the :class:`~online_id.service.assembly.SampleAssembler` (frames' values to samples on a grid),
the estimator (:class:`~online_id.estimation.online.OnlineDriveline`), the excitation signal, and the
detection policy (:class:`~online_id.service.policy.DetectionPolicy`, :attr:`Pipeline.policy`), which judges
each publication's estimate and returns the alerts due.  Slow work runs in the worker
(:mod:`online_id.service.offload`); the state a restart keeps is :mod:`online_id.service.persistence`'s
document of the estimator and the policy; what a run gives (:meth:`Pipeline.result`) is
:mod:`online_id.service.summary`'s.
"""

from __future__ import annotations

import math
from collections import deque
from collections.abc import Callable

import numpy as np

from online_id.service.assembly import AssembledSample, SampleAssembler
from online_id.config import Settings
from online_id.monitoring.baseline import Baseline
from online_id.monitoring.detection import ChangeDetector
from online_id.monitoring.engaged import EngagedFlank
from online_id.estimation.model import ArmaxOrders
from online_id.estimation.online import OnlineDriveline, OnlineEstimate, physical_parameters
from online_id.estimation.window import RefitJob, solve
from online_id.analysis.physical import DrivelineParameters
from online_id.monitoring.tracks import PoleTracker
from online_id.analysis.excitation import Excitation
from online_id.service.events import MAX_EVENTS, PHYSICAL, WINDOW, Event
from online_id.service.offload import InlineWorker
from online_id.service.persistence import restore_state, state_document
from online_id.service.policy import DetectionPolicy
from online_id.service.summary import run_summary
from online_id.records import (
    AlertKind,
    AlertOut,
    EstimateOut,
    FrameFault,
    Publication,
    QualityOut,
    ServiceState,
    SignalSample,
    StatusOut,
)

COMMAND_ACK = 1
COMMAND_RELEARN = 2
COMMAND_RESET = 3
QUIET_S = 0.005
"""With a worker process, no slow work (a job handed over, a result adopted) starts within this much stream time
before a publication falls due (at most a quarter of the publish interval): its frames then never wait behind a
job's copy of the window (up to a millisecond or two on a busy PC) when their sample comes (see
:meth:`Pipeline.publication_near`)."""


class Pipeline:
    """The streaming pipeline (see module notes)."""

    def __init__(self, settings: Settings, worker=None) -> None:
        self.settings = settings
        s = settings
        # slow work (window refits, multi-start checks, physical fits): at once in replay, in a worker process
        # in the live service (see online_id.service.offload)
        self._worker = worker if worker is not None else InlineWorker()
        self.assembler = SampleAssembler(s.input.sample_rate_hz, s.input.timeout_s, s.input.slow_roles,
                                         max_jump_s=s.input.max_time_jump_s)
        self.estimator = self._new_estimator()
        self.excitation = Excitation(s)
        self.state = ServiceState.STARTING
        self.t_s = float("nan")
        self.t_first: float | None = None
        self._next_publish: float | None = None
        self._poll_deferred = False  # the worker was not polled on the last sample (it published)
        self._rest: tuple[OnlineEstimate, list[AssembledSample]] | None = None  # see on_signal(split=True)
        self._ahead: tuple[OnlineEstimate, Callable[[], None]] | None = None  # see estimate_ahead
        self._quiet_s = min(QUIET_S, 0.25 / s.publish.rate_hz)  # see publication_near
        self._window_since: float | None = None  # stream time the last window job was submitted
        self._next_physical: float | None = None
        self._physical: DrivelineParameters | None = None
        self._refit_pending = False
        self._detect_pending: tuple[OnlineEstimate, float, float] | None = None  # see _publish_rest
        self._estimate: OnlineEstimate | None = None
        self._resets_seen = 0
        self._reset_times: list[float] = []
        self.events: deque[Event] = deque(maxlen=MAX_EVENTS)
        self.alerts: list[AlertOut] = []
        self.alerts_total = 0  # alerts raised since start (the list keeps the last MAX_EVENTS)
        # tracking, learning and detection on the published estimates (see online_id.service.policy)
        self.policy = DetectionPolicy(settings, dt=self.estimator.dt, worker=self._worker,
                                      submit_window=self._submit_window, clock=lambda: self.t_s,
                                      events=self.events, record=self._record)
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
    def worker(self):
        """Where the slow work runs (the detection policy's too: fixed at construction)."""
        return self._worker

    # -- the detection policy's parts (read-only; see online_id.service.policy) ---------------------
    @property
    def baseline(self) -> Baseline:
        """The learned baselines."""
        return self.policy.baseline

    @property
    def detector(self) -> ChangeDetector:
        """The change detector (its latched alarms, the alarms withheld)."""
        return self.policy.detector

    @property
    def engaged(self) -> EngagedFlank:
        """The engaged flank's readings on a shaft that showed backlash."""
        return self.policy.engaged

    @property
    def tracker(self) -> PoleTracker:
        """The pole tracks."""
        return self.policy.tracker

    @property
    def run_label(self) -> str:
        """The run the cells learned now are marked with (replay: the log's name)."""
        return self.policy.run_label

    @run_label.setter
    def run_label(self, label: str) -> None:
        self.policy.run_label = label

    @property
    def reference_run(self) -> bool:
        """The cells learned now are a reference (``relearn --from LOG``)."""
        return self.policy.reference_run

    @reference_run.setter
    def reference_run(self, reference: bool) -> None:
        self.policy.reference_run = reference

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
    def on_signal(self, sample: SignalSample, split: bool = False) -> list[Publication]:
        """One decoded value from a frame.

        ``split``: return as soon as a publication's estimate is made, with the
        :class:`EstimateOut` last, whose frame the live service owes the bus at
        once; the rest of that publication (its sample's update of the model
        included: a publication's estimate is of the model as its sample finds
        it), and of the samples this value completed, come from :meth:`finish`,
        which must be called next.  The publications and the state are the same
        as without it.
        """
        return self.on_value(sample.role, sample.value, sample.t_s, sample.counter, split)

    def on_value(self, role: str, value: float, t_s: float, counter: int | None = None,
                 split: bool = False) -> list[Publication]:
        """:meth:`on_signal` of a :class:`SignalSample` given by its fields (no sample object to make: the replay
        of bench data takes this, three values per sample)."""
        if self._rest is not None:
            raise RuntimeError("Pipeline.on_signal: the split publication before was not finished (call finish())")
        assembler = self.assembler
        samples = assembler.push_value(role, value, t_s, counter)  # checks the timestamp (see online_id.service.assembly)
        if samples:
            if self.t_first is None:
                self.t_first = samples[0].t_s
            publishes = self._next_publish is not None and samples[-1].t_s >= self._next_publish
            if self._poll_deferred or not (publishes or self.publication_near(samples[-1].t_s)):
                # adopt finished slow work before the samples use the model; not on a sample that publishes
                # (adopting a window fit takes up to a millisecond): its estimate goes out first, the result
                # is adopted on the next sample (an inline worker, as replay's, has nothing to adopt here);
                # with a worker process, not within QUIET_S before it either
                self._drop_ahead()
                self.worker.poll()
                self._poll_deferred = False
            else:
                self._poll_deferred = publishes
        return self._consume(samples, assembler.now_s, split)

    def finish(self) -> list[Publication]:
        """What :meth:`on_signal` with ``split`` left: the rest of its publication, then the samples after it."""
        if self._rest is None:
            return []
        est, samples = self._rest
        self._rest = None
        out: list[Publication] = []
        self._run(samples, out, made=est)
        return out

    @property
    def split_pending(self) -> bool:
        """:meth:`on_signal` with ``split`` left the rest of a publication for :meth:`finish`."""
        return self._rest is not None

    @property
    def estimate_ahead(self) -> OnlineEstimate | None:
        """With a worker process, on the sample before a publication: that publication's estimate, made already
        (None: none made, or dropped since).

        A publication's estimate is of the model as its sample finds it: after the update of the sample before,
        which makes it then (:meth:`OnlineDriveline.estimate_ahead`), so that the publication's frame, which the
        live loop owes the bus at once, waits for no estimate (and the live loop encodes its OidEstimate ahead
        too).  Anything that may touch the estimator before the publication's sample (a worker's result
        adopted, a tick, a command, the state saved or loaded, a sample that does not publish) first undoes it
        (:meth:`_drop_ahead`), and the publication makes its estimate afresh: the estimate is the same either
        way.
        """
        return self._ahead[0] if self._ahead is not None else None

    def _drop_ahead(self) -> None:
        """Undo the estimate made ahead, if any (see estimate_ahead)."""
        if self._ahead is not None:
            self._ahead[1]()
            self._ahead = None

    @property
    def publishes_next(self) -> bool:
        """With a worker process: the next sample publishes (the live loop readies the publication's encoding)."""
        return (self.worker.asynchronous and self._next_publish is not None
                and 0.0 <= self._next_publish - self.t_s <= self.assembler.dt)

    def publication_near(self, t_s: float) -> bool:
        """With a worker process: a publication falls due within ``QUIET_S`` of stream time ``t_s`` (or fell due
        less than that ago and waits for its sample), and no slow work starts (see ``QUIET_S``).  Always False
        with the inline worker, whose jobs take no stream time: a replay's schedule depends only on the
        samples."""
        return (self.worker.asynchronous and self._next_publish is not None
                and abs(self._next_publish - t_s) <= self._quiet_s)

    def tick(self, now_s: float) -> list[Publication]:
        """The stream clock moved without a frame (silence on the bus, the end of a log)."""
        self._drop_ahead()
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
        out.extend(self.policy.assess(est, t_s, speed, self.estimator))
        if self.policy.estimate is not est:  # a new cell learned from a multi-start refit: the estimate now
            self._estimate = self.policy.estimate

    def on_command(self, command: int, t_s: float) -> list[Publication]:
        """A command frame: acknowledge alerts, re-learn, reset the estimator."""
        self.commands += 1
        self._drop_ahead()
        out: list[Publication] = []
        if command == COMMAND_RESET:
            self.estimator = self._new_estimator()
            self._estimate = None
            self._physical = None
            self._detect_pending = None
            self.events.append(Event(t_s, "command", "estimator reset on command"))
        elif command == COMMAND_ACK:
            self.policy.acknowledge()
            self.events.append(Event(t_s, "command", "alerts acknowledged"))
            out.append(AlertOut(t_s, AlertKind.NONE, 0, 0.0, self.estimator.speed_rpm, "alerts acknowledged"))
        elif command == COMMAND_RELEARN:
            self.policy.relearn()
            self.events.append(Event(t_s, "command", "baselines forgotten: learning anew"))
            out.append(AlertOut(t_s, AlertKind.NONE, 0, 0.0, self.estimator.speed_rpm, "baselines re-learned"))
        return out

    def process(self, a: AssembledSample) -> None:
        """Feed one assembled sample to the estimator (also used by offline runs)."""
        if self._ahead is not None:
            self._drop_ahead()
        restart = a.discontinuity and self.counters.samples > 1
        if restart:
            self.estimator.restart_history()
        self.policy.keep_sample(a.t_s, a.dyno_speed, a.engine_speed, a.dyno_torque, restart)
        self.estimator.update(a.dyno_speed, a.engine_speed, a.dyno_torque)

    def _consume(self, samples: list[AssembledSample], now_s: float, split: bool = False) -> list[Publication]:
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
        if samples:
            self._run(samples, out, split)
        return out

    def _run(self, samples: list[AssembledSample], out: list[Publication], split: bool = False,
             made: OnlineEstimate | None = None) -> None:
        """The samples into the estimator, publications and slow work into ``out`` (``split``: see on_signal;
        ``made``: the estimate of the publication on ``samples[0]``, which the split made)."""
        for i, a in enumerate(samples):
            if self._next_publish is None:
                self._next_publish = a.t_s
                self._next_physical = a.t_s
                self._set_state(ServiceState.LEARNING, a.t_s, out)
            est = made if i == 0 else None
            ahead, self._ahead = self._ahead, None  # made on the sample before (see estimate_ahead)
            if est is None and a.t_s >= self._next_publish:
                # a publication: the estimate is the model's as this sample finds it (its update comes after,
                # with the rest of the publication): the live loop sends it before the sample's work
                self._next_publish += 1.0 / self.settings.publish.rate_hz
                if self._next_publish <= a.t_s:  # after a gap: no burst of publications
                    self._next_publish = a.t_s + 1.0 / self.settings.publish.rate_hz
                est = self._publish_estimate(a.t_s, out, ahead[0] if ahead is not None else None)
                if split:
                    self._rest = (est, samples[i:])
                    return
            elif ahead is not None:  # this sample does not publish: the estimate is made when one does
                ahead[1]()
            self.process(a)
            self.t_s = a.t_s
            rels = self.estimator.rels
            if rels.n_resets != self._resets_seen:
                self._resets_seen = rels.n_resets
                self._reset_times.append(a.t_s)
                self._alert(out, a.t_s, AlertKind.ESTIMATOR_RESET, 2, 0.0,
                            f"estimator reset after a numerical failure (resets: {rels.n_resets})")
            if self.excitation.enabled:  # (step() does nothing else when it is not)
                healthy = self.state in (ServiceState.LEARNING, ServiceState.TRACKING)
                exc = self.excitation.step(a.t_s, healthy, self.estimator.speed_rpm)
                if exc:
                    out.append(exc)
            if est is not None:
                out.extend(self._publish_rest(est, a.t_s))
            elif self._detect_pending is not None:
                self._run_pending_detection(out)
            # slow work starts on a sample that publishes nothing, so it never delays an estimate; with the
            # process worker it runs beside the stream and is adopted when it is back (``worker.poll``), and
            # it waits while a publication is near
            elif self.publication_near(a.t_s):
                # the next sample publishes (see estimate_ahead); half a sample's margin, as the schedule's sum and the
                # sample grid may round the publication's time either way
                if a.t_s + 1.5 * self.assembler.dt >= self._next_publish:
                    self._ahead = self.estimator.estimate_ahead()
            elif self.estimator.refit_due and not self.worker.busy(WINDOW):
                self._submit_refit()
            elif self._refit_pending and not self.worker.busy(PHYSICAL):
                self._submit_physical()

    def poll_worker(self) -> int:
        """Adopt the results of finished slow work (also done before every sample)."""
        self._drop_ahead()
        return self.worker.poll()

    @property
    def slow_work_lag_s(self) -> float:
        """Stream seconds since the window job in flight (a refit or check) was submitted, 0 when none is: how
        far the stream has run ahead of the slow work (on a bench, well under a second; a stream fed faster
        than real time, as the demo and the soak feed it, can outrun a worker the machine starves)."""
        if self._window_since is None or not self.worker.busy(WINDOW):
            return 0.0
        return max(0.0, self.t_s - self._window_since)

    def _submit_window(self, fn, args: tuple, done) -> None:
        """A window job (a refit or a multi-start check) to the worker: its lag counts from now."""
        self._window_since = self.t_s
        self.worker.submit(WINDOW, fn, args, done)

    def _submit_refit(self) -> None:
        """The due window refit (10-20 ms, a cold one about 0.5 s) to the worker."""
        estimator = self.estimator
        job = estimator.refit_job()
        if job is not None:
            self._submit_window(solve, (job,), lambda fit, err: estimator.complete(job, fit, err))

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
        self.policy.on_state(state)
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
        self.policy.on_time_jump()
        self.events.append(Event(t_s, "time", message, {"time_jumps": self.counters.time_jumps}))
        out.append(self.status(t_s))

    def _state_of(self, est: OnlineEstimate, t_s: float) -> ServiceState:
        recent = [t for t in self._reset_times if t_s - t < 10.0]
        if len(recent) >= 3:
            return ServiceState.FAULT
        if est.frozen:
            return ServiceState.NO_EXCITATION
        return ServiceState.TRACKING if est.valid else ServiceState.LEARNING

    def _publish_estimate(self, t_s: float, out: list[Publication], made: OnlineEstimate | None = None
                          ) -> OnlineEstimate:
        """The estimate of a publication into ``out``, first of its publications (the rest: _publish_rest);
        ``made``: the estimate made ahead on the sample before (see estimate_ahead)."""
        est = made if made is not None else self.estimator.estimate(defer_std=True)  # completed by _publish_rest
        self._estimate = est
        phys = self._physical
        nan = float("nan")
        out.append(EstimateOut(t_s, est.f0_hz, est.zeta, phys.c_s if phys and phys.c_s else nan,
                               phys.d_s if phys and phys.d_s else nan, est.valid))
        return est

    def _publish_rest(self, est: OnlineEstimate, t_s: float) -> list[Publication]:
        """The rest of the publication of ``est``: the state it gives, its quality, the status."""
        out: list[Publication] = []
        est = self._estimate = self.estimator.complete_estimate(est)
        state = self._state_of(est, t_s)
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
        out.append(QualityOut(t_s, est.residual_rms, est.fpe, est.excitation_nm, est.samples_used))
        out.append(self.status(t_s))
        return out

    def status(self, t_s: float) -> StatusOut:
        c = self.counters
        # both counts are lower bounds of the frames lost (alive counters see losses anywhere upstream, the kernel
        # its own drops, which the counters see too): the status frame carries the larger
        return StatusOut(t_s, self.state, c.bad_frames, max(c.missing_frames, self.dropped_frames))

    # -- state -----------------------------------------------------------------------------------
    def get_state(self) -> dict:
        """Everything a restart must keep (:func:`~online_id.service.persistence.state_document`)."""
        self._drop_ahead()
        return state_document(self.estimator, self.policy, self.alerts)

    def load_state(self, state: dict, new_run: bool = False) -> None:
        """Restore a state saved by :meth:`get_state` (``new_run``: see
        :func:`~online_id.service.persistence.restore_state`)."""
        self._drop_ahead()
        self.alerts = restore_state(state, self.estimator, self.policy, new_run)

    # -- results ---------------------------------------------------------------------------------
    def result(self) -> dict:
        """The final estimate and the history of states and alerts (times from the stream start,
        :func:`~online_id.service.summary.run_summary`)."""
        return run_summary(self)

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
    return feed_bench_data(pipe, data, progress=progress, on_output=on_output)


_FEED_CHUNK = 4096


def feed_bench_data(pipe: Pipeline, data, start: int = 0, stop: int | None = None, progress=None,
                    on_output=None) -> Pipeline:
    """Feed samples ``start`` to ``stop`` (default: the end) of bench data to ``pipe`` as
    :func:`run_bench_data` does (``progress``, ``on_output``: as there)."""
    t = data.time_s
    cols = (("dyno_speed", data.dyno_speed_rad_s), ("engine_speed", data.engine_speed_rad_s),
            ("dyno_torque", data.dyno_torque_nm))
    n = len(data) if stop is None else stop
    step = max(1, n // 200)
    on_value = pipe.on_value
    for k0 in range(start, n, _FEED_CHUNK):  # (Python floats, converted a chunk at a time)
        k1 = min(n, k0 + _FEED_CHUNK)
        chunk = [(role, np.asarray(arr[k0:k1], dtype=float).tolist()) for role, arr in cols]
        for k, tk in enumerate(np.asarray(t[k0:k1], dtype=float).tolist(), k0):
            for role, values in chunk:
                out = on_value(role, values[k - k0], tk)
                if out and on_output is not None:
                    on_output(pipe, tk, out)
            if progress is not None and k % step == 0:
                progress(k / n, f"t = {tk:.1f} s")
    return pipe
