"""The engaged flank's resonance and damping across visits: a change test that does not move with the load.

Notes
-----
On a shaft with backlash the service's apparent resonance (the ARMAX fit's)
moves with the operating point: the linear model sees a stiffness that
depends on how much of the time the twist spends in the gap, 5-15 % between
the points of one bench. A learned cell serves its own point only, and the
learned cells of smaller and larger loads bound a point between them
(:meth:`~online_id.monitoring.baseline.Baseline.bracketed`); a point above
every learned load is compared with nothing but its own visit's first
estimates, so a change that comes with the visit (a 10 % stiffness loss on the ramp to
a point 3 Nm above every learned one) goes unseen until a learned point is
visited again.

The backlash test (:mod:`online_id.diagnose.linearity`) fits both inertia
equations with a dead zone of the twist and reads the resonance and damping
of the *engaged* flank (:attr:`~online_id.diagnose.linearity.BacklashTest.engaged_f0_hz`,
``engaged_zeta``): the shaft outside the gap, which does not move with the
load (0.8 % median spread of the stiffness across the plateaus of 27 benches,
against 5.4 % for the apparent one, ``scripts/engaged-stiffness-survey``).
On a shaft that showed backlash the service runs the test on every visit,
every ``EVERY_S`` on the last ``WINDOW_S`` of steady samples, and this
module keeps the readings of healthy visits as one reference for the whole
shaft, whatever the point:

* *learn*: a reading joins the reference (at most ``MAX_LEARNED``, then the
  reference stays fixed until re-learned) while the service is healthy with
  no alarm latched, and only where it agrees with the readings learned so far
  (their median: the stiffness :math:`\\propto f^2` within the dead band
  ``dead_band_k``, the damping within ``dead_band_zeta``): a change that
  comes while the reference learns is not taken in;
* *compare*: once it holds ``MIN_LEARNED`` readings, a reading whose stiffness
  is below the reference's median by more than
  ``dead_band_k + SIGMAS * s_k`` (:math:`s_k` the learned readings' spread
  in stiffness, floored at ``MIN_STD_K``) counts against the shaft; the damping
  alike, both ways, with ``dead_band_zeta + SIGMAS * s_zeta`` (floor
  ``MIN_STD_ZETA``). Only a loss of stiffness is tested: the engaged flank of
  a worn shaft gets softer, and a higher load reads the flank a little
  stiffer (the survey's top plateau: -1.2 to +2.5 % healthy);
* *confirm*: ``CONFIRM`` readings in a row beyond, on the same side, raise
  the change (:class:`EngagedChange`, a warning; a fault where their mean
  change is twice the threshold); it is raised once until
  :meth:`EngagedFlank.acknowledge`, after which a change that persists is
  raised again from ``CONFIRM`` new readings.

Why these numbers. Per window (14 s) the engaged stiffness of a healthy
point reads within -1.2 to +2.5 % of the other plateaus' mean, a 5 % loss
-6.0 to -1.8 % (median -5.0), a 10 % loss -11.1 to -6.2 %; over plant
1002's fault-free hour (72 visits) the engaged resonance stayed within
+-0.35 % of its median (0.7 % in stiffness), its damping within +-4 %. The
dead band of 3 % in stiffness with three spreads (at least 0.4 % each) puts
the threshold at 4.2 % or more; two readings in a row keep one odd window
from raising anything. The damping's 20 % (the detector's dead band) with
three spreads of at least 3 % puts its threshold at 29 % or more, where a
+-50 % change reads +47 / -43 %. The false-alarm rate and the delays are
measured by ``online-id evaluate`` (README).
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import asdict, dataclass
from typing import Any

import numpy as np

from online_id.monitoring import defaults
from online_id.monitoring.detection import DAMPING, FREQUENCY

EVERY_S = 6.0  # a reading at most this often within a visit (the test's CPU: 0.16 s median)
WINDOW_S = 14.0  # of the last this many seconds of steady samples (the survey's windows)
MAX_LEARNED = 12  # readings a reference holds; then fixed until re-learned
MIN_LEARNED = 3  # readings before it is compared with
SIGMAS = 3.0
MIN_STD_K = 0.004  # floor of the learned readings' spread in stiffness (relative)
MIN_STD_ZETA = 0.03  # ... in damping (relative)
CONFIRM = 2  # readings in a row beyond the threshold raise a change
DEAD_BAND_K = 0.03  # stiffness change below this counts as none
MAX_CHANGES = 50  # confirmed changes kept for reports


@dataclass(frozen=True)
class EngagedReading:
    """One backlash test's engaged-flank reading (times in stream seconds)."""

    t_s: float
    visit: int
    speed_rpm: float
    load_nm: float
    f0_hz: float
    zeta: float
    source: str = ""  # the run it was taken in (learned readings: what the reference was learned from)

    def as_dict(self) -> dict[str, Any]:
        return asdict(self)


