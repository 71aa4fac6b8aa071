"""What an estimate is compared with, and how that reads for people.

An estimate is compared with its own cell's baseline (learned, or still learning with its first estimates), else a
learned cell of another load or an adjacent band, else the pooled baseline
(:class:`~online_id.monitoring.baseline.Baseline`).  On a shaft that showed backlash the resonance moves with the
operating point: the learned cells of smaller and larger loads bound it, and where nothing bounds it (or one side
only), the first estimates of the visit serve (:mod:`~online_id.monitoring.visit`).

:class:`Comparison` is a part the :class:`~online_id.service.policy.DetectionPolicy` owns: it counts the visits of
operating points and keeps the first estimates of the current one.  The baselines and the detector's dead bands
are the policy's and come with each call.
"""

from __future__ import annotations

import dataclasses
import math

from online_id.config import DetectionSettings
from online_id.estimation.online import OnlineDriveline, OnlineEstimate
from online_id.estimation.reference import ReferenceWindow
from online_id.monitoring.baseline import Baseline
from online_id.monitoring.cells import BandStats
from online_id.monitoring.detection import FREQUENCY, ChangeDetector
from online_id.monitoring.visit import VisitReference
from online_id.service.confirmation import in_cell
from online_id.service.events import Event


class Comparison:
    """The choice of what an estimate is compared with, and the visits of operating points (see module notes).

    Parameters
    ----------
    detection
        The detection settings in force (``load_band_nm``: the load that makes another operating point).
    """

    def __init__(self, detection: DetectionSettings) -> None:
        self.detection = detection
        self.visit = 0  # counts the arrivals of healthy estimates at another operating point
        self.visit_ref: VisitReference | None = None  # a visit's first estimates, where no learned cell bounds it
        self._next_visit_sample = 0.0
        self._visit_not_compared = -1  # the visit where another point's baseline was last not compared with

    def on_time_jump(self) -> None:
        """The stream clock jumped: the visit's next estimate is taken at once."""
        self._next_visit_sample = -math.inf

    def baseline_for(self, baseline: Baseline, speed: float, load: float, learning: bool = False) -> BandStats | None:
        """What an estimate at ``speed`` and ``load`` is compared with in ``baseline``: its own cell, learned, or still
        learning (not held) with its first estimates (frozen: ``provisional_count`` of them, then ``freeze_count``)
        once it holds them (the same operating point: a learned cell at another load of the band differs by 0.1-0.5 %
        per Nm with backlash); else a learned cell of the band at another load or of an adjacent band
        (:meth:`Baseline.lookup`); else the pooled baseline (for detection the pool's spread is doubled, for the
        learning check, ``learning``, it is not). On a shaft that showed backlash (:attr:`Baseline.nonlinear`) no
        other single point serves: the learned cells of smaller and larger loads bound the resonance
        (:meth:`Baseline.bracketed`, its bounds widened by the order's slack; None where none does)."""
        n = baseline.provisional_count
        own = baseline.cell(speed, load, frozen=True)
        if own is not None and own.count >= n:
            return own  # as it is: its spread is widened while it holds fewer than freeze_count estimates
        stats = baseline.lookup(speed, load)
        nonlinear = baseline.nonlinear
        if stats is not None and (not nonlinear or is_own(stats, speed, load, baseline.load_band_nm)):
            return stats
        if nonlinear:
            # a shaft with backlash: its resonance moves with the operating point, but rises with the magnitude of
            # the load; the learned cells of smaller and larger loads bound it (None where nothing does)
            pool = baseline.bracketed(speed, load)
        else:
            pool = baseline.pooled(speed, load, min_n=n)
        if pool is not None and not learning and pool.kind == "pooled":
            # for detection, doubled: it stands for a point it has not seen (a bracket's bounds hold the slack)
            pool = dataclasses.replace(pool, std_f=2.0 * pool.std_f, std_zeta=2.0 * pool.std_zeta)
        return pool

    def not_compared(self, baseline: Baseline, t_s: float, speed: float, load: float) -> Event | None:
        """The event, once a visit, that no learned cell is compared with at ``speed`` and ``load`` (where
        :meth:`baseline_for` gives nothing), on a shaft that showed backlash whose baseline has learned cells."""
        if not baseline.nonlinear or self._visit_not_compared == self.visit or baseline.learned_range_rpm is None:
            return None
        # on a shaft with backlash the resonance moves with the operating point (rising with the load's
        # magnitude): where no learned cell bounds it (a load below them all, farther than they span, or
        # no cell yet), the visit's own first settled estimates serve, then the cell's,
        # and a change that comes with the visit shows at the established points (it shows everywhere)
        self._visit_not_compared = self.visit
        return Event(t_s, "not_compared", f"at {speed:.0f} rpm, {load:.1f} Nm no learned cell is "
                     f"compared with: the shaft shows backlash, so its resonance moves with the "
                     f"load, and no learned cell bounds it here; the estimates are compared with "
                     f"the first estimates of this visit", {})

    @staticmethod
    def visit_serves(stats: BandStats | None, nonlinear: bool) -> bool:
        """Whether the first estimates of the visit serve where ``stats`` (what :meth:`baseline_for` gives)
        does: on a shaft with backlash (``nonlinear``), where no learned cell of this point serves (its damping;
        its frequency too where no learned cell bounds the point, or bounds it on one side only)."""
        return nonlinear and (stats is None or stats.kind == "bracketed")

    def sample_visit(self, est: OnlineEstimate, t_s: float, speed: float, load: float, settled: bool,
                     bounds: BandStats | None, model: OnlineDriveline, baseline: Baseline,
                     detector: ChangeDetector) -> None:
        """Offer a settled estimate (about one a second) to the first estimates of this visit
        (:mod:`~online_id.monitoring.visit`); one that the detector would count as outside the one-sided ``bounds``
        (beyond the dead band) does not join, so that there the bound goes on serving."""
        ref = self.visit_ref
        if ref is not None and not ref.matches(self.visit, load, self.detection.load_band_nm):
            ref = self.visit_ref = None  # another visit, or the load moved: another operating point
        if not settled:
            return
        if bounds is not None and bounds.outside_f(est.f0_hz, detector.min_change_f, 0.0):
            return  # beyond the dead band of the bound the learned cells set: a change must not become the reference
        if ref is None:
            ref = self.visit_ref = VisitReference(self.visit, load, baseline.band_of(speed),
                                                  min_count=baseline.provisional_count,
                                                  size=baseline.freeze_count,
                                                  min_rel_std_f=baseline.min_rel_std_f,
                                                  min_rel_std_zeta=baseline.min_rel_std_zeta)
            self._next_visit_sample = t_s
        if t_s >= self._next_visit_sample:
            self._next_visit_sample = t_s + 1.0  # about one independent-ish estimate per second
            solution = model.solution
            if (ref.add(t_s, est.f0_hz, est.zeta, load, detector.min_change_f, solution,
                        detector.min_change_zeta) and len(ref.f) <= ref.min_count and solution is not None):
                job = model.verify_job()  # the data of the frozen first estimates, for a recheck
                if job is not None:
                    ref.window = ReferenceWindow(job.y, job.u, solution, speed, load, t_s)

    def with_visit(self, stats: BandStats | None, load: float, nonlinear: bool) -> BandStats | None:
        """``stats``, or the first estimates of this visit where they serve (:meth:`visit_serves`) and hold
        ``provisional_count`` estimates: their frequency where nothing or one side bounds the point; their damping
        where the learned cells do not measure how far it moves between points (fewer than
        ``MIN_CELLS_DAMPING``, :meth:`Baseline.bracketed`: it moves 3-57 % between points with backlash, and
        was not compared at all), in a two-sided bracket too (:attr:`BandStats.zeta_visit`)."""
        ref = self.visit_ref
        if not self.visit_serves(stats, nonlinear) or ref is None or not ref.matches(self.visit, load,
                                                                                     self.detection.load_band_nm):
            return stats
        visit = ref.stats()
        if visit is None or stats is None:
            return visit or stats
        measured = math.isfinite(stats.std_zeta)  # the learned cells measure how far the damping moves between points
        if not math.isfinite(stats.above_f + stats.below_f):  # bounded on one side only: the visit's frequency
            return visit if not measured else dataclasses.replace(
                visit, mean_zeta=stats.mean_zeta, std_zeta=stats.std_zeta, tolerance_zeta=stats.tolerance_zeta,
                between_zeta=stats.between_zeta, zeta_visit=False)
        return stats if measured else dataclasses.replace(
            stats, mean_zeta=visit.mean_zeta, std_zeta=visit.std_zeta, tolerance_zeta=0.0, between_zeta=math.nan,
            widen=visit.widen, zeta_visit=True)


