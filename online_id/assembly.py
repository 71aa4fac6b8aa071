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
regressor history instead of bridging the gap.

Time is checked, never trusted:

* a NaN or infinite timestamp is a bad frame (``FrameFault.BAD_TIME``);
* a frame stamped before the last one of its role is dropped
  (``TIME_BACKWARDS``);
* a frame stamped more than ``max_jump_s`` after the stream clock (the newest
  accepted timestamp) is held, not used: when :data:`JUMP_CONFIRM` frames in
  a row agree on the new time, the clock really jumped (a clock set forward,
  a log resumed after a pause) and the grid is re-anchored there; a frame in
  the old time base in between shows the held frames to be outliers (a frame
  stamped +2 h or 1e300 s), and they are counted as ``BAD_TIME``;
* :data:`JUMP_CONFIRM` frames in a row stamped more than ``timeout_s``
  before the stream clock (a clock set back, a log that restarts) re-anchor
  the grid at the new time;
* :meth:`SampleAssembler.poll` (the clock of a silent bus) advances the
  stream clock at most ``max_jump_s`` past the newest frame, so a wrong
  clock cannot hold the stream in a timeout.

Every re-anchoring is counted (``AssemblyCounters.time_jumps``) and reported
once through :meth:`SampleAssembler.take_time_jump`, so that the consumer
re-anchors its own schedules (publication, learning); the first sample after
it has ``discontinuity = True``.

Alive counters: a step of more than one is a ``COUNTER_JUMP``, counted once.
The frames it says were lost are added to ``missing_frames`` only as far as
the time since the role's previous frame allows; a counter that the time
cannot explain (a corrupt or random payload) is dropped and the expected
counter kept, and two consecutive frames that agree with each other
re-synchronise (a sender that restarted its counter).
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass, field

from online_id.records import ROLES, FrameFault, SignalSample

