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

* a NaN or infinite timestamp, or one beyond :data:`MAX_TIME_S` either way
  (``1e300``), is a bad frame (``FrameFault.BAD_TIME``), the first frame's
  too;
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

De-jittering.  A frame's timestamp is when the receiving PC took it, not
when the bench sent it: a PC busy with other work stamps frames late by
milliseconds (the kernel's receive work waits for a CPU; a USB adapter
delivers 1 ms batches), by a different amount for each frame.  On a 1 kHz
grid a frame late by more than half a period is taken one sample late: a
time jitter on the speeds that spoils the fit (measured: the frames the
live service received on a loaded machine, replayed, never gave a valid
estimate; stamped on the bench's clock they did at 10.1 s).  A fast role's
frames carry an alive counter: its steps count the sender's periods
between frames (lost frames included), so frame :math:`k` was sent at
:math:`k\\,\\Delta t` on the sender's clock plus an offset, and its arrival
is that plus a delay that is never negative.  The frame is stamped
:math:`k\\,\\Delta t + \\min_j (a_j - j\\,\\Delta t)`, the least such
difference over the role's last :data:`DEJITTER_WINDOW_S` (a running
minimum: a late frame moves nothing, a sender's clock that runs fast or
slow against :math:`\\Delta t` is followed within the window).  A frame
far behind that (more than half the timeout: the sender paused with its
counter running, or its clock jumped), a counter the time cannot explain,
a role without a counter or a slow role is stamped on arrival, as before.
Once every such role has a full window, the grid is moved once onto the
phase of their frames (at most half a period; not where it is within a
tenth of one), since late first frames set it.  Stamps on the bench's
clock (a simulation, a clean log) are left as they are.

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

DEJITTER_WINDOW_S = 1.0
"""A fast role's frame is stamped at its send time: its sequence number (by the alive counter) times the period,
plus the least lateness over this many seconds of the role's frames (see module notes, *de-jittering*)."""

