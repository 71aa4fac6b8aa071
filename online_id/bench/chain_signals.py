"""Signals that drive a chain run: the test PRBS, speed set-point plateaus, narrow lines and resonators.

Notes
-----
- PRBS: a maximal-length sequence (``scipy.signal.max_len_seq``) of +-1, one bit per ``bit_s``.
- A narrow line from a nearby machine: ``a (1 + m(t)) sin(2 pi f t + phi(t))`` with ``phi`` a random
  walk and ``m`` a slow amplitude wander, both low-passed below ``bandwidth_hz``: its spectrum is a
  line of that width.
- A heavily damped structural resonance driven by its own broadband source: white noise through
  ``w_n^2 / (s^2 + 2 zeta w_n s + w_n^2)`` (``scipy.signal.lsim`` of the exact discretisation),
  scaled to an RMS torque.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import signal

from online_id.errors import ConfigError


def prbs_bits(nbits: int, seed: int = 0) -> np.ndarray:
    """One period of a maximal-length sequence of ``2**nbits - 1`` bits as +-1, rotated by ``seed``."""
    seq, _state = signal.max_len_seq(nbits)
    seq = 2.0 * seq.astype(float) - 1.0
    return np.roll(seq, seed % seq.size)


@dataclass(frozen=True)
class Plateaus:
    """Speed plateaus of ``hold_s`` each at ``speeds`` [rad/s], joined by ramps of ``ramp_s``, after ``lead_s``
    at the first speed (the run-in that a recording leaves out)."""

    speeds: tuple[float, ...]
    hold_s: tuple[float, ...]
    ramp_s: float
    lead_s: float

    def __post_init__(self) -> None:
        if len(self.speeds) != len(self.hold_s) or not self.speeds or self.ramp_s <= 0 or self.lead_s < 0:
            raise ConfigError(f"plateaus: one hold per speed, ramp > 0, lead >= 0 (got {self})")

    def knots(self) -> tuple[tuple[float, float], ...]:
        """Set-point knots ``(t_s, rad/s)``."""
        out = [(0.0, self.speeds[0])]
        t = self.lead_s + self.hold_s[0]
        out.append((t, self.speeds[0]))
        for w, hold in zip(self.speeds[1:], self.hold_s[1:]):
            t += self.ramp_s
            out.append((t, w))
            t += hold
            out.append((t, w))
        return tuple(out)

    @property
    def duration_s(self) -> float:
        return self.knots()[-1][0]

    def windows(self) -> list[tuple[float, float, float]]:
        """``(start_s, end_s, speed)`` of every plateau, the lead included in the first."""
        k = self.knots()
        return [(k[2 * i][0] if i else self.lead_s, k[2 * i + 1][0], self.speeds[i]) for i in range(len(self.speeds))]


def narrow_line(duration_s: float, rate_hz: float, freq_hz: float, amplitude: float, bandwidth_hz: float,
                rng: np.random.Generator) -> np.ndarray:
    """A line at ``freq_hz`` of ``amplitude`` whose phase and amplitude wander within ``bandwidth_hz``."""
    n = int(np.ceil(duration_s * rate_hz)) + 2
    t = np.arange(n) / rate_hz
    b, a = signal.butter(1, bandwidth_hz / (rate_hz / 2))
    deviation = signal.lfilter(b, a, rng.standard_normal(n))
    deviation *= 0.5 * bandwidth_hz / max(float(np.std(deviation)), 1e-12)  # instantaneous frequency offset [Hz]
    phase = 2 * np.pi * np.cumsum(deviation) / rate_hz
    wander = signal.lfilter(b, a, rng.standard_normal(n))
    wander = 0.2 * wander / max(float(np.std(wander)), 1e-12)
    return amplitude * (1.0 + wander) * np.sin(2 * np.pi * freq_hz * t + phase + rng.uniform(0, 2 * np.pi))


def resonator_noise(duration_s: float, rate_hz: float, freq_hz: float, zeta: float, rms: float,
                    rng: np.random.Generator) -> np.ndarray:
    """White noise through a resonator at ``freq_hz`` with damping ``zeta``, scaled to ``rms``."""
    n = int(np.ceil(duration_s * rate_hz)) + 2
    w = 2 * np.pi * freq_hz
    sys = signal.cont2discrete(([w * w], [1.0, 2 * zeta * w, w * w]), 1.0 / rate_hz, method="zoh")
    y = signal.lfilter(np.ravel(sys[0]), sys[1], rng.standard_normal(n))
    settle = min(n - 1, int(5 / (zeta * w) * rate_hz))
    y[:settle] *= np.linspace(0.0, 1.0, settle) if settle else 1.0
    return rms * y / max(float(np.std(y[settle:])), 1e-12)