JUMP_CONFIRM = 2 * len(ROLES)
"""Frames in a row that must agree before a jump of the clock is believed."""


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
    time_jumps: int = 0  # re-anchorings of the grid after the stream clock jumped
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
        max_jump_s: float = 1.0,
    ) -> None:
        self.dt = 1.0 / sample_rate_hz
        self.timeout_s = timeout_s
        self.max_jump_s = max(max_jump_s, 2.0 * timeout_s)
        self.slow_roles = frozenset(slow_roles)
        self.fast_roles = tuple(r for r in ROLES if r not in self.slow_roles)
        self.counter_modulo = counter_modulo
        self.counters = AssemblyCounters()
        self._hist: dict[str, deque[tuple[float, float]]] = {r: deque(maxlen=64) for r in ROLES}
        # the same deques in ROLES order, and those of the fast roles (the hot path indexes no dict)
        self._hists = tuple(self._hist[r] for r in ROLES)
        self._fast_hists = tuple(self._hist[r] for r in self.fast_roles)
        self._last_counter: dict[str, int | None] = {r: None for r in ROLES}
        self._last_counter_t: dict[str, float] = {r: -math.inf for r in ROLES}
        self._resync: dict[str, int | None] = {r: None for r in ROLES}
        self._t0: float | None = None
        self._k = 0
        self._newest = -float("inf")  # the stream clock: newest accepted timestamp, or a poll shortly after it
        self._clock: float | None = None  # newest accepted frame timestamp
        self._ahead: list[SignalSample] = []  # frames beyond max_jump_s, held until confirmed
        self._jump: str | None = None  # the last re-anchoring, not yet taken
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
        role = s.role
        last = self._last_counter[role]
        if last is None:
            self._last_counter[role], self._last_counter_t[role] = s.counter, s.t_s
            return True
        step = (s.counter - last) % self.counter_modulo
        if step == 0:
            self.counters.count(FrameFault.DUPLICATE)
            return False
        if step > 1:
            lost = self._lost_by_time(role, s.t_s)
            cand = self._resync[role]
            if lost is not None and step - 1 > lost:
                # the time since the last frame cannot explain the jump: a corrupt counter, unless the
                # previous refused frame and this one agree (the sender restarted its counter)
                if cand is None or (s.counter - cand) % self.counter_modulo != 1:
                    if cand is None:
                        self.counters.count(FrameFault.COUNTER_JUMP)
                    self._resync[role] = s.counter
                    # the refused frame took the next slot: the sender's next frame is not a jump
                    self._last_counter[role] = (last + 1) % self.counter_modulo
                    self._last_counter_t[role] = s.t_s
                    return False
            else:
                self.counters.count(FrameFault.COUNTER_JUMP)
                self.counters.missing_frames += step - 1
        self._resync[role] = None
        self._last_counter[role], self._last_counter_t[role] = s.counter, s.t_s
        return True

    def _lost_by_time(self, role: str, t_s: float) -> float | None:
        """Most frames that can have been lost since the role's last counted frame (None: unknown rate)."""
        if role in self.slow_roles:
            return None
        return 1.5 * (t_s - self._last_counter_t[role]) / self.dt + 2.0

    def push(self, s: SignalSample) -> list[AssembledSample]:
        """Add one decoded value; returns the samples that became complete."""
        t = s.t_s
        if not math.isfinite(t):
            self.counters.count(FrameFault.BAD_TIME)
            return []
        if self._clock is not None:
            if t > self._clock + self.max_jump_s:
                return self._hold_ahead(s)
            if self._ahead:  # back in the old time base: the held frames were outliers
                self.counters.count(FrameFault.BAD_TIME, len(self._ahead))
                self._ahead.clear()
            if t < self._clock - self.timeout_s:
                self.counters.count(FrameFault.TIME_BACKWARDS)
                # a single stale frame is dropped; a stream that keeps arriving far in the past
                # (a log that restarted, a clock that was set back) re-anchors the grid
                self._back_run += 1
                if self._back_run < JUMP_CONFIRM:
                    return []
                self._reanchor(t)
        self._back_run = 0
        return self._accept(s)

    def _hold_ahead(self, s: SignalSample) -> list[AssembledSample]:
        """A frame far ahead of the stream clock: an outlier, or the first of a clock that jumped."""
        if self._ahead and abs(s.t_s - self._ahead[-1].t_s) > self.max_jump_s:
            if len(self._ahead) > 1:  # frames that agree with each other outvote the one that does not
                self.counters.count(FrameFault.BAD_TIME)
                return []
            self.counters.count(FrameFault.BAD_TIME, len(self._ahead))
            self._ahead.clear()
        self._ahead.append(s)
        if len(self._ahead) < JUMP_CONFIRM:
            return []
        held, self._ahead = self._ahead, []
        self._reanchor(held[0].t_s)
        out: list[AssembledSample] = []
        for h in held:
            out.extend(self.push(h))
        return out

    def _reanchor(self, t_s: float) -> None:
        jump = t_s - (self._clock if self._clock is not None else t_s)
        self.counters.time_jumps += 1
        self._jump = f"stream clock jumped by {jump:+.3f} s: sample grid re-anchored at t = {t_s:.3f} s"
        self._restart()

    def take_time_jump(self) -> str | None:
        """The last re-anchoring of the grid (a message), once; None when there was none since."""
        jump, self._jump = self._jump, None
        return jump

    @property
    def now_s(self) -> float:
        """The stream clock (NaN before the first accepted frame)."""
        return self._newest if self._newest > -math.inf else math.nan

    def _accept(self, s: SignalSample) -> list[AssembledSample]:
        hist = self._hist[s.role]
        if hist and s.t_s < hist[-1][0]:
            self.counters.count(FrameFault.TIME_BACKWARDS)
            return []
        if not self._check_counter(s):
            return []
        hist.append((s.t_s, s.value))
        if self._start is None:
            self._start = s.t_s
        if self._clock is None or s.t_s > self._clock:
            self._clock = s.t_s
        if s.t_s > self._newest:
            self._newest = s.t_s
        return self._drain()

    def poll(self, now_s: float) -> list[AssembledSample]:
        """Advance the stream clock without a frame (for timeouts while the bus is silent).

        The clock moves at most ``max_jump_s`` past the newest frame: enough
        for any timeout, and a wrong ``now_s`` cannot hold the stream in one.
        """
        if self._clock is None or not math.isfinite(now_s):
            return []
        now_s = min(now_s, self._clock + self.max_jump_s)
        if now_s > self._newest:
            self._newest = now_s
        return self._drain()

    def _restart(self) -> None:
        for h in self._hists:
            h.clear()
        for r in ROLES:
            self._last_counter[r] = None
            self._resync[r] = None
        self._t0 = None
        self._newest = -float("inf")
        self._clock = None
        self._start = None
        self._back_run = 0
        self._timed_out = False
        self.timed_out_roles = ()
        self._pending_discontinuity = True

    def _update_timeout(self) -> bool:
        start = self._start
        if start is None:
            return False
        newest, limit = self._newest, self.timeout_s
        if not self._timed_out:  # the common case, checked without building anything
            for h in self._hists:
                if newest - (h[-1][0] if h else start) > limit:
                    break
            else:
                return False
        silent = tuple(
            r for r, h in zip(ROLES, self._hists) if newest - (h[-1][0] if h else start) > limit
        )
        now_out = bool(silent)
        if now_out and not self._timed_out:
            self.counters.timeouts += 1
            self._t0 = None  # the grid restarts when the inputs come back
            self._pending_discontinuity = True
            for h in self._hists:
                h.clear()
        self._timed_out = now_out
        self.timed_out_roles = silent if now_out else ()
        return now_out

    @staticmethod
    def _value_at(h: deque[tuple[float, float]], limit: float) -> float | None:
        """The latest value of one role's history stamped at or before ``limit`` (None: none yet)."""
        best = None
        for ts, v in h:
            if ts <= limit:
                best = v
            else:
                break
        return best

    def _drain(self) -> list[AssembledSample]:
        if self._update_timeout():
            return []
        hists = self._hists
        for h in hists:
            if not h:
                return []
        dt = self.dt
        if self._t0 is None:
            # start the grid at the newest of the roles' first values still held
            self._t0 = max(h[0][0] for h in self._fast_hists) if self._fast_hists else self._newest
            self._k = 0
        out: list[AssembledSample] = []
        half = 0.5 * dt
        t0, fast, value_at, counters = self._t0, self._fast_hists, self._value_at, self.counters
        h0, h1, h2 = hists
        while True:
            t = t0 + self._k * dt
            lim = t - half
            for h in fast:
                if h[-1][0] < lim:
                    return out
            limit = t + half
            v0, v1, v2 = value_at(h0, limit), value_at(h1, limit), value_at(h2, limit)
            if v0 is None or v1 is None or v2 is None:
                # a held role has no value old enough yet: skip this grid point
                self._k += 1
                continue
            out.append(AssembledSample(t, v0, v1, v2, self._pending_discontinuity))
            if self._pending_discontinuity and counters.samples:
                counters.gaps += 1
            self._pending_discontinuity = False
            counters.samples += 1
            self._k += 1
            # forget what the next grid point can no longer use (keep one value at or before it)
            for h in hists:
                while len(h) > 1 and h[1][0] <= limit:
                    h.popleft()
