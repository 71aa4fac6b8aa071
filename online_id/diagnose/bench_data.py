"""Bench records for the diagnosis: a causal data path and the operating points.

Notes
-----
Anti-alias filtering keeps causality: every signal (torque, both speeds) is
filtered with the same linear-phase FIR ``h`` (``scipy.signal.firwin``,
``numtaps`` odd) by ``lfilter``, and the known group delay ``D = (numtaps -
1) / 2`` samples is removed from all of them alike (``x_f[n] = (h * x)[n +
D]``), then every ``q``-th sample is kept.  Since input and output pass the
same filter, the input-output relation is the plant's, and a sensor delay
or a feedback path still shows at the lag where it is.  Shaft angles are
integrated from the raw speeds and sampled at the same instants (they need
no filter).

Operating points are the steady plateaus of the dyno speed
(:func:`online_id.analysis.plateaus.find_plateaus`).  Each plateau is cut
into blocks of ``block_s``; the last ``holdout_s`` of each block is held out
(interleaved validation within the same operating point).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy.signal import firwin, lfilter

from online_id.analysis.plateaus import Plateau, find_plateaus
from online_id.diagnose.effects import shaft_angle
from online_id.errors import InputDataError
from online_id.estimation.preprocess import decimation_factor

RPM_PER_RAD_S = 30.0 / np.pi
DEFAULT_PULSES_PER_REV = 2.0  # compression pulses per revolution where none is declared: four-stroke four-cylinder
TARGET_FS_HZ = 500.0
CUTOFF = 0.8  # passband edge, fraction of the decimated Nyquist frequency
MIN_PLATEAU_S = 8.0
PLATEAU_TOL_RPM = 100.0
# the slope a plateau's 2 s-smoothed speed may have: the test torque of a soft bench moves the speed by tens
# of rpm within seconds (a slope of 30 rpm/s cut every plateau of such a bench into pieces under 8 s);
# the ramps between operating points leave a plateau by the 100 rpm tolerance
PLATEAU_MAX_RATE_RPM_S = 120.0


@dataclass(frozen=True)
class CausalPath:
    """The FIR anti-alias filter and decimation that were applied."""

    fs_in_hz: float
    q: int
    numtaps: int

    @property
    def fs_hz(self) -> float:
        return self.fs_in_hz / self.q

    @property
    def group_delay_samples(self) -> int:
        return (self.numtaps - 1) // 2

    @property
    def passband_hz(self) -> float:
        return CUTOFF * 0.5 * self.fs_hz

    def as_dict(self) -> dict:
        return {"fs_in_hz": self.fs_in_hz, "decimation": self.q, "fir_taps": self.numtaps,
                "group_delay_removed_samples": self.group_delay_samples,
                "fs_hz": self.fs_hz, "passband_hz": self.passband_hz}


def causal_path(fs_hz: float, target_hz: float = TARGET_FS_HZ) -> CausalPath:
    """Decimation factor and FIR length for ``fs_hz`` (no filter when ``q = 1``)."""
    # a rate measured from a recorder's clock (999.97 Hz for 1 kHz) decimates as the nominal rate does
    q = decimation_factor(fs_hz, min(target_hz, fs_hz))
    return CausalPath(float(fs_hz), q, 1 if q == 1 else 16 * q + 1)


def filter_decimate(x: np.ndarray, path: CausalPath) -> np.ndarray:
    """Linear-phase FIR, group delay removed, every ``q``-th sample kept."""
    x = np.asarray(x, dtype=float)
    if path.q == 1:
        return x.copy()
    h = firwin(path.numtaps, CUTOFF / path.q)
    d = path.group_delay_samples
    # pad with the last value so that the removed delay does not shorten the record
    y = lfilter(h, 1.0, np.concatenate((x, np.full(d, x[-1]))), zi=None)
    y[: path.numtaps] = y[path.numtaps]  # filter start-up held (plateaus start after it)
    return y[d:][:: path.q]


@dataclass
class BenchSeries:
    """Torque and both speeds on the diagnosis grid, with shaft angles and plateaus.

    ``torque`` [Nm], ``dyno``, ``engine`` [rad/s], ``theta_dyno``,
    ``theta_engine`` [rad]; ``valid`` marks samples past the filter start-up.
    """

    torque: np.ndarray
    dyno: np.ndarray
    engine: np.ndarray
    theta_dyno: np.ndarray
    theta_engine: np.ndarray
    path: CausalPath
    plateaus: list[Plateau]
    source: str = "<memory>"
    pulses_per_rev: float = 2.0
    meta: dict = field(default_factory=dict)
    demand: np.ndarray | None = None  # the recorded test-torque demand (PRBS) [Nm], if any
    full: "BenchSeries | None" = None  # the same record at its own rate (lines above the decimated band)

    @property
    def fs_hz(self) -> float:
        return self.path.fs_hz


def prepare(time_s: np.ndarray, torque_nm: np.ndarray, dyno_rad_s: np.ndarray,
            engine_rad_s: np.ndarray, *, source: str = "<memory>", pulses_per_rev: float = 2.0,
            target_hz: float = TARGET_FS_HZ, demand_nm: np.ndarray | None = None) -> BenchSeries:
    """Validate, filter causally, decimate and find the operating points of a bench record.

    ``demand_nm`` is the recorded test-torque demand (the PRBS), optional: an
    external excitation the speed controller does not react to, used as the
    instrument that tells a mode (excited by it) from a disturbance (not).
    """
    t = np.asarray(time_s, dtype=float)
    cols = {"dyno torque": torque_nm, "dyno speed": dyno_rad_s, "engine speed": engine_rad_s}
    if demand_nm is not None:
        cols["torque demand"] = demand_nm
    arrays = {}
    for name, x in cols.items():
        x = np.asarray(x, dtype=float).ravel()
        if x.size != t.size:
            raise InputDataError(f"{source}: {name} has {x.size} samples, time has {t.size}")
        bad = np.flatnonzero(~np.isfinite(x))
        if bad.size:
            raise InputDataError(f"{source}: {name} has {bad.size} non-finite values (first at "
                                 f"sample {bad[0]})")
        arrays[name] = x
    if t.size < 100:
        raise InputDataError(f"{source}: only {t.size} samples; a bench diagnosis needs seconds of data")
    dt = np.diff(t)
    if not np.all(dt > 0):
        raise InputDataError(f"{source}: time is not strictly increasing "
                             f"(first at sample {int(np.argmin(dt > 0)) + 1})")
    fs = 1.0 / float(np.median(dt))
    path = causal_path(fs, target_hz)
    dec = [filter_decimate(arrays[k], path) for k in cols]
    theta1 = shaft_angle(arrays["dyno speed"], fs)[:: path.q]
    theta2 = shaft_angle(arrays["engine speed"], fs)[:: path.q]
    n = dec[0].size
    t_dec = np.arange(n) / path.fs_hz
    rpm = dec[1] * RPM_PER_RAD_S
    plateaus = find_plateaus(t_dec, rpm, min_duration_s=MIN_PLATEAU_S, tol_rpm=PLATEAU_TOL_RPM,
                             smooth_s=2.0, max_rate_rpm_s=PLATEAU_MAX_RATE_RPM_S)
    skip = path.numtaps // path.q + 16  # filter start-up and the longest model lag
    min_len = int(MIN_PLATEAU_S * path.fs_hz)
    plateaus = [Plateau(max(p.start, skip), p.stop, p.speed_rpm, p.t_start_s, p.t_end_s)
                for p in plateaus if p.stop - max(p.start, skip) >= min_len]
    if not plateaus:
        raise InputDataError(f"{source}: no steady operating point of at least {MIN_PLATEAU_S:g} s "
                             f"(dyno speed within {PLATEAU_TOL_RPM:g} rpm); a bench diagnosis "
                             "needs plateaus")
    full = None
    if path.q > 1:  # lines up to the recording's own Nyquist frequency are looked for at its own rate
        q = path.q
        full = BenchSeries(arrays["dyno torque"], arrays["dyno speed"], arrays["engine speed"],
                           shaft_angle(arrays["dyno speed"], fs), shaft_angle(arrays["engine speed"], fs),
                           CausalPath(fs, 1, 1),
                           [Plateau(p.start * q, p.stop * q, p.speed_rpm, p.t_start_s, p.t_end_s) for p in plateaus],
                           source, pulses_per_rev,
                           demand=arrays["torque demand"] if demand_nm is not None else None)
    return BenchSeries(dec[0], dec[1], dec[2], theta1[:n], theta2[:n], path, plateaus,
                       source, pulses_per_rev, demand=dec[3] if demand_nm is not None else None, full=full)
