"""Sample assembly: decoded signal values -> samples on a regular time grid.

The three input roles may arrive in separate frames, at different rates, with
jitter, gaps, duplicates and alive counters that jump.  The assembler keeps
a short history per role and emits a sample for grid time :math:`T_k = T_0 +
k/f_s` as soon as every full-rate role has delivered its value for
:math:`T_k` (a frame stamped at or after :math:`T_k - \\tfrac12 \\Delta t`);
the value used is the latest one stamped at or before :math:`T_k +
\\tfrac12\\Delta t` (sample and hold).  Roles listed as *slow* (sent at a lower
rate, e.g. engine speed at 100 Hz) are held and never delay a sample.

A role silent for longer than ``timeout_s`` (by the stream's own clock: the
newest timestamp seen on any role) is a timeout: no samples are emitted, the
consumer is told (``timed_out``) and, when all roles flow again, the grid
restarts with ``discontinuity = True`` so that the estimator restarts its
regressor history instead of bridging the gap.  A frame stamped before the
last one of its role is dropped and counted; a jump of the whole clock
backwards by more than ``timeout_s`` (a log that restarts) restarts the grid.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass, field

from online_id.records import ROLES, FrameFault, SignalSample


@dataclass
class AssembledSample:
    """One sample on the grid: SI values of every role at ``t_s``."""

    t_s: float
    dyno_speed: float
    engine_speed: float
    dyno_torque: float
    discontinuity: bool = False


@dataclass
class AssemblyCounters:
    """Counts of what the assembler saw."""

    samples: int = 0
    gaps: int = 0
    timeouts: int = 0
    missing_frames: int = 0
    faults: dict[FrameFault, int] = field(default_factory=lambda: {k: 0 for k in FrameFault})

    def count(self, fault: FrameFault, n: int = 1) -> None:
        self.faults[fault] = self.faults.get(fault, 0) + n

    @property
    def bad_frames(self) -> int:
        """Frames that were received but could not be used (foreign IDs excluded)."""
        return sum(v for k, v in self.faults.items() if k not in (FrameFault.UNKNOWN_ID, FrameFault.COUNTER_JUMP))


class SampleAssembler:
    """Build regular samples from decoded values (see module notes)."""

    def __init__(
        self,
        sample_rate_hz: float,
        timeout_s: float,
        slow_roles: tuple[str, ...] = (),
        counter_modulo: int = 256,
    ) -> None:
        self.dt = 1.0 / sample_rate_hz
        self.timeout_s = timeout_s
        self.slow_roles = frozenset(slow_roles)
        self.fast_roles = tuple(r for r in ROLES if r not in self.slow_roles)
        self.counter_modulo = counter_modulo
        self.counters = AssemblyCounters()
        self._hist: dict[str, deque[tuple[float, float]]] = {r: deque(maxlen=64) for r in ROLES}
        self._last_counter: dict[str, int | None] = {r: None for r in ROLES}
        self._t0: float | None = None
        self._k = 0
        self._newest = -float("inf")
        self._start: float | None = None
        self._back_run = 0
        self._timed_out = False
        self._pending_discontinuity = True
        self.timed_out_roles: tuple[str, ...] = ()

    @property
    def timed_out(self) -> bool:
        """True while at least one role is silent for longer than the timeout."""
        return self._timed_out

    def _check_counter(self, s: SignalSample) -> bool:
        if s.counter is None:
            return True
        last = self._last_counter[s.role]
        self._last_counter[s.role] = s.counter
        if last is None:
            return True
        step = (s.counter - last) % self.counter_modulo
        if step == 0:
            self.counters.count(FrameFault.DUPLICATE)
            return False
        if step > 1:
            self.counters.count(FrameFault.COUNTER_JUMP)
            self.counters.missing_frames += step - 1
        return True

    def push(self, s: SignalSample) -> list[AssembledSample]:
        """Add one decoded value; returns the samples that became complete."""
        hist = self._hist[s.role]
        if hist and s.t_s < hist[-1][0]:
            self.counters.count(FrameFault.TIME_BACKWARDS)
            # a single stale frame is dropped; a stream that keeps arriving far in the past
            # (a log that restarted, a clock that was set back) restarts the grid
            self._back_run = self._back_run + 1 if s.t_s < self._newest - self.timeout_s else 0
            if self._back_run < 2 * len(ROLES):
                return []
            self._restart()
            hist = self._hist[s.role]
        self._back_run = 0
        if not self._check_counter(s):
            return []
        hist.append((s.t_s, s.value))
        if self._start is None:
            self._start = s.t_s
        if s.t_s > self._newest:
            self._newest = s.t_s
        return self._drain()

    def poll(self, now_s: float) -> list[AssembledSample]:
        """Advance the stream clock without a frame (for timeouts while the bus is silent)."""
        if now_s > self._newest:
            self._newest = now_s
        return self._drain()

    def _restart(self) -> None:
        for h in self._hist.values():
            h.clear()
        for r in ROLES:
            self._last_counter[r] = None
        self._t0 = None
        self._newest = -float("inf")
        self._start = None
        self._pending_discontinuity = True

    def _update_timeout(self) -> bool:
        if self._start is None:
            return False
        silent = tuple(
            r for r in ROLES
            if (self._newest - (self._hist[r][-1][0] if self._hist[r] else self._start)) > self.timeout_s
        )
        now_out = bool(silent)
        if now_out and not self._timed_out:
            self.counters.timeouts += 1
            self._t0 = None  # the grid restarts when the inputs come back
            self._pending_discontinuity = True
            for h in self._hist.values():
                h.clear()
        self._timed_out = now_out
        self.timed_out_roles = silent if now_out else ()
        return now_out

    def _value_at(self, role: str, t: float) -> float | None:
        best = None
        limit = t + 0.5 * self.dt
        for ts, v in self._hist[role]:
            if ts <= limit:
                best = v
            else:
                break
        return best

    def _drain(self) -> list[AssembledSample]:
        if self._update_timeout():
            return []
        if any(not self._hist[r] for r in ROLES):
            return []
        if self._t0 is None:
            # start the grid at the newest of the roles' first values still held
            self._t0 = max(self._hist[r][0][0] for r in self.fast_roles) if self.fast_roles else self._newest
            self._k = 0
        out: list[AssembledSample] = []
        half = 0.5 * self.dt
        while True:
            t = self._t0 + self._k * self.dt
            if any(self._hist[r][-1][0] < t - half for r in self.fast_roles):
                break
            vals = [self._value_at(r, t) for r in ROLES]
            if any(v is None for v in vals):
                # a held role has no value old enough yet: skip this grid point
                self._k += 1
                continue
            out.append(AssembledSample(t, vals[0], vals[1], vals[2], self._pending_discontinuity))
            if self._pending_discontinuity and self.counters.samples:
                self.counters.gaps += 1
            self._pending_discontinuity = False
            self.counters.samples += 1
            self._k += 1
            # forget what the next grid point can no longer use (keep one value at or before it)
            for r in ROLES:
                h = self._hist[r]
                while len(h) > 1 and h[1][0] <= t + half:
                    h.popleft()
        return out
