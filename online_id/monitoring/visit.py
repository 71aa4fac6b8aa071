"""The first estimates of a visit: what a point that no learned cell bounds is compared with.

On a shaft with backlash the apparent resonance moves with the load (it rises with the load's magnitude), so a point
whose load lies below every learned cell has no bound from below
(:meth:`~online_id.monitoring.baseline.Baseline.bracketed`). A change of the driveline while the bench dwells there
would go unseen until the bench came back to a learned point, and the point's cell would learn the changed resonance.
The visit's own first settled estimates serve instead: a change during the visit shows as a step against them (a
change that comes with the visit still shows at the learned points).

The reference never absorbs a change. Its first ``min_count`` estimates are frozen at once and serve, their spread
floored at ``min_rel_std_f`` of the mean and widened by :math:`\\sqrt{N_\\text{size} / N}` (a few strongly correlated
estimates under-state it), as a cell's provisional reference; a later estimate joins only when it agrees with them
(the detector's dead band plus three spreads, as :meth:`~online_id.monitoring.cells.BandStats.disagrees`), and once
``size`` have joined, they serve. Against the running statistics of all it holds, a change that the 10 s fit window
takes in bit by bit would creep in, each estimate within the tolerance of those before it.

It compares the damping too, with the same frozen first estimates (spread floored at ``min_rel_std_zeta`` of the mean
and widened alike); a later estimate joins only when its damping agrees as well (half the damping dead band plus three
unwidened spreads, the learning check's). The damping of a mismatched model moves by 30-40 % between nearly equal
minima of the fit, which a visit's few estimates cannot tell from a change; the alarm's checks do (see
``AlarmChecks.confirm``): the second look refits the window from the minimum the reference sat in (:attr:`solution`),
and the recheck refits the data of the reference's first estimates (:attr:`window`, a
:class:`~online_id.estimation.reference.ReferenceWindow` the caller keeps) from the current solution, which gives the
current estimate again where only the minimum moved. Without the visit's damping, a damping change at a point no
cell has learned on a shaft with backlash would go into the point's cell and never be seen (-42 % at a new point,
3 s after the estimate was valid there, on a simulated bench).
"""

from __future__ import annotations

import math
from typing import Any

from online_id.monitoring.cells import BandStats


class VisitReference:
    """The first settled estimates of one visit of an operating point (see module notes).

    Parameters
    ----------
    visit
        The visit's number (the caller's count of arrivals at another operating point).
    load_nm
        The load of the visit's first estimate [Nm].
    band
        The speed band ``(low_rpm, high_rpm)`` the visit is in.
    min_count
        Estimates the reference needs before it serves (and before an estimate must agree to join).
    size
        Estimates it holds at most.
    min_rel_std_f, min_rel_std_zeta
        Floors of the frequency and damping spreads, relative to the means.
    """

    def __init__(self, visit: int, load_nm: float, band: tuple[float, float], *, min_count: int = 3, size: int = 10,
                 min_rel_std_f: float = 0.002, min_rel_std_zeta: float = 0.03) -> None:
        if not (2 <= min_count <= size):
            raise ValueError(f"VisitReference: expected 2 <= min_count <= size, got {min_count} and {size}")
        self.visit = visit
        self.load_nm = float(load_nm)
        self.band = band
        self.min_count = min_count
        self.size = size
        self.min_rel_std_f = min_rel_std_f
        self.min_rel_std_zeta = min_rel_std_zeta
        self.t_first: float | None = None
        self.f: list[float] = []
        self.z: list[float] = []
        self.loads: list[float] = []
        self.solution: Any = None
        self.window: Any = None  # the caller's window of the first estimates (their data, for a recheck)
        self.refused = 0  # estimates that disagreed and did not join

    def matches(self, visit: int, load_nm: float, load_band_nm: float) -> bool:
        """Whether an estimate of ``visit`` at ``load_nm`` belongs to this visit (within half a load band)."""
        return visit == self.visit and abs(load_nm - self.mean_load) <= 0.5 * load_band_nm

    @property
    def mean_load(self) -> float:
        return sum(self.loads) / len(self.loads) if self.loads else self.load_nm

    def add(self, t_s: float, f0_hz: float, zeta: float, load_nm: float, min_change_f: float,
            solution: Any = None, min_change_zeta: float = math.inf) -> bool:
        """Offer one estimate; True if it joined (see module notes). ``min_change_zeta``: the damping's dead band
        (relative; half of it, plus three unwidened spreads, is what a joining estimate's damping must agree
        within)."""
        if len(self.f) >= self.size or not all(math.isfinite(x) for x in (f0_hz, zeta, load_nm)):
            return False
        stats = self.stats()
        if stats is not None and stats.disagrees(f0_hz, zeta, min_change_f, 0.5 * min_change_zeta):
            self.refused += 1
            return False
        if self.t_first is None:
            self.t_first = t_s
        self.f.append(float(f0_hz))
        self.z.append(float(zeta))
        self.loads.append(float(load_nm))
        if solution is not None:
            self.solution = solution
        return True

    def stats(self) -> BandStats | None:
        """What an estimate of the visit is compared with (kind ``"visit"``), or None with fewer than
        ``min_count`` estimates: the first ``min_count`` estimates until it holds ``size`` (frozen, so that a
        change the fit window takes in bit by bit cannot creep into it), then all ``size``; the damping alike."""
        n = len(self.f)
        if n < self.min_count:
            return None
        if n < self.size:
            n = self.min_count
        f = self.f[:n]
        mean = sum(f) / n
        std = math.sqrt(sum((x - mean) ** 2 for x in f) / (n - 1))
        z = self.z[:n]
        mean_z = sum(z) / n
        std_z = math.sqrt(sum((x - mean_z) ** 2 for x in z) / (n - 1))
        widen = math.sqrt(self.size / n)
        std = max(std, self.min_rel_std_f * abs(mean)) * widen
        std_z = max(std_z, self.min_rel_std_zeta * abs(mean_z)) * widen
        return BandStats(mean, std, mean_z, std_z, n, self.band, self.mean_load, "visit",
                         f"this visit since t = {self.t_first:.1f} s", widen=widen, zeta_visit=True)
