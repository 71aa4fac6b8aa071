"""Sending timed frames at a pace: real time, a multiple of it, and the demo's backpressure."""

import threading
import time

import pytest

from online_id.io.player import send_paced


class _Recorder:
    """A bus that notes when each frame was sent."""

    def __init__(self) -> None:
        self.sent: list[tuple[float, float]] = []  # (stream time, perf_counter)

    def send(self, ident: int, data: bytes, t_s: float | None = None) -> None:
        self.sent.append((t_s, time.perf_counter()))


def _frames(seconds: float, rate_hz: float = 1000.0) -> list:
    return [(k / rate_hz, 0x101, b"\0" * 8) for k in range(int(seconds * rate_hz))]


def test_the_pace_is_a_multiple_of_real_time() -> None:
    bus = _Recorder()
    assert send_paced(bus, _frames(1.0), speed=4.0) == 1000
    span = bus.sent[-1][1] - bus.sent[0][1]
    assert 0.999 / 4.0 - 0.01 <= span < 0.999  # never early (a stalled machine may make it late, not 4x late)
    with pytest.raises(ValueError):
        send_paced(bus, _frames(0.01), speed=0.0)


def test_slow_down_sends_at_real_time_without_a_pause_and_resumes_the_speed() -> None:
    """While ``slow_down()`` holds, frames keep coming at real time (no silence for the receiver to time out
    on), and the given speed resumes afterwards without a burst."""
    bus = _Recorder()
    frames = _frames(2.0)  # 2 s of stream at 20x: 0.1 s; with 0.5 s of it at real time, about 0.575 s
    slow = threading.Event()

    def slow_down() -> bool:
        n = len(bus.sent)
        if n >= 500:
            slow.set()
        return 500 <= n < 1000

    t0 = time.perf_counter()
    assert send_paced(bus, frames, speed=20.0, slow_down=slow_down, check_every=100) == 2000
    elapsed = time.perf_counter() - t0
    assert slow.is_set() and elapsed >= 0.57
    slow_part = bus.sent[1000][1] - bus.sent[500][1]  # at real time: 0.5 s, never less (20x: 0.025 s)
    assert 0.49 <= slow_part
    # frames flowed all through it: in each tenth of it a tenth of its frames, as a bus would carry them
    t_slow = [t for _s, t in bus.sent[500:1000]]
    assert all(t_slow[k + 50] - t_slow[k] >= 0.045 for k in range(0, 450, 50))
    fast_part = bus.sent[1999][1] - bus.sent[1000][1]  # back to 20x: 0.05 s (real time would be 1 s)
    assert fast_part < 0.5
