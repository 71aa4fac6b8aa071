"""Hostile input for soak tests: what an attacker on the bus and a broken bench would send.

:class:`HostileEvents` interleaves a stream of genuine input frames with one
hostile frame event every ``every_s`` seconds and one command scenario every
``command_every_s`` seconds, and counts in :attr:`HostileEvents.tried` what it
tried and in ``expect`` the frame faults each try must give.

Frame events (:data:`KINDS`): lying timestamps (NaN, +2 h, 1e300, +inf),
short frames, duplicates, frames of foreign IDs (11 and 29 bit), random
payloads on the service's own IDs, and values out of their DBC range.

Command scenarios (:data:`SCENARIOS`), by a legitimate operator and by an
attacker who has the DBC and listens on the bus (it reads the freshness value
the service publishes, :meth:`HostileEvents.observe`), but has not the key:

* ``legit``: the operator asks for the freshness value and sends an ACK or a
  RELEARN pair (with the key in authenticated mode); accepted, and captured
  by the attacker;
* ``forged``: a valid RELEARN pair of the attacker: right CRC, fresh freshness
  value, a MAC of another key; refused in authenticated mode, accepted in plain
  mode (what plain mode is);
* ``replayed``: a pair the operator sent earlier, sent again; refused;
* ``stale``: a forged pair with a freshness value the service already took;
  refused.

Clock steps (a PC clock set back or forward) are the caller's, at the times
of :func:`clock_steps`.
"""

from __future__ import annotations

import math
from collections import Counter

import numpy as np

from online_id.io.crc import crc8_j1850
from online_id.io.dbc import BenchCommand, InputDecoder, encode_command
from online_id.records import FrameFault

KINDS = ("nan", "future", "short", "duplicate", "foreign", "random_payload", "out_of_range")
SCENARIOS = ("legit", "forged", "replayed", "stale")
COMMAND_ID = 0x120  # OidCommand in the packaged DBC
FRESHNESS_ID = 0x306  # OidFreshness
INPUT_IDS = (0x101, 0x102, 0x103)
STEP_SIZES_S = (-7200.0, 3600.0, -600.0, 120.0)
OTHER_KEY = bytes.fromhex("5a" * 32)

Frame = tuple[float, int, bytes]


def new_expectation() -> dict[FrameFault, int]:
    """The fault counts the events can give (and that are predicted exactly), all zero."""
    return {f: 0 for f in (FrameFault.BAD_TIME, FrameFault.BAD_DLC, FrameFault.COMMAND_REFUSED, FrameFault.DUPLICATE,
                           FrameFault.UNKNOWN_ID, FrameFault.OUT_OF_RANGE)}


def clock_steps(duration_s: float, seed: int = 16, every_s: float = 1200.0) -> list[tuple[float, float]]:
    """``(t_s, step_s)``: at least two steps of the PC clock in any run, at random times, one in each
    ``every_s`` (or each half of a shorter run), sizes cycling through :data:`STEP_SIZES_S`."""
    rng = np.random.default_rng(seed)
    n = max(2, int(round(duration_s / every_s)))
    span = duration_s / n
    return [(span * (k + float(rng.uniform(0.25, 0.75))), STEP_SIZES_S[k % len(STEP_SIZES_S)]) for k in range(n)]


