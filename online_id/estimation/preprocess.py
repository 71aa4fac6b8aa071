"""Signal preprocessing before identification: units, sampling, decimation, offsets.

Notes
-----
**Why offsets vanish.**  The models of the paper are linearised about an
operating point: speed, torque and friction are deviations from their
stationary values, so the constant terms (mean dyno torque, the constant
friction :math:`b_0`, the working-point speed) drop out of the difference
equation.  Measured signals carry them, and a constant :math:`k` in
:math:`A y = B u + k + C e` otherwise biases every parameter.  Two remedies,
both supported: subtract the mean of each stationary segment from ``y`` and
``u`` (:func:`remove_offset`, or :func:`detrend_linear` when the operating
point drifts slowly), or estimate :math:`k` with the offset regressor
(``ArmaxOrders(offset=True)``).  For the integrating driveline (``A`` has a
root near 1) the constant in ``y`` is annihilated by ``A`` anyway; the
constant in ``u`` is what matters, and the offset regressor absorbs it
without assuming the segment is exactly balanced.
"""

from __future__ import annotations

import numpy as np
from scipy.signal import firwin, resample_poly

from online_id.errors import ConfigError, InputDataError

_RPM_TO_RAD_S = 2.0 * np.pi / 60.0


def rpm_to_rad_s(speed_rpm: np.ndarray | float) -> np.ndarray | float:
    """Convert a speed from rpm to rad/s."""
    return np.multiply(speed_rpm, _RPM_TO_RAD_S)


def rad_s_to_rpm(speed_rad_s: np.ndarray | float) -> np.ndarray | float:
    """Convert a speed from rad/s to rpm."""
    return np.divide(speed_rad_s, _RPM_TO_RAD_S)


def angle_to_speed(angle: np.ndarray, time_s: np.ndarray, unit: str = "deg",
                   period: float | None = None) -> np.ndarray:
    """Angular speed in rad/s from a cumulative angle signal.

    Parameters
    ----------
    angle
        Cumulative angle (not wrapped), in ``unit``.
    time_s
        Sample times, strictly increasing; need not be uniform.
    unit
        ``"deg"`` or ``"rad"``.
    period
        If the angle wraps (e.g. 360 for an encoder counting 0..360 deg),
        its period in ``unit``; the angle is unwrapped first.

    Returns
    -------
    np.ndarray
        Speed in rad/s, same length as ``angle``.

    Notes
    -----
    Second-order central differences for non-uniform spacing
    (``numpy.gradient``), one-sided at the two ends.
    """
    angle = np.asarray(angle, dtype=float)
    time_s = np.asarray(time_s, dtype=float)
    if unit not in ("deg", "rad"):
        raise ConfigError(f'angle unit must be "deg" or "rad", got {unit!r}')
    if angle.ndim != 1 or angle.shape != time_s.shape:
        raise InputDataError(f"angle and time_s must be 1-D of equal length, got shapes "
                             f"{angle.shape} and {time_s.shape}")
    if angle.size < 2:
        raise InputDataError(f"angle_to_speed needs at least 2 samples, got {angle.size}")
    _check_finite(angle, "angle")
    _check_increasing(time_s)
    if period is not None:
        angle = np.unwrap(angle, period=period)
    if unit == "deg":
        angle = np.deg2rad(angle)
    return np.gradient(angle, time_s)


def check_uniform(time_s: np.ndarray, max_jitter: float = 0.01) -> float:
    """Check that sampling is uniform and return the sample interval in s.

    Parameters
    ----------
    time_s
        Sample times.
    max_jitter
        Largest allowed deviation of an interval from the mean interval, as a
        fraction of it (default 1 %).

    Returns
    -------
    float
        Mean sample interval ``(t[-1] - t[0]) / (n - 1)``.

    Raises
    ------
    InputDataError
        Fewer than 2 samples, non-finite times, times not strictly increasing
        (names the first offending index), or jitter above ``max_jitter``
        (names the worst index and the jitter in percent).
    """
    time_s = np.asarray(time_s, dtype=float)
    if time_s.ndim != 1 or time_s.size < 2:
        raise InputDataError(f"time_s must be 1-D with at least 2 samples, got shape {time_s.shape}")
    _check_finite(time_s, "time_s")
    dt = np.diff(time_s)
    _check_increasing(time_s, dt)
    mean_dt = (time_s[-1] - time_s[0]) / (time_s.size - 1)
    # the largest |dt - mean| is at the smallest or the largest interval (no temporaries: long records)
    lo, hi = int(np.argmin(dt)), int(np.argmax(dt))
    d_lo, d_hi = abs(dt[lo] - mean_dt), abs(dt[hi] - mean_dt)
    worst = lo if d_lo > d_hi else hi if d_hi > d_lo else min(lo, hi)
    deviation = abs(dt[worst] - mean_dt) / mean_dt
    if deviation > max_jitter:
        raise InputDataError(
            f"sampling is not uniform: interval before index {worst + 1} is {dt[worst]:.6g} s "
            f"against a mean of {mean_dt:.6g} s, a jitter of {100 * deviation:.3g} % "
            f"(allowed {100 * max_jitter:.3g} %)")
    return float(mean_dt)


RATE_TOL = 1e-3
"""Relative distance of ``fs / target`` from an integer within which :func:`decimation_factor` rounds."""


