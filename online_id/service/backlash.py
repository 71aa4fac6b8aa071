"""The backlash tests the detection policy runs: their input samples, their schedule, and the alarm a change of
the engaged flank raises.

:class:`BacklashTests` is a part the :class:`~online_id.service.policy.DetectionPolicy` owns.  It keeps the input
samples of the last ``BACKLASH_TEST_MAX_S`` while a test may run, says when one is due (until a point shows
backlash, once per visit of an operating point; on a shaft that showed backlash, with ``detection.engaged_flank``,
every ``EVERY_S`` of a visit, :mod:`online_id.monitoring.engaged`) and starts it in the worker on the operating
point's steady samples (:mod:`online_id.diagnose.linearity`).  What a test finds goes back to the policy, which
judges it.
"""

from __future__ import annotations

import itertools
import math
from collections import deque
from typing import Callable

import numpy as np

from online_id.config import DetectionSettings
from online_id.diagnose.bench_data import DEFAULT_PULSES_PER_REV
from online_id.diagnose.linearity import BacklashTest, backlash_test
from online_id.monitoring import engaged as engaged_flank
from online_id.monitoring.detection import FREQUENCY, Alarm, alarm_message
from online_id.monitoring.engaged import EngagedChange
from online_id.service.events import LINEARITY

BACKLASH_TEST_MAX_S = 30.0  # the backlash test takes at most this much of an operating point's steady samples


class BacklashTests:
    """The backlash tests' samples, schedule and count (see module notes).

    Parameters
    ----------
    detection
        The detection settings in force (``backlash_test_s``, ``engaged_flank``).
    sample_rate_hz
        The input sample rate.
    pulses_per_rev
        The compression orders the test declares (the model's; 0 or None: the bench diagnosis's default).
    worker
        Where the tests run (:mod:`online_id.service.offload`): ``submit(lane, fn, args, done)`` and ``busy(lane)``.
    """

    def __init__(self, detection: DetectionSettings, sample_rate_hz: float, pulses_per_rev: int | None,
                 worker) -> None:
        self.detection = detection
        self.sample_rate_hz = sample_rate_hz
        # the compression orders the test declares: the model's, else the bench diagnosis's default (a test with
        # none would fail on every point of a config without model.pulses_per_rev)
        self.pulses_per_rev = pulses_per_rev or DEFAULT_PULSES_PER_REV
        self.worker = worker
        # the input samples of the last BACKLASH_TEST_MAX_S (t, dyno speed, engine speed, torque)
        self.samples: deque[tuple[float, float, float, float]] = deque(
            maxlen=max(1, int(BACKLASH_TEST_MAX_S * sample_rate_hz)))
        self.count = 0  # the tests that came back
        self.last: BacklashTest | None = None  # the last test that was done
        self._visit_tested = -1  # the visit whose samples the last test took
        self._next_engaged = -math.inf  # stream time of the next engaged-flank reading in this visit

    def keep(self, t_s: float, dyno_speed: float, engine_speed: float, dyno_torque: float, restart: bool,
             wanted: bool) -> None:
        """An input sample, kept if ``wanted`` (a test may still run) and tests run at all; ``restart``: the
        stream broke before it (the samples kept so far are dropped)."""
        if restart:
            self.samples.clear()
        if self.detection.backlash_test_s > 0 and wanted:
            self.samples.append((t_s, dyno_speed, engine_speed, dyno_torque))

    def on_time_jump(self) -> None:
        """The stream clock jumped: the engaged flank's next reading is due at once."""
        self._next_engaged = -math.inf

    def due(self, t_s: float, visit: int, nonlinear: bool) -> float | None:
        """The most steady samples [s] a test due now at stream time ``t_s`` in ``visit`` takes, or None (none
        is due, or one runs).  ``nonlinear``: the shaft showed backlash."""
        d = self.detection
        if d.backlash_test_s <= 0 or self.worker.busy(LINEARITY):
            return None
        if not nonlinear:
            return BACKLASH_TEST_MAX_S if self._visit_tested != visit else None
        if d.engaged_flank and (self._visit_tested != visit or t_s >= self._next_engaged):
            return engaged_flank.WINDOW_S
        return None

    def start(self, t_s: float, visit: int, steady_s: float, window_s: float,
              done: Callable[[BacklashTest | None, str | None], None]) -> None:
        """Start a test in the worker on the last ``min(steady_s, window_s)`` of samples, the speed having been
        steady for ``steady_s``, if that covers ``detection.backlash_test_s``; ``done(test, error)`` takes its
        outcome."""
        least = self.detection.backlash_test_s
        steady = min(steady_s, window_s)
        rate = self.sample_rate_hz
        if steady < least or len(self.samples) < least * rate:
            return
        self._visit_tested = visit
        self._next_engaged = t_s + engaged_flank.EVERY_S
        n = min(len(self.samples), int(steady * rate))
        rows = np.asarray(list(itertools.islice(self.samples, len(self.samples) - n, None)), dtype=float)

        def finished(test: BacklashTest | None, error: str | None) -> None:
            self.count += 1
            if test is not None:
                self.last = test
            done(test, error)

        self.worker.submit(LINEARITY, backlash_test,
                           (rows[:, 0], rows[:, 3], rows[:, 1], rows[:, 2], self.pulses_per_rev), finished)


def engaged_alarm(change: EngagedChange, latched: Alarm | None) -> Alarm:
    """The alarm of a change of the engaged flank; ``latched``: an alarm of its kind already latched, whose onset
    it keeps (an escalation)."""
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
    return Alarm(change.kind, change.level, since, change.detected_t_s, change.speed_rpm, pct, stiff, message)