def is_own(stats: BandStats, speed: float, load: float, load_band_nm: float) -> bool:
    """Whether ``stats`` is the baseline of the cell of ``speed`` and ``load`` itself (not the pool's or
    another band's or load's), cells being ``load_band_nm`` wide."""
    if stats.kind == "learning":
        return True  # only a cell's own first estimates serve it while it learns
    return stats.kind in ("learned", "reference") and in_cell(stats, speed, load, load_band_nm)


def versus_text(why: str, est: OnlineEstimate, ref: BandStats) -> str:
    """The disagreeing quantity of ``est`` against ``ref`` for an event: "26.412 Hz against 26.583 +- 0.053 Hz"."""
    if why == FREQUENCY and ref.kind == "bracketed":
        return f"{est.f0_hz:.3f} Hz against {bounds_text(ref)}, +- {ref.std_f:.3f} Hz"
    if why == FREQUENCY:
        return f"{est.f0_hz:.3f} Hz against {ref.mean_f:.3f} +- {ref.std_f:.3f} Hz"
    return f"zeta {est.zeta:.4f} against {ref.mean_zeta:.4f} +- {ref.std_zeta:.4f}"


def against_text(stats: BandStats) -> str:
    """What an alarm was raised against, for people: "the learned baseline of 1500 rpm, 20 Nm (24.10 Hz), learned
    from run 3", "the pooled baseline (...)", "the bounds of the learned cells of other loads (...)", "the first
    estimates of this visit since t = 67.0 s (22.28 Hz)"."""
    if stats.kind == "visit":
        return (f"the first estimates of {stats.source} ({stats.mean_f:.2f} Hz"
                + (f", zeta {stats.mean_zeta:.4f})" if stats.zeta_visit else
                   "), the damping against the learned cells of other loads"))
    what = (f"the pooled baseline ({stats.mean_f:.2f} Hz)" if stats.kind == "pooled" else
            f"the bounds of the learned cells of other loads ({bounds_text(stats)})" if stats.kind == "bracketed" else
            f"the {stats.kind} baseline of {0.5 * (stats.band[0] + stats.band[1]):.0f} rpm"
            + (f", {stats.load_nm:.0f} Nm" if math.isfinite(stats.load_nm) else "") + f" ({stats.mean_f:.2f} Hz)")
    return (what + (f", learned from {stats.source}" if stats.source else "")
            + (f", the damping against the first estimates of this visit ({stats.mean_zeta:.4f})"
               if stats.zeta_visit else ""))


def bounds_text(stats: BandStats) -> str:
    """A bracketed baseline's bounds for people: ``f0 >= 20.10 Hz``, ``f0 <= ...`` or ``20.10-20.50 Hz``."""
    lo, hi = stats.bounds_f
    if math.isfinite(lo) and math.isfinite(hi):
        return f"{lo:.2f}-{hi:.2f} Hz"
    return f"f0 >= {lo:.2f} Hz" if math.isfinite(lo) else f"f0 <= {hi:.2f} Hz"
