"""A simulated test centre's archive: several benches, months of recordings, slow wear and a sudden fault.

:func:`plan_archive` draws (no I/O) what :mod:`online_id.archive.simulated`
simulates and writes as MDF 4 files:

* **benches** ``B01``, ``B02``, ...: each a random two-mass driveline
  (resonance 18-32 Hz, damping ratio 3-7 %, a 4- or 6-cylinder engine,
  measurement noise as in ``online-id evaluate``) and three operating
  points of its own whose engine orders stay at least 25 % away from the
  resonance;
* **conditions**: ``wear`` on two benches (the second and fourth): from a
  random day in the 2nd to 4th month on, the shaft stiffness falls by 3-6 %
  per month and its damping rises by the same share, linearly; a sudden
  ``fault`` on one bench (the third): from a random day in the 3rd to 5th
  month on, the stiffness is 15 % lower; the other benches stay
  ``healthy``.  Every recording also carries a day-to-day stiffness
  scatter of 0.3 % (standard deviation; a coupling's stiffness moves with
  its temperature), so that a healthy bench is not a constant;
* **recordings**: spread evenly over the benches and the period, on working
  days between 06:00 and 18:00 UTC; each visits the bench's three
  operating points for ``dwell_s`` seconds (with a few rpm of jitter).

The truth of every bench and recording is kept (:meth:`ArchivePlan.truth`)
to score ``online-id trend`` against.
"""

from __future__ import annotations

import dataclasses
import datetime as dt
import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from online_id.bench.evaluate import random_driveline
from online_id.bench.scenario import BenchScenario, Noise, OperatingPoint, PrbsSettings

HEALTHY, WEAR, FAULT = "healthy", "wear", "fault"
DAY_S = 86400.0
SPEEDS_RPM = tuple(range(1000, 3001, 100))
STIFFNESS_SCATTER = 0.003  # relative day-to-day scatter of the stiffness
FAULT_STIFFNESS = 0.85


@dataclass(frozen=True)
class BenchPlan:
    """One bench of the archive: its plant, operating points and condition."""

    name: str
    J1: float
    J2: float
    c_s: float
    d_s: float
    n_cyl: int
    speeds_rpm: tuple[float, ...]
    condition: str  # healthy, wear, fault
    onset: dt.datetime | None = None  # wear begins / the fault happens
    wear_per_month: float = 0.0  # relative stiffness loss per 30 days (wear)
    noise: Noise = Noise()
    prbs_nm: float = 40.0

    @property
    def f0_hz(self) -> float:
        """The healthy resonance of the linear two-mass model."""
        return math.sqrt(self.c_s * (self.J1 + self.J2) / (self.J1 * self.J2)) / (2.0 * math.pi)

    def factors(self, when: dt.datetime) -> tuple[float, float]:
        """Stiffness and damping factors of the condition at ``when`` (without the day-to-day scatter)."""
        if self.onset is None or when < self.onset:
            return 1.0, 1.0
        if self.condition == FAULT:
            return FAULT_STIFFNESS, 1.0
        loss = self.wear_per_month * (when - self.onset).total_seconds() / (30.0 * DAY_S)
        return 1.0 - loss, 1.0 + loss


@dataclass(frozen=True)
class RecordingPlan:
    """One recording: its bench, start, scenario and file name."""

    bench: str
    start: dt.datetime
    scenario: BenchScenario
    name: str  # relative path of the file in the archive
    run_id: str
    stiffness_factor: float  # condition times scatter

    def truth(self) -> dict[str, Any]:
        s = self.scenario
        f0 = math.sqrt(s.c_s * (s.J1 + s.J2) / (s.J1 * s.J2)) / (2.0 * math.pi)
        return {"file": self.name, "bench": self.bench, "start": self.start.isoformat(), "f0_hz": f0,
                "stiffness_factor": self.stiffness_factor, "c_s": s.c_s, "d_s": s.d_s}


@dataclass(frozen=True)
class ArchivePlan:
    """Benches and recordings (see module notes)."""

    benches: tuple[BenchPlan, ...]
    recordings: tuple[RecordingPlan, ...]
    start: dt.datetime
    days: float

    def truth(self) -> dict[str, Any]:
        """JSON-able: every bench's condition and onset, every recording's true resonance."""
        return {
            "start": self.start.isoformat(), "days": self.days,
            "benches": [{"bench": b.name, "condition": b.condition, "f0_hz": b.f0_hz, "c_s": b.c_s, "d_s": b.d_s,
                         "J1": b.J1, "J2": b.J2, "n_cyl": b.n_cyl, "speeds_rpm": list(b.speeds_rpm),
                         "onset": b.onset.isoformat() if b.onset else None,
                         "wear_per_month_pct": 100.0 * b.wear_per_month,
                         "fault_stiffness_factor": FAULT_STIFFNESS if b.condition == FAULT else None}
                        for b in self.benches],
            "recordings": [r.truth() for r in self.recordings],
        }