def decimation_factor(fs_hz: float, target_fs_hz: float) -> int:
    """Largest integer factor ``q`` with ``fs_hz / q >= target_fs_hz``; ``fs / target`` is rounded instead
    when within :data:`RATE_TOL` of an integer.

    A rate measured from jittered or rounded timestamps (999.97 Hz for 1 kHz) would otherwise floor to one
    factor less (4 instead of 5 for 200 Hz; 1, no decimation at all, for 500 Hz).
    """
    if not (np.isfinite(fs_hz) and np.isfinite(target_fs_hz)) or fs_hz <= 0 or target_fs_hz <= 0:
        raise ConfigError(f"sample rates must be positive, got fs_hz={fs_hz}, "
                          f"target_fs_hz={target_fs_hz}")
    if target_fs_hz > fs_hz * (1 + RATE_TOL):
        raise ConfigError(f"target sample rate {target_fs_hz} Hz is above the data rate "
                          f"{fs_hz} Hz; decimation cannot raise it")
    r = fs_hz / target_fs_hz
    k = round(r)
    return max(1, int(k) if abs(r - k) <= RATE_TOL * r else int(np.floor(r)))


def decimate(x: np.ndarray, factor: int, axis: int = -1) -> np.ndarray:
    """Anti-alias filter and downsample by an integer factor, without phase shift.

    Parameters
    ----------
    x
        Signal(s).
    factor
        Integer decimation factor; 1 returns a copy.
    axis
        Time axis.

    Returns
    -------
    np.ndarray
        ``ceil(n / factor)`` samples along ``axis``: ``x[::factor]`` of the
        filtered signal.

    Notes
    -----
    The filter of ``scipy.signal.decimate(ftype="fir", zero_phase=True)``:
    a Hamming-window FIR of ``20 q + 1`` taps with cutoff at the new Nyquist
    frequency, applied by polyphase filtering (``resample_poly``), which is
    zero phase.  Unlike ``decimate`` the signal is extended with a line at
    both ends instead of zeros, so a large mean (a speed of 300 rad/s) gives
    no edge transient.  Factors above 10 run as a cascade of stages of at most
    10 (a prime factor above 10 is one stage).  The pass band is flat (within
    0.03 dB) to 0.7 of the new Nyquist frequency and the stop band (> 55 dB)
    starts at 1.3 times it; content in between is only partly removed.
    """
    x = np.asarray(x, dtype=float)
    if isinstance(factor, bool) or not isinstance(factor, (int, np.integer)) or factor < 1:
        raise ConfigError(f"decimation factor must be an integer >= 1, got {factor!r}")
    if factor == 1:
        return x.copy()
    if x.shape[axis] < 2:
        raise InputDataError(f"cannot decimate a signal of {x.shape[axis]} samples")
    _check_finite(x, "signal to decimate")
    out = x
    for q in _stages(int(factor)):
        taps = firwin(20 * q + 1, 1.0 / q, window="hamming")
        out = resample_poly(out, 1, q, axis=axis, window=taps, padtype="line")
    return out


def remove_offset(x: np.ndarray, axis: int = -1) -> tuple[np.ndarray, np.ndarray | float]:
    """Subtract the mean; return ``(x - mean, mean)`` (see module notes)."""
    x = np.asarray(x, dtype=float)
    mean = np.mean(x, axis=axis, keepdims=True)
    centred = x - mean
    mean = np.squeeze(mean, axis=axis)
    return centred, (float(mean) if mean.ndim == 0 else mean)


def detrend_linear(x: np.ndarray, time_s: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Subtract the least-squares straight line; return ``(x - trend, trend)``.

    Parameters
    ----------
    x
        1-D signal.
    time_s
        Sample times (default: the sample index), for non-uniform sampling.

    Returns
    -------
    tuple[np.ndarray, np.ndarray]
        Detrended signal and the removed line, so ``x == detrended + trend``.
    """
    x = np.asarray(x, dtype=float)
    if x.ndim != 1 or x.size < 2:
        raise InputDataError(f"detrend_linear needs a 1-D signal of at least 2 samples, "
                             f"got shape {x.shape}")
    t = np.arange(x.size, dtype=float) if time_s is None else np.asarray(time_s, dtype=float)
    if t.shape != x.shape:
        raise InputDataError(f"time_s has shape {t.shape} but x has {x.shape}")
    tc = t - t.mean()
    denom = float(tc @ tc)
    slope = float(tc @ (x - x.mean())) / denom if denom > 0 else 0.0
    trend = x.mean() + slope * tc
    return x - trend, trend


def _stages(factor: int) -> list[int]:
    """Split ``factor`` into integer stages of at most 10 (largest first)."""
    primes: list[int] = []
    n, p = factor, 2
    while p * p <= n:
        while n % p == 0:
            primes.append(p)
            n //= p
        p += 1
    if n > 1:
        primes.append(n)
    stages: list[int] = []
    for p in sorted(primes, reverse=True):
        for i, s in enumerate(stages):
            if s * p <= 10:
                stages[i] = s * p
                break
        else:
            stages.append(p)
    return sorted(stages, reverse=True)


def _check_finite(x: np.ndarray, name: str) -> None:
    bad = np.flatnonzero(~np.isfinite(np.ravel(x)))
    if bad.size:
        raise InputDataError(f"{name} has {bad.size} non-finite values (first at flat index {bad[0]})")


def _check_increasing(time_s: np.ndarray, steps: np.ndarray | None = None) -> None:
    """Raise if ``time_s`` does not strictly increase (``steps``: its ``np.diff``, if at hand)."""
    bad = np.flatnonzero((np.diff(time_s) if steps is None else steps) <= 0)
    if bad.size:
        i = int(bad[0]) + 1
        raise InputDataError(
            f"time_s is not strictly increasing at index {i}: {time_s[i]!r} s follows "
            f"{time_s[i - 1]!r} s ({bad.size} such samples)")
