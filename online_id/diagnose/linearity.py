"""Does the driveline's apparent resonance move with the operating point? A backlash test on one plateau.

Notes
-----
A linear driveline has one resonance wherever the bench runs (the seed
paper's invariant poles). A shaft with backlash does not: the linear model
the service fits sees a stiffness that depends on how much of the time the
twist spends in the gap, and that depends on the mean load and the
excitation at the operating point -- 5-15 % in :math:`f_0` between
operating points on the simulated benches of ``online-id evaluate``. A
baseline learned at other operating points (pooled, or a cell of another
speed band or load) then cannot tell a point's own resonance from a change
of the driveline, and comparing with it raises a false alarm at the first
visit of a point whose resonance differs.

The test asks the data: the steady samples of one operating point go
through the bench diagnosis's data path (:mod:`online_id.diagnose.bench_data`),
both inertia equations are fitted with the linear twist, and a dead zone
of the twist, ``clip(twist - c, +-gap/2)``, is searched and added
(:func:`online_id.diagnose.bench_diagnosis.backlash_fit`). Its *gain* is
the share of the held-out one-step error variance it removes, its *t* the
batch-means t statistic of that improvement. Measured on 14 s of one
plateau (the first four plateaus of 26 random fault-free benches, seeds
1000-1025): -1.6 to 1.4 % on the 19 linear benches (with torque ripple,
sensor delays, disturbances and structural resonances), 3.4-31.5 % on the 7
with backlash, median 16 %; a plateau whose shaft torque seldom reverses
can read low. A plateau shows backlash when ``gain >= min_gain`` (3 %,
twice the largest linear reading) and ``t >= T_CRIT`` (2.86, the
diagnosis's). About 0.16 s of CPU for 14 s of data (median; 0.55 s at
most), ``scripts/backlash-survey``.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np

from online_id.diagnose.bench_data import RPM_PER_RAD_S, prepare
from online_id.diagnose.bench_diagnosis import T_CRIT, backlash_fit
from online_id.diagnose.bench_model import Spec

MIN_GAIN = 0.03  # the share of the one-step error a dead zone must remove (see the notes)
ORDERS = (6, 6)  # the bench diagnosis's default model orders


@dataclass(frozen=True)
class BacklashTest:
    """The outcome of :func:`backlash_test` on one operating point."""

    gain: float
    t_stat: float
    gap_rad: float
    speed_rpm: float
    duration_s: float

    def shows_backlash(self, min_gain: float = MIN_GAIN) -> bool:
        """Whether the dead zone removes at least ``min_gain`` of the error, significantly."""
        return bool(self.gain >= min_gain and self.t_stat >= T_CRIT)

    def as_dict(self) -> dict:
        return asdict(self)


def backlash_test(time_s: np.ndarray, torque_nm: np.ndarray, dyno_rad_s: np.ndarray, engine_rad_s: np.ndarray,
                  pulses_per_rev: float) -> BacklashTest:
    """The backlash test on samples of one steady operating point (see the module notes).

    Raises
    ------
    InputDataError
        If the samples hold no steady stretch of at least 8 s (or are not finite, or not in time order).
    """
    series = prepare(time_s, torque_nm, dyno_rad_s, engine_rad_s, source="backlash test",
                     pulses_per_rev=pulses_per_rev)
    term, _fit, gain, t_stat = backlash_fit(series, Spec(*ORDERS))
    t = np.asarray(time_s, dtype=float)
    return BacklashTest(float(gain), float(t_stat), float(term.gap),
                        float(np.median(np.asarray(engine_rad_s, dtype=float)) * RPM_PER_RAD_S),
                        float(t[-1] - t[0]))
