"""Send timed frames onto a bus at their own pace (real time, or a multiple of it).

Like python-can's ``can.player`` for a log, for frames made in memory (a
simulated bench): the demo, the tests of the service as its own process and
the live benchmark send with it.  Frames are sent when the wall clock since
the first frame reaches their stream time divided by ``speed``; the sender
sleeps only when it is more than ``min_sleep_s`` ahead, so it keeps the pace
in bursts of about a millisecond rather than drifting.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable, Sequence

from online_id.errors import BusError
from online_id.io.bus import CanBus

TimedFrame = tuple[float, int, bytes]
"""``(t_s, arbitration_id, data)``: a frame and its stream time."""


def send_paced(bus: CanBus, frames: Sequence[TimedFrame], speed: float = 1.0,
               stop: threading.Event | None = None, on_sent: Callable[[int, float], None] | None = None,
               keep_timestamps: bool = True, min_sleep_s: float = 0.001,
               slow_down: Callable[[], bool] | None = None, check_every: int = 300) -> int:
    """Send ``frames`` in order at ``speed`` times real time; returns how many were sent.

    ``on_sent(index, perf_counter_s)`` is called just before each send (for
    latency measurements); ``stop`` ends the sending early.  ``slow_down()``,
    asked every ``check_every`` frames, makes the pace real time while it is
    true (the demo's backpressure: its service's slow work fell behind a
    stream sent faster than real time); the frames keep flowing, so the
    receiver sees no silence.  A bus error is raised (:class:`BusError`,
    naming the frame it failed on).
    """
    if not frames:
        return 0
    if not speed > 0:
        raise ValueError(f"send_paced: expected speed > 0, but got {speed!r}")
    t_ref, wall_ref, pace = frames[0][0], time.perf_counter(), speed  # the pace holds from (t_ref, wall_ref)
    sent = 0
    for i, (t_s, ident, data) in enumerate(frames):
        if slow_down is not None and i % check_every == 0:
            want = 1.0 if slow_down() else speed
            if want != pace:  # the new pace from this frame on, without a burst or a pause
                t_ref, wall_ref, pace = t_s, max(time.perf_counter(), wall_ref + (t_s - t_ref) / pace), want
        delay = (t_s - t_ref) / pace - (time.perf_counter() - wall_ref)
        if delay > min_sleep_s:
            if stop is not None and stop.is_set():
                break
            time.sleep(delay)
        if on_sent is not None:
            on_sent(i, time.perf_counter())
        try:
            bus.send(ident, data, t_s=t_s if keep_timestamps else None)
        except BusError as err:
            raise BusError(f"{err} (frame {i} of {len(frames)}, t = {t_s:.3f} s)") from err
        sent += 1
    return sent