JUMP_CONFIRM = 2 * len(ROLES)
"""Frames in a row that must agree before a jump of the clock is believed."""
MAX_TIME_S = 1e10
"""A timestamp beyond this (Unix time of the year 2286; a stream's own time from 0) is no time."""


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
        # de-jittering (see module notes): the send time of each fast role's last frame, and the send periods since
        # the role's previous frame by its alive counter (None: unknown)
        self._step: int | None = None
        self._seq: dict[str, int] = {r: 0 for r in ROLES}
        self._minq: dict[str, deque[tuple[int, float]]] = {r: deque() for r in ROLES}
        self._window_n = max(1, int(round(DEJITTER_WINDOW_S * sample_rate_hz)))
        self.max_lag_s = 0.5 * timeout_s
        self._t0: float | None = None
        self._k = 0
        self._phased = False  # the grid was moved onto the send clocks' phase (see _phase_grid)
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

    def _check_counter(self, role: str, counter: int, t_s: float) -> bool:
        """The alive counter of a frame of ``role`` stamped ``t_s``: False when the frame is refused."""
        self._step = None
        last = self._last_counter[role]
        if last is None:
            self._last_counter[role], self._last_counter_t[role] = counter, t_s
            return True
        step = (counter - last) % self.counter_modulo
        if step == 0:
            self.counters.count(FrameFault.DUPLICATE)
            return False
        if step > 1:
            lost = self._lost_by_time(role, t_s)
            cand = self._resync[role]
            if lost is not None and step - 1 > lost:
                # the time since the last frame cannot explain the jump: a corrupt counter, unless the
                # previous refused frame and this one agree (the sender restarted its counter)
                if cand is None or (counter - cand) % self.counter_modulo != 1:
                    if cand is None:
                        self.counters.count(FrameFault.COUNTER_JUMP)
                    self._resync[role] = counter
                    # the refused frame took the next slot: the sender's next frame is not a jump
                    self._last_counter[role] = (last + 1) % self.counter_modulo
                    self._last_counter_t[role] = t_s
                    return False
                step = 0  # the sender restarted its counter: the periods since its last frame are unknown
            else:
                self.counters.count(FrameFault.COUNTER_JUMP)
                self.counters.missing_frames += step - 1
        self._resync[role] = None
        self._last_counter[role], self._last_counter_t[role] = counter, t_s
        self._step = step or None
        return True

    def _send_time(self, role: str, t_s: float) -> float:
        """The send time of a fast role's frame that arrived at ``t_s`` (see module notes, *de-jittering*)."""
        step, q = self._step, self._minq[role]
        if step is None or role in self.slow_roles:
            q.clear()
            return t_s
        k = self._seq[role] = self._seq[role] + step if q else 0
        offset = t_s - k * self.dt  # arrival less the sender's clock, up to a constant
        while q and q[-1][1] >= offset:  # the running minimum over the last DEJITTER_WINDOW_S (monotonic queue)
            q.pop()
        q.append((k, offset))
        while q[0][0] <= k - self._window_n:
            q.popleft()
        t = k * self.dt + q[0][1]
        if t_s - t > self.max_lag_s:  # far behind: the sender paused or its clock jumped; start again here
            q.clear()
            q.append((0, t_s))
            self._seq[role] = 0
            return t_s
        return t

    def _lost_by_time(self, role: str, t_s: float) -> float | None:
        """Most frames that can have been lost since the role's last counted frame (None: unknown rate)."""
        if role in self.slow_roles:
            return None
        return 1.5 * (t_s - self._last_counter_t[role]) / self.dt + 2.0

    def push(self, s: SignalSample) -> list[AssembledSample]:
        """Add one decoded value; returns the samples that became complete."""
        return self.push_value(s.role, s.value, s.t_s, s.counter)

    def push_value(self, role: str, value: float, t: float, counter: int | None = None) -> list[AssembledSample]:
        """:meth:`push` of the value of a :class:`SignalSample` given by its fields (no sample object to make: the
        replay of bench data takes this, three values per sample)."""
        if not -MAX_TIME_S <= t <= MAX_TIME_S:  # NaN too
            self.counters.count(FrameFault.BAD_TIME)
            return []
        clock = self._clock
        if clock is not None:
            if t > clock + self.max_jump_s:
                return self._hold_ahead(SignalSample(role, value, t, counter))
            if self._ahead:  # back in the old time base: the held frames were outliers
                self.counters.count(FrameFault.BAD_TIME, len(self._ahead))
                self._ahead.clear()
            if t < clock - self.timeout_s:
                self.counters.count(FrameFault.TIME_BACKWARDS)
                # a single stale frame is dropped; a stream that keeps arriving far in the past
                # (a log that restarted, a clock that was set back) re-anchors the grid
                self._back_run += 1
                if self._back_run < JUMP_CONFIRM:
                    return []
                self._reanchor(t)
        self._back_run = 0
        return self._accept(role, value, t, counter)

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

    def _accept(self, role: str, value: float, t_s: float, counter: int | None) -> list[AssembledSample]:
        hist = self._hist[role]
        if hist and t_s < hist[-1][0]:
            self.counters.count(FrameFault.TIME_BACKWARDS)
            return []
        if counter is None:  # no alive counter: stamped on arrival (as _check_counter and _send_time take it)
            self._step = None
            self._minq[role].clear()
            t = t_s
        else:
            if not self._check_counter(role, counter, t_s):
                return []
            t = self._send_time(role, t_s)
        hist.append((t, value))
        if self._start is None:
            self._start = t
        clock = self._clock
        if clock is None or t > clock:
            self._clock = t
        if t > self._newest:
            self._newest = t
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
            self._minq[r].clear()
        self._t0 = None
        self._newest = -float("inf")
        self._clock = None
        self._start = None
        self._back_run = 0
        self._timed_out = False
        self.timed_out_roles = ()
        self._pending_discontinuity = True

    def _update_timeout(self) -> bool:
        """The roles silent for longer than the timeout, after the first frame (``_drain`` calls this only while
        timed out, or where a role looks silent): True while there is one."""
        start = self._start
        newest, limit = self._newest, self.timeout_s
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

    def _phase_grid(self) -> None:
        """Once the fast roles' send clocks have a full window (de-jittering), move the grid so that their frames
        fall on its points, not half a period off, where late first frames set it (see module notes)."""
        fast = [r for r in self.fast_roles if self._last_counter[r] is not None]
        if not fast:  # no alive counters, no send clocks: the stamps are all there is
            self._phased = True
            return
        if any(not self._minq[r] or self._seq[r] < self._window_n for r in fast):
            return
        self._phased = True
        dt, t0 = self.dt, self._t0
        newest = [self._hist[r][-1][0] for r in fast if self._hist[r]]
        if not newest:
            return
        wrap = lambda x: (x + 0.5 * dt) % dt - 0.5 * dt  # noqa: E731 - onto (-dt/2, dt/2]
        ref = newest[0]
        rel = [wrap(t - ref) for t in newest]  # the roles of one send instant, around the first one
        if max(rel) - min(rel) >= 0.5 * dt:
            return  # not one send instant: leave the grid
        shift = wrap(ref + max(rel) - t0)  # the grid's points onto the last role's frames
        if abs(shift) > 0.1 * dt:
            self._t0 = t0 + shift

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
        hists = self._hists
        start = self._start
        if start is not None:
            if self._timed_out:
                if self._update_timeout():
                    return []
            else:  # the common case (no role silent), checked without a call or building anything
                newest, limit = self._newest, self.timeout_s
                for h in hists:
                    if newest - (h[-1][0] if h else start) > limit:
                        if self._update_timeout():
                            return []
                        break
        h0, h1, h2 = hists
        if not (h0 and h1 and h2):
            return []
        dt = self.dt
        if self._t0 is None:
            # start the grid at the newest of the roles' first values still held
            self._t0 = max(h[0][0] for h in self._fast_hists) if self._fast_hists else self._newest
            self._k = 0
            self._phased = False
        elif not self._phased:
            self._phase_grid()
        half = 0.5 * dt
        t0, fast = self._t0, self._fast_hists
        t = t0 + self._k * dt
        lim = t - half
        for h in fast:  # the next grid point is not complete (two of a sample's three values find it so)
            if h[-1][0] < lim:
                return []
        out: list[AssembledSample] = []
        value_at, counters = self._value_at, self.counters
        while True:
            limit = t + half
            v0, v1, v2 = value_at(h0, limit), value_at(h1, limit), value_at(h2, limit)
            if v0 is None or v1 is None or v2 is None:
                # a held role has no value old enough yet: skip this grid point
                self._k += 1
            else:
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
            t = t0 + self._k * dt
            lim = t - half
            for h in fast:
                if h[-1][0] < lim:
                    return out