def _speeds(rng: np.random.Generator, f0: float, n_cyl: int) -> tuple[float, ...]:
    """Three speeds at least 300 rpm apart whose compression order stays 25 % away from ``f0``."""
    ok = [s for s in SPEEDS_RPM if abs(n_cyl / 2.0 * s / 60.0 - f0) > 0.25 * f0]
    for _ in range(200):
        pick = sorted(rng.choice(ok, size=3, replace=False))
        if min(np.diff(pick)) >= 300:
            return tuple(float(x) for x in pick)
    return tuple(float(x) for x in ok[:: max(1, len(ok) // 3)][:3])


def conditions(n_benches: int) -> list[str]:
    """The condition of each bench: wear on the 2nd and 4th, the fault on the 3rd, the rest healthy."""
    out = [HEALTHY] * n_benches
    for i, c in ((1, WEAR), (2, FAULT), (3, WEAR)):
        if i < n_benches:
            out[i] = c
    return out


def plan_archive(n_benches: int = 6, months: float = 6.0, recordings: int = 300, *, seed: int = 1,
                 start: dt.datetime = dt.datetime(2025, 1, 6, tzinfo=dt.timezone.utc),
                 dwell_s: float = 30.0, fs_hz: float = 1000.0) -> ArchivePlan:
    """The archive's benches and recordings (see module notes)."""
    if n_benches < 1 or recordings < n_benches or months <= 0 or dwell_s <= 0:
        raise ValueError(f"plan_archive: expected benches >= 1, recordings >= benches, months > 0, dwell > 0; "
                         f"got {n_benches}, {recordings}, {months}, {dwell_s}")
    rng = np.random.default_rng([seed, 41])
    days = 30.4 * months
    benches = []
    for i, cond in enumerate(conditions(n_benches)):
        d, f0 = random_driveline(rng, (18.0, 32.0), (0.03, 0.07))
        J1, J2, c_s, d_s, n_cyl, noise = d["J1"], d["J2"], d["c_s"], d["d_s"], d["n_cyl"], d["noise"]
        onset, rate = None, 0.0
        if cond == WEAR:
            onset = start + dt.timedelta(days=float(rng.uniform(1.0, 3.0) / 6.0 * days))
            rate = float(rng.uniform(0.03, 0.06))
        elif cond == FAULT:
            onset = start + dt.timedelta(days=float(rng.uniform(2.0, 4.0) / 6.0 * days))
        benches.append(BenchPlan(f"B{i + 1:02d}", J1, J2, c_s, d_s, n_cyl, _speeds(rng, f0, n_cyl), cond, onset,
                                 rate, noise, float(rng.uniform(30.0, 50.0))))
    recs = []
    per_bench = np.full(n_benches, recordings // n_benches)
    per_bench[: recordings % n_benches] += 1
    for b, n in zip(benches, per_bench):
        brng = np.random.default_rng([seed, 42, int(b.name[1:])])
        slots = (np.arange(n) + brng.uniform(0.1, 0.9, n)) * days / n
        for k, day in enumerate(slots):
            when = start + dt.timedelta(days=float(np.floor(day)))
            while when.weekday() >= 5:  # a working day
                when += dt.timedelta(days=1)
            when += dt.timedelta(seconds=float(brng.uniform(6.0, 18.0) * 3600.0))
            when = when.replace(microsecond=0)
            k_c, k_d = b.factors(when)
            k_c *= 1.0 + STIFFNESS_SCATTER * float(brng.standard_normal())
            points = tuple(OperatingPoint(s + float(brng.uniform(-10.0, 10.0)), dwell_s)
                           for s in brng.permutation(b.speeds_rpm))
            sc = dataclasses.replace(
                BenchScenario(), fs_hz=fs_hz, J1=b.J1, J2=b.J2, c_s=b.c_s * k_c, d_s=b.d_s * k_d, n_cyl=b.n_cyl,
                operating_points=points, noise=b.noise, prbs=PrbsSettings(amplitude_nm=b.prbs_nm, period_s=1.0),
                seed=int(brng.integers(0, 2**31)))
            stamp = when.strftime("%Y%m%dT%H%M%S")
            recs.append(RecordingPlan(b.name, when, sc, f"{b.name}/{when:%Y-%m}/{b.name}_{stamp}.mf4",
                                      f"{b.name}-{k + 1:04d}", k_c))
    recs.sort(key=lambda r: (r.start, r.bench))
    return ArchivePlan(tuple(benches), tuple(recs), start, days)
