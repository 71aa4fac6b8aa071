"""What sensors and loggers make of a chain run: sampled angles, counter speeds, torques, noise, quantisation.

Notes
-----
The record holds angle and speed of every element at the store rate; an angle at any instant is the
cubic Hermite interpolant through both (the store grid is uniform), exact to about
``(w h)^4 / 384`` of a line at ``w`` for the store interval ``h``.  A speed sensor on a toothed wheel
or an encoder reports the mean speed over its sample interval ``T``, late by its delay ``tau``::

    n(t) = (theta(t - tau) - theta(t - tau - T)) / T

which is ``omega`` through ``sinc(f T)`` and a delay of ``tau + T / 2``; both speeds of a bench see the
same ``T / 2``, only ``tau`` differs between them.
"""

from __future__ import annotations

import numpy as np
from online_id.bench.chain_run import ChainRecord

RPM_PER_RAD_S = 30.0 / np.pi


class Sampler:
    """Samples of a :class:`ChainRecord` at arbitrary instants (see module notes)."""

    def __init__(self, record: ChainRecord) -> None:
        self.record = record
        self.step_s = float(record.t[1] - record.t[0])

    def angle(self, element: int, times: np.ndarray, delay_s: float = 0.0) -> np.ndarray:
        """Angle [rad] of ``element`` at ``times - delay_s``."""
        rec, h = self.record, self.step_s
        pos = (np.asarray(times, dtype=float) - delay_s - rec.t[0]) / h
        i = np.clip(np.floor(pos).astype(np.int64), 0, rec.t.size - 2)
        s = pos - i
        th, om = rec.theta[:, element], rec.omega[:, element]
        s2, s3 = s * s, s * s * s
        return ((2 * s3 - 3 * s2 + 1) * th[i] + (s3 - 2 * s2 + s) * h * om[i]
                + (-2 * s3 + 3 * s2) * th[i + 1] + (s3 - s2) * h * om[i + 1])

    def counter_speed(self, element: int, times: np.ndarray, interval_s: float, delay_s: float = 0.0) -> np.ndarray:
        """Mean speed [rad/s] of ``element`` over the ``interval_s`` before each of ``times - delay_s``."""
        times = np.asarray(times, dtype=float)
        return (self.angle(element, times, delay_s) - self.angle(element, times, delay_s + interval_s)) / interval_s

    def series(self, values: np.ndarray, times: np.ndarray, delay_s: float = 0.0) -> np.ndarray:
        """A stored signal (store rate, e.g. a sensed torque) at ``times - delay_s`` (linear interpolation)."""
        return np.interp(np.asarray(times, dtype=float) - delay_s, self.record.t, values)


def quantise(x: np.ndarray, step: float) -> np.ndarray:
    """``x`` rounded to multiples of ``step`` (0: unchanged)."""
    return np.round(np.asarray(x) / step) * step if step > 0 else np.asarray(x, dtype=float)


def jittered_times(start_s: float, end_s: float, rate_hz: float, jitter_s: float,
                   rng: np.random.Generator) -> np.ndarray:
    """A logger's sample instants from ``start_s`` to ``end_s`` at ``rate_hz``, each off by white jitter of
    standard deviation ``jitter_s`` (kept increasing)."""
    n = int(np.floor((end_s - start_s) * rate_hz)) + 1
    t = start_s + np.arange(n) / rate_hz
    if jitter_s > 0:
        t = t + np.clip(rng.standard_normal(n) * jitter_s, -0.4 / rate_hz, 0.4 / rate_hz)
    return t