class HostileEvents:
    """Hostile frames after genuine ones (see module notes).

    Parameters
    ----------
    db
        The DBC (the service's).
    expect
        Fault counts the tries must give (:func:`new_expectation`), added to.
    key
        The service's key (authenticated mode), None in plain mode: the operator's, never the attacker's.
    """

    def __init__(self, db, expect: dict[FrameFault, int], seed: int = 16, every_s: float = 0.5,
                 key: bytes | None = None, command_every_s: float = 10.0) -> None:
        self.db = db
        self.expect = expect
        self.rng = np.random.default_rng(seed)
        self.every_s = every_s
        self.command_every_s = command_every_s
        self.key = key
        self.next_event: float | None = None
        self.next_command: float | None = None
        self.freshness: int | None = None  # what a listener on the bus last read in OidFreshness
        self.captured: list[list[tuple[int, bytes]]] = []  # the operator's pairs, as the attacker recorded them
        self.tried: Counter[str] = Counter()
        self.accepted = 0  # command frames the service must accept (legit; forged ones in plain mode)
        self.awaiting = 0  # first RELEARN frames it must hold for their confirmation
        self.forged_acted = 0  # forged pairs that acted (plain mode only)
        self.replayed_frames = 0  # captured frames sent again
        self.unpredicted = 0  # random payloads in range: the assembler's counter check tells (DUPLICATE or not)
        self._oracle = InputDecoder(db)  # a decoder of its own, to tell what a random payload must give
        self._scenario = 0
        self._foreign = [i for i in range(0x800) if i not in (*INPUT_IDS, COMMAND_ID)]

    def observe(self, frames: list[tuple[int, bytes]]) -> None:
        """The service's output frames, as a node on the bus sees them: the freshness value is public."""
        for ident, data in frames:
            if ident == FRESHNESS_ID and len(data) == 8:
                self.freshness = int.from_bytes(data[0:4], "little")

    def after(self, t_true: float, frame: Frame) -> list[Frame]:
        """The frames to send after genuine ``frame`` (true stream time ``t_true``): none, or an event."""
        if self.next_event is None:
            self.next_event = t_true + 2 * self.every_s  # the first event after two periods
            self.next_command = t_true + min(self.command_every_s, 5.0)
        out: list[Frame] = []
        if t_true >= self.next_event:
            self.next_event += self.every_s
            out += self._frame_event(frame)
        if t_true >= self.next_command:
            self.next_command += self.command_every_s
            out += self._command_scenario(frame[0])
        return out

    # -- frame events --------------------------------------------------------------------------------
    def _frame_event(self, frame: Frame) -> list[Frame]:
        ts, ident, data = frame
        kind = KINDS[int(self.rng.integers(len(KINDS)))]
        self.tried[kind] += 1
        expect, rng = self.expect, self.rng
        if kind == "nan":
            expect[FrameFault.BAD_TIME] += 1
            return [(math.nan, ident, data)]
        if kind == "future":
            expect[FrameFault.BAD_TIME] += 1
            return [(ts + float(rng.choice([7200.0, 1e300, math.inf])), ident, data)]
        if kind == "short":
            expect[FrameFault.BAD_DLC] += 1
            return [(ts, ident, data[:5])]
        if kind == "duplicate":
            expect[FrameFault.DUPLICATE] += 1
            return [(ts, ident, data)]
        if kind == "foreign":
            expect[FrameFault.UNKNOWN_ID] += 1
            if rng.random() < 0.5:
                other = int(rng.choice(self._foreign))
            else:
                other = int(rng.integers(0x800, 0x20000000))  # a 29-bit ID: never ours
                return [(ts, other, bytes(rng.integers(0, 256, 8, dtype=np.uint8)), True)]
            return [(ts, other, bytes(rng.integers(0, 256, int(rng.integers(0, 9)), dtype=np.uint8)))]
        if kind == "random_payload":
            target = int(rng.choice([*INPUT_IDS, COMMAND_ID]))
            payload = bytes(rng.integers(0, 256, 8, dtype=np.uint8))
            self._expect_of(target, payload, ts)
            return [(ts, target, payload)]
        # out_of_range: the frame's value beyond its DBC range (+-10000 rpm, +-3000 Nm), its counter kept
        expect[FrameFault.OUT_OF_RANGE] += 1
        raw = int(rng.choice([-1, 1])) * int(rng.integers(100_000_001, 2**31 - 1))
        return [(ts, ident, raw.to_bytes(4, "little", signed=True) + data[4:])]

    def _expect_of(self, ident: int, payload: bytes, ts: float) -> None:
        """What a random payload must give, by the rules the service decodes with."""
        if ident == COMMAND_ID:
            if crc8_j1850(payload[:7]) != payload[7]:
                self.expect[FrameFault.COMMAND_REFUSED] += 1
                self.tried["random_payload: bad CRC"] += 1
                return
        res = self._oracle.decode(ident, payload, ts)
        if isinstance(res, FrameFault):
            if res in self.expect:
                self.expect[res] += 1
            self.tried[f"random_payload: {res.name}"] += 1
        elif isinstance(res, list):
            # no input CRC mapped to tell: its alive counter does (a COUNTER_JUMP, and the sender's next frame
            # then repeats the counter the corrupt one took: a DUPLICATE), or rarely it is data
            self.tried["random_payload: in range, judged by its counter"] += 1
            self.unpredicted += 1
        elif res.command != BenchCommand.NONE:
            self.expect[FrameFault.COMMAND_REFUSED] += 1  # a CRC passed by chance: stale, or no MAC
            self.tried["random_payload: a command by chance"] += 1

    # -- command scenarios ---------------------------------------------------------------------------
    def _command(self, command: int, freshness: int, key: bytes | None) -> tuple[int, bytes]:
        return encode_command(self.db, "OidCommand", "Command", command, freshness, key=key)

    def _command_scenario(self, ts: float) -> list[Frame]:
        scenario = SCENARIOS[self._scenario % len(SCENARIOS)]
        self._scenario += 1
        request = (ts, *self._command(BenchCommand.NONE, 0, None))
        if self.freshness is None:  # the operator's first request: its answer comes with the service's frames
            self.tried["command: request (NONE)"] += 1
            return [request]
        if scenario == "replayed" and not self.captured:
            scenario = "legit"
        self.tried[f"command: {scenario}"] += 1
        last = self.freshness
        if scenario == "legit":
            if self.rng.random() < 0.5:
                frames = [self._command(BenchCommand.ACK_ALERT, last + 1, self.key)]
            else:
                frames = [self._command(BenchCommand.RELEARN_BASELINE, last + 1 + k, self.key) for k in range(2)]
                self.awaiting += 1
            self.accepted += 1
            self.captured.append(frames)
            self.freshness = last + len(frames)
            return [request] + [(ts, *f) for f in frames]
        if scenario == "forged":
            frames = [self._command(BenchCommand.RELEARN_BASELINE, last + 1 + k, OTHER_KEY) for k in range(2)]
            if self.key is None:  # plain mode: a valid pair from anyone acts
                self.accepted += 1
                self.awaiting += 1
                self.forged_acted += 1
                self.freshness = last + 2
            else:
                self.expect[FrameFault.COMMAND_REFUSED] += 2
            return [(ts, *f) for f in frames]
        if scenario == "replayed":
            frames = self.captured[int(self.rng.integers(len(self.captured)))]
            self.replayed_frames += len(frames)
        else:  # stale: a forged pair with values the service took already
            old = last - int(self.rng.integers(0, 200))
            frames = [self._command(BenchCommand.RELEARN_BASELINE, old - 1 + k, OTHER_KEY) for k in range(2)]
        self.expect[FrameFault.COMMAND_REFUSED] += len(frames)
        return [(ts, *f) for f in frames]

    def summary(self) -> dict[str, int]:
        """What was tried, by kind (sorted)."""
        return dict(sorted(self.tried.items()))


def hostile(frames, expect: dict[FrameFault, int], db, clock=lambda t: t, seed: int = 16, every_s: float = 0.5,
            key: bytes | None = None, command_every_s: float = 10.0, events: HostileEvents | None = None):
    """Yield ``(t_true, batch)``: each genuine frame stamped ``clock(t_true)``, then its hostile event if any.
    The caller hands the service's output frames to ``events.observe`` (pass ``events`` to keep it)."""
    events = events or HostileEvents(db, expect, seed, every_s, key, command_every_s)
    for t, ident, data in frames:
        frame = (clock(t), ident, data)
        yield t, [frame, *events.after(t, frame)]
