"""Binary test signals: maximal-length sequences, the held PRBS torque, and the service's request.

Below both the simulator (:mod:`online_id.bench`) and the pipeline: the
bench adds the PRBS to its dyno torque, the service asks the bench for it
(:class:`Excitation`, published as ``OidExcitation``).

Notes
-----
A maximal-length sequence (MLS) of an ``n``-bit linear feedback shift
register has period :math:`2^n - 1` and holds :math:`2^{n-1}` ones and
:math:`2^{n-1} - 1` zeros; mapped to :math:`\\pm 1` it is balanced up to one
extra :math:`+1`.  Holding each bit for ``h`` samples gives a signal whose
period is :math:`h (2^n - 1)` samples, flat spectrum up to about
:math:`f_s / (2 h)`.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from online_id.errors import ConfigError
from online_id.records import ExcitationOut

if TYPE_CHECKING:
    from online_id.config import Settings

# Feedback taps (polynomial exponents) of primitive polynomials, Fibonacci form.
_TAPS: dict[int, tuple[int, ...]] = {
    2: (2, 1),
    3: (3, 2),
    4: (4, 3),
    5: (5, 3),
    6: (6, 5),
    7: (7, 6),
    8: (8, 6, 5, 4),
    9: (9, 5),
    10: (10, 7),
    11: (11, 9),
    12: (12, 11, 10, 4),
    13: (13, 12, 11, 8),
    14: (14, 13, 12, 2),
    15: (15, 14),
    16: (16, 15, 13, 4),
    17: (17, 14),
    18: (18, 11),
    19: (19, 18, 17, 14),
    20: (20, 17),
}

MIN_BITS = min(_TAPS)
MAX_BITS = max(_TAPS)


def mls(n_bits: int) -> np.ndarray:
    """Return one period of a maximal-length binary sequence.

    Parameters
    ----------
    n_bits
        Register length, between 2 and 20.

    Returns
    -------
    numpy.ndarray
        ``2**n_bits - 1`` values of ``+1.0`` or ``-1.0`` (register output bit
        1 maps to ``+1``), starting from the all-ones register state.

    Raises
    ------
    ConfigError
        If no feedback polynomial is tabulated for ``n_bits``.
    """
    if isinstance(n_bits, bool) or int(n_bits) != n_bits or n_bits not in _TAPS:
        raise ConfigError(
            f"Expected prbs n_bits between {MIN_BITS} and {MAX_BITS}, but got {n_bits!r}."
        )
    n = int(n_bits)
    shifts = [n - tap for tap in _TAPS[n]]
    length = (1 << n) - 1
    register = length  # all ones
    out = np.empty(length, dtype=np.int8)
    for k in range(length):
        out[k] = register & 1
        bit = 0
        for shift in shifts:
            bit ^= (register >> shift) & 1
        register = (register >> 1) | (bit << (n - 1))
    return 2.0 * out.astype(float) - 1.0


def prbs_hold_samples(fs_hz: float, period_s: float, n_bits: int) -> int:
    """Samples each bit is held so that a full sequence lasts about ``period_s``.

    Returns ``max(1, round(period_s * fs_hz / (2**n_bits - 1)))``.
    """
    return max(1, int(round(period_s * fs_hz / ((1 << int(n_bits)) - 1))))


def prbs_signal(
    n_samples: int,
    fs_hz: float,
    period_s: float,
    amplitude: float,
    n_bits: int = 9,
    seed: int | None = None,
) -> np.ndarray:
    """Return a held binary PRBS of ``n_samples`` values ``+-amplitude``.

    Parameters
    ----------
    n_samples
        Length of the returned signal.
    fs_hz
        Sampling rate.
    period_s
        Wanted period of the full sequence; the realised period is
        ``prbs_hold_samples(fs_hz, period_s, n_bits) * (2**n_bits - 1)`` samples.
    amplitude
        Level of the signal (same unit as the result).
    n_bits
        Register length of the underlying MLS.
    seed
        Selects the starting phase within the sequence; ``None`` starts at
        the all-ones state.

    Returns
    -------
    numpy.ndarray
        The signal, periodic with the realised period.
    """
    if n_samples < 0:
        raise ConfigError(f"Expected n_samples >= 0, but got {n_samples}.")
    if not fs_hz > 0 or not period_s > 0:
        raise ConfigError(
            f"Expected fs_hz > 0 and period_s > 0, but got {fs_hz!r} and {period_s!r}."
        )
    seq = mls(n_bits)
    if seed is not None:
        start = int(np.random.default_rng(seed).integers(0, seq.size))
        seq = np.roll(seq, -start)
    held = np.repeat(seq, prbs_hold_samples(fs_hz, period_s, n_bits))
    n_rep = -(-n_samples // held.size) if n_samples else 0
    return amplitude * np.tile(held, n_rep)[:n_samples]


class Excitation:
    """The paper's discrete binary test signal as a torque-offset request."""

    def __init__(self, settings: Settings) -> None:
        e = settings.excitation
        self.enabled = e.enabled
        self.amplitude = min(e.amplitude_nm, e.max_amplitude_nm)
        self.window = e.speed_window_rpm
        seq = mls(e.n_bits)
        hold = max(1, int(round(e.period_s * settings.input.sample_rate_hz / seq.size)))
        self.seq = seq
        self.hold = hold
        self.k = 0
        self.active = False
        self.level = 0.0

    def step(self, t_s: float, healthy: bool, speed_rpm: float) -> ExcitationOut | None:
        """Advance one input sample; returns a request when the output changes."""
        if not self.enabled:
            return None
        ok = healthy and self.window[0] <= speed_rpm <= self.window[1]
        if not ok:
            if self.active:
                self.active = False
                self.level = 0.0
                return ExcitationOut(t_s, 0.0, False)
            return None
        level = self.amplitude * float(self.seq[(self.k // self.hold) % self.seq.size])
        self.k += 1
        if not self.active or level != self.level:
            self.active = True
            self.level = level
            return ExcitationOut(t_s, level, True)
        return None

    def stop(self, t_s: float) -> ExcitationOut | None:
        """Stop at once (fault, timeout, shutdown)."""
        if self.active:
            self.active = False
            self.level = 0.0
            return ExcitationOut(t_s, 0.0, False)
        return None