@dataclass(frozen=True)
class EngagedChange:
    """A change of the engaged flank, confirmed by ``CONFIRM`` readings in a row."""

    kind: str  # "frequency" or "damping"
    level: int  # 1 warning, 2 fault
    since_t_s: float  # the first of the confirming readings
    detected_t_s: float
    speed_rpm: float
    load_nm: float
    change: float  # relative change of the resonance (frequency) or damping, mean of the confirming readings
    stiffness_change: float | None  # the frequency's (1 + change)**2 - 1
    reference: float  # the reference's median resonance [Hz] or damping ratio
    threshold: float  # the relative change (stiffness for the frequency) the readings went beyond
    learned: int  # readings the reference holds
    source: str  # the run(s) they were learned in


class EngagedFlank:
    """The reference of the engaged flank and its change test (see the module notes).

    Parameters
    ----------
    dead_band_k
        Relative stiffness loss that counts as none.
    dead_band_zeta
        Relative damping change that counts as none (the detector's dead band).
    """

    def __init__(self, dead_band_k: float = DEAD_BAND_K, dead_band_zeta: float = defaults.MIN_DAMPING_CHANGE_PCT / 100.0) -> None:
        self.dead_band_k = float(dead_band_k)
        self.dead_band_zeta = float(dead_band_zeta)
        self.learned: list[EngagedReading] = []
        self.readings = 0  # readings offered
        self.last: EngagedReading | None = None  # the latest readable one
        self.rejected = 0  # readings not learned (they disagreed with the learned ones)
        self._runs: dict[str, list[tuple[EngagedReading, float]]] = {FREQUENCY: [], DAMPING: []}
        self._raised: dict[str, int] = {FREQUENCY: 0, DAMPING: 0}  # level raised since the last acknowledgement
        self.confirmed = 0  # changes confirmed (raised or not: an alarm of the kind may be latched already)
        self.changes: deque[EngagedChange] = deque(maxlen=MAX_CHANGES)  # the latest of them

    # -- the reference ---------------------------------------------------------------------------
    @property
    def sources(self) -> list[str]:
        """The runs the learned readings were taken in."""
        return sorted({r.source for r in self.learned if r.source})

    @property
    def usable(self) -> bool:
        """Whether the reference holds enough readings to be compared with."""
        return len(self.learned) >= MIN_LEARNED

    def reference(self) -> dict[str, float] | None:
        """Median resonance and damping of the learned readings and their relative spreads (stiffness,
        damping; floored), None while nothing is learned."""
        if not self.learned:
            return None
        f = np.array([r.f0_hz for r in self.learned])
        z = np.array([r.zeta for r in self.learned])
        f_ref, z_ref = float(np.median(f)), float(np.median(z))
        k = (f / f_ref) ** 2 - 1.0
        dz = z / z_ref - 1.0
        ddof = 1 if f.size > 1 else 0
        return {"f0_hz": f_ref, "zeta": z_ref,
                "std_k": max(float(np.std(k, ddof=ddof)), MIN_STD_K),
                "std_zeta": max(float(np.std(dz, ddof=ddof)), MIN_STD_ZETA)}

    def thresholds(self, ref: dict[str, float]) -> tuple[float, float]:
        """The stiffness loss and damping change beyond which a reading counts (relative)."""
        return (self.dead_band_k + SIGMAS * ref["std_k"], self.dead_band_zeta + SIGMAS * ref["std_zeta"])

    # -- per reading -----------------------------------------------------------------------------
    def offer(self, reading: EngagedReading, learn: bool) -> list[EngagedChange]:
        """One reading: learned (where ``learn`` and it agrees), compared, and the changes it confirms."""
        if not (math.isfinite(reading.f0_hz) and reading.f0_hz > 0.0 and math.isfinite(reading.zeta)
                and reading.zeta > 0.0):
            return []
        self.readings += 1
        self.last = reading
        ref = self.reference()
        if ref is None:
            if learn:
                self.learned.append(reading)
            return []
        k = (reading.f0_hz / ref["f0_hz"]) ** 2 - 1.0
        dz = reading.zeta / ref["zeta"] - 1.0
        agrees = abs(k) <= self.dead_band_k and abs(dz) <= self.dead_band_zeta
        changes: list[EngagedChange] = []
        if self.usable:
            th_k, th_z = self.thresholds(ref)
            for kind, beyond, side, th in ((FREQUENCY, k < -th_k, -1.0, th_k),
                                           (DAMPING, abs(dz) > th_z, math.copysign(1.0, dz), th_z)):
                run = self._runs[kind]
                if not beyond or (run and run[-1][1] != side):
                    run.clear()
                if beyond:
                    run.append((reading, side))
                    change = self._confirmed(kind, run, ref, th)
                    if change is not None:
                        changes.append(change)
        if learn and agrees and len(self.learned) < MAX_LEARNED and not changes:
            self.learned.append(reading)
        elif not agrees:
            self.rejected += 1
        return changes

    def _confirmed(self, kind: str, run: list[tuple[EngagedReading, float]], ref: dict[str, float],
                   threshold: float) -> EngagedChange | None:
        if len(run) < CONFIRM:
            return None
        last = [r for r, _ in run[-CONFIRM:]]
        if kind == FREQUENCY:
            change = float(np.mean([r.f0_hz for r in last])) / ref["f0_hz"] - 1.0
            measure = -((1.0 + change) ** 2 - 1.0)
        else:
            change = float(np.mean([r.zeta for r in last])) / ref["zeta"] - 1.0
            measure = abs(change)
        level = 2 if measure >= 2.0 * threshold else 1
        if level <= self._raised[kind]:
            return None
        self._raised[kind] = level
        now = last[-1]
        self.confirmed += 1
        self.changes.append(EngagedChange(kind, level, last[0].t_s, now.t_s, now.speed_rpm, now.load_nm, change,
                                          (1.0 + change) ** 2 - 1.0 if kind == FREQUENCY else None,
                                          ref["f0_hz"] if kind == FREQUENCY else ref["zeta"], threshold,
                                          len(self.learned), ", ".join(self.sources)))
        return self.changes[-1]

    # -- commands --------------------------------------------------------------------------------
    def acknowledge(self) -> None:
        """Alarms acknowledged: a change that persists is raised again from ``CONFIRM`` new readings."""
        self._raised = {FREQUENCY: 0, DAMPING: 0}
        for run in self._runs.values():
            run.clear()

    def reset(self) -> None:
        """Forget the reference (re-learn on command: a new shaft)."""
        self.__init__(self.dead_band_k, self.dead_band_zeta)

    # -- persistence -----------------------------------------------------------------------------
    def to_dict(self) -> dict[str, Any]:
        return {"learned": [r.as_dict() for r in self.learned], "readings": self.readings,
                "rejected": self.rejected, "raised": dict(self._raised),
                "dead_band_k": self.dead_band_k, "dead_band_zeta": self.dead_band_zeta}

    @classmethod
    def from_dict(cls, data: Any) -> EngagedFlank:
        """A flank as :meth:`to_dict` saved it, with its dead bands (a report of a saved state; the service
        restores with :meth:`load` and keeps the dead bands of the config in force)."""
        bands = data if isinstance(data, dict) else {}
        keep = {k: float(v) for k in ("dead_band_k", "dead_band_zeta") if isinstance(v := bands.get(k), (int, float))
                and not isinstance(v, bool) and math.isfinite(v) and v >= 0.0}
        flank = cls(**keep)
        flank.load(data)
        return flank

    def load(self, data: Any) -> None:
        """Restore the learned readings and the counts saved by :meth:`to_dict` (malformed entries are skipped)."""
        if not isinstance(data, dict):
            return
        for name in ("readings", "rejected"):
            n = data.get(name)
            if isinstance(n, int) and not isinstance(n, bool) and n >= 0:
                setattr(self, name, n)
        kept = []
        for x in data.get("learned", []) if isinstance(data.get("learned"), list) else ():
            try:
                r = EngagedReading(**x)
            except TypeError:
                continue
            if all(isinstance(v, (int, float)) and math.isfinite(v) for v in (r.t_s, r.f0_hz, r.zeta)):
                kept.append(r)
        self.learned = kept[:MAX_LEARNED]
        raised = data.get("raised", {})
        self._raised = {k: int(raised.get(k, 0)) if isinstance(raised, dict) else 0 for k in (FREQUENCY, DAMPING)}

    def summary(self) -> dict[str, Any]:
        """For reports: the reference, its thresholds and counts."""
        ref = self.reference()
        out: dict[str, Any] = {"learned": len(self.learned), "readings": self.readings, "rejected": self.rejected,
                               "usable": self.usable, "confirmed": self.confirmed}
        if ref is not None:
            th_k, th_z = self.thresholds(ref)
            out |= {"f0_hz": ref["f0_hz"], "zeta": ref["zeta"], "std_k_pct": 100 * ref["std_k"],
                    "std_zeta_pct": 100 * ref["std_zeta"], "threshold_k_pct": 100 * th_k,
                    "threshold_zeta_pct": 100 * th_z,
                    "sources": self.sources}
        return out
