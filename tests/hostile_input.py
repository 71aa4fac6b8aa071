"""Hostile input for soak tests: lying timestamps, garbage, short frames, duplicates, forged commands.

:func:`hostile_events` interleaves a stream of genuine input frames with
one hostile event every ``every_s`` seconds and counts, in ``expect``, the
frame faults each event must give.  The clock steps themselves (a PC clock
set back or forward) are the caller's: it passes the timestamps it wants.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Iterator

import numpy as np

from online_id.io.dbc import BenchCommand, encode_command
from online_id.records import FrameFault

KINDS = ("nan", "future", "short", "duplicate", "forged_command", "repeat_command")
COMMAND_ID = 0x120  # OidCommand in the packaged DBC

Frame = tuple[float, int, bytes]


def new_expectation() -> dict[FrameFault, int]:
    """The fault counts the events can give, all zero."""
    return {FrameFault.BAD_TIME: 0, FrameFault.BAD_DLC: 0, FrameFault.COMMAND_REFUSED: 0, FrameFault.DUPLICATE: 0}


class HostileEvents:
    """One hostile event after a genuine frame every ``every_s`` seconds (see module notes)."""

    def __init__(self, db, expect: dict[FrameFault, int], seed: int = 16, every_s: float = 0.5) -> None:
        self.db = db
        self.expect = expect
        self.rng = np.random.default_rng(seed)
        self.every_s = every_s
        self.next_event: float | None = None
        self.cmd_counter = 0

    def after(self, t_true: float, frame: Frame) -> list[Frame]:
        """The frames to send after genuine ``frame`` (true stream time ``t_true``): none, or one event."""
        if self.next_event is None:
            self.next_event = t_true + 2 * self.every_s  # the first event after two periods
        if t_true < self.next_event:
            return []
        self.next_event += self.every_s
        ts, ident, data = frame
        kind = KINDS[int(self.rng.integers(len(KINDS)))]
        expect = self.expect
        if kind == "nan":
            expect[FrameFault.BAD_TIME] += 1
            return [(math.nan, ident, data)]
        if kind == "future":
            expect[FrameFault.BAD_TIME] += 1
            return [(ts + float(self.rng.choice([7200.0, 1e300, math.inf])), ident, data)]
        if kind == "short":
            expect[FrameFault.BAD_DLC] += 1
            return [(ts, ident, data[:5])]
        if kind == "duplicate":
            expect[FrameFault.DUPLICATE] += 1
            return [(ts, ident, data)]
        expect[FrameFault.COMMAND_REFUSED] += 1
        if kind == "forged_command":
            return [(ts, COMMAND_ID, bytes([2, 9, 0, 0, 0, 0, 0, 0]))]  # no CRC
        self.cmd_counter += 20
        cmd = encode_command(self.db, "OidCommand", "Command", BenchCommand.ACK_ALERT, self.cmd_counter)
        return [(ts, *cmd), (ts, *cmd)]  # the second is a repeat


def hostile(frames: Iterable[Frame], expect: dict[FrameFault, int], db, clock=lambda t: t, seed: int = 16,
            every_s: float = 0.5) -> Iterator[tuple[float, list[Frame]]]:
    """Yield ``(t_true, batch)``: each genuine frame stamped ``clock(t_true)``, then its hostile event if any."""
    events = HostileEvents(db, expect, seed, every_s)
    for t, ident, data in frames:
        frame = (clock(t), ident, data)
        yield t, [frame, *events.after(t, frame)]
