"""The checks a drift alarm passes before it stands, and the references they compare with.

:class:`AlarmChecks` is a part the :class:`~online_id.service.policy.DetectionPolicy` owns.  Before the
detector raises a new drift alarm it asks :meth:`~AlarmChecks.confirm`:

* *still accepted*: an earlier recheck found the cell's own data give the current resonance, and nothing since
  says otherwise: withheld without another recheck;
* *second look*: a multi-start refit of the current window (from the minimum the baseline was learned in among
  its starts) still deviates beyond the dead band;
* *recheck*: the data the cell's baseline was learned from (its reference window), refitted from the current
  window solution, do not give the current estimate again (:mod:`~online_id.estimation.reference`).

A mismatched model (backlash) has nearly equal minima of the criterion whose damping differs by 30-40 % and whose
resonance differs by 1-3 %; the estimate may sit in either for minutes at a learned operating point.  The checks
tell such a hop between minima from a change of the driveline.

It keeps the window solution each baseline band was learned from (:attr:`~AlarmChecks.references`) and the window
of each cell's first estimates (:attr:`~AlarmChecks.windows`), and runs the multi-start refits a new cell learns
from (:meth:`~AlarmChecks.verify`).  Its slow work goes to the worker it is given; the inputs that belong to the
policy (the estimate judged, the baselines, the detector's dead bands, the visit) come with each call.
"""

from __future__ import annotations

import math
from collections import deque
from typing import Callable

import numpy as np

from online_id.config import DetectionSettings
from online_id.estimation.online import OnlineDriveline, OnlineEstimate
from online_id.estimation.reference import ReferenceWindow, judge, refit_each
from online_id.estimation.window import solve
from online_id.monitoring.baseline import Baseline
from online_id.monitoring.cells import BandStats
from online_id.monitoring.detection import DAMPING, FREQUENCY, ChangeDetector, when_text
from online_id.monitoring.visit import VisitReference
from online_id.service.events import WINDOW, Event

PENDING = None  # a multi-start check is running in the worker: decide later
VERIFY_FRESH_S = 5.0  # a multi-start check older than this is not used for a decision
RECHECK_WAIT_S = 10.0  # a recheck of a reference window older than this is dropped (see AlarmChecks.confirm)
# the two nearly equal minima of a model that does not fit exactly (backlash) differ by 1-3 % in the resonance
# (see online_id.monitoring.detection): a frequency change a recheck withheld stands only within this
MINIMA_SPREAD_F = 0.03
ACCEPTED_SIGMAS = 3.0  # ... while the estimate moves no farther from the baseline than this many of its own stds


def of_visit(stats: BandStats, kind: str) -> bool:
    """Whether an alarm of ``kind`` against ``stats`` is checked against the visit's first estimates (their
    solution and window): of the visit's own baseline (kind ``"visit"``), or of a bracket's damping that is
    the visit's (:attr:`BandStats.zeta_visit`)."""
    return stats.kind == "visit" or (kind == DAMPING and stats.zeta_visit)


def in_cell(stats: BandStats, speed: float, load: float, load_band_nm: float) -> bool:
    """Whether ``speed`` and ``load`` fall in the band and load cell of ``stats`` (any load if it has none), cells
    being ``load_band_nm`` wide."""
    return stats.band[0] <= speed < stats.band[1] and not abs(stats.load_nm - load) > 0.5 * load_band_nm


class AlarmChecks:
    """The checks before a drift alarm stands, and the reference solutions and windows (see module notes).

    Parameters
    ----------
    detection
        The detection settings in force (the ties ``frequency_tie_pct`` and ``damping_tie_pct``).
    worker
        Where slow work runs (:mod:`online_id.service.offload`): ``submit(lane, fn, args, done)`` and
        ``busy(lane)``.
    submit_window
        ``submit_window(fn, args, done)``: a multi-start refit to the worker's window lane.
    events
        The event log the checks append to (an alarm withheld, and why).
    """

    def __init__(self, detection: DetectionSettings, worker, submit_window: Callable, events: deque[Event]) -> None:
        self.detection = detection
        self.worker = worker
        self._submit_window = submit_window
        self.events = events
        self.references: dict[int, np.ndarray] = {}  # per baseline band: a window solution it was learned from
        # per baseline band, one per cell (load): the window of the cell's first estimates, see keep_window
        self.windows: dict[int, list[ReferenceWindow]] = {}
        self._rechecks: dict[str, dict] = {}  # per alarm kind: a recheck of a reference window under way
        self._accepted: dict | None = None  # the frequency a recheck found the cell's own data give (_still_accepted)
        self._verify_results: dict = {}  # purpose -> (t_s submitted, adopted) of finished multi-start checks
        self._verify_running: set = set()

    def forget(self) -> None:
        """Forget the reference solutions and windows and the checks under way (a relearn)."""
        self.references.clear()
        self.windows.clear()
        self.restart()

    def restart(self) -> None:
        """Drop the checks under way and a recheck's finding (a restored state)."""
        self._rechecks = {}
        self._accepted = None

    def to_dict(self) -> dict:
        """The reference solutions and windows, items of the state document (:mod:`online_id.service.persistence`)."""
        return {"references": {str(k): v.tolist() for k, v in self.references.items()},
                "windows": {str(k): [w.to_dict() for w in ws] for k, ws in self.windows.items()}}

    def load(self, state: dict, n_params: int) -> None:
        """Restore the items of :meth:`to_dict` from the state document ``state`` (solutions of ``n_params`` model
        parameters; others are dropped), without checks under way."""
        self.references = {int(k): np.asarray(v, dtype=float) for k, v in state.get("references", {}).items()
                           if isinstance(v, (list, np.ndarray)) and len(v) == n_params}
        windows = state.get("windows", {})
        self.windows = {}
        for k, v in windows.items() if isinstance(windows, dict) else ():
            saved = v if isinstance(v, list) and str(k).lstrip("-").isdigit() else []
            kept = [w for w in (ReferenceWindow.from_dict(x, n_params) for x in saved if isinstance(x, dict))
                    if w is not None]
            if kept:
                self.windows[int(k)] = kept
        self.restart()

    def verify(self, purpose, t_s: float, model: OnlineDriveline, starts: tuple = (),
               prefer_last_within: float = 0.0) -> bool | None:
        """A multi-start refit of the window for ``purpose``: True/False (a fit adopted or not), or PENDING.

        With the inline worker the check runs at once; with the process
        worker the first call starts it and returns PENDING, and a later call
        (within ``VERIFY_FRESH_S``) gets its outcome.
        """
        done = self._verify_results.pop(purpose, None)
        if done is not None and 0.0 <= t_s - done[0] <= VERIFY_FRESH_S:
            return done[1]
        if purpose in self._verify_running or self.worker.busy(WINDOW):
            return PENDING
        job = model.verify_job(starts, prefer_last_within)
        if job is None:
            return False

        def finished(fit, error: str | None) -> None:
            self._verify_running.discard(purpose)
            self._verify_results[purpose] = (t_s, model.complete(job, fit, error))

        self._verify_running.add(purpose)
        self._submit_window(solve, (job,), finished)
        done = self._verify_results.pop(purpose, None)
        return PENDING if done is None else done[1]

    def keep_window(self, cell: BandStats, speed: float, load: float, t_s: float, solution: np.ndarray,
                    model: OnlineDriveline, baseline: Baseline) -> None:
        """Keep the window of a cell's first estimates, the ones its frozen reference holds (up to
        ``provisional_count``), for the recheck; later estimates do not replace it (one learned after a
        change the learning check let through would make the recheck compare the change with itself)."""
        if cell.count > baseline.provisional_count:
            return
        job = model.verify_job()
        if job is None:
            return
        key, width = baseline.key(speed), baseline.load_band_nm
        kept = [w for w in self.windows.get(key, []) if not in_cell(cell, w.speed_rpm, w.load_nm, width)]
        self.windows[key] = kept + [ReferenceWindow(job.y, job.u, solution, speed, load, t_s)]

    def confirm(self, kind: str, stats: BandStats, t_s: float, model: OnlineDriveline, estimate: OnlineEstimate | None,
                baseline: Baseline, detector: ChangeDetector, visit: int,
                visit_ref: VisitReference | None) -> bool | None:
        """Before a new drift alarm of ``kind`` against ``stats``: does the change stand a second look at the window,
        and a recheck of the data the baseline was learned from?  True: raise it; False: withhold it; None: a check
        runs in the worker (the detector asks again at its next interval).

        ``estimate`` is the estimate judged, ``baseline`` and ``detector`` (its dead bands) the policy's,
        ``visit`` counts the visits of operating points and ``visit_ref`` holds the first estimates of one.
        """
        check = self._rechecks.get(kind)
        if check is not None and (t_s - check["t_s"] > RECHECK_WAIT_S or check["band"] != stats.band):
            del self._rechecks[kind]  # of an alarm the detector no longer asks about: this one starts afresh
            check = None
        if check is None and self._still_accepted(kind, stats, t_s, estimate, visit):
            return False
        if check is None:
            verdict = self._second_look(kind, stats, t_s, model, baseline, detector, visit_ref)
            if verdict is not True:
                return verdict
        return self._recheck(kind, stats, t_s, model, baseline, detector, visit, visit_ref)

    def _still_accepted(self, kind: str, stats: BandStats, t_s: float, est: OnlineEstimate | None,
                        visit: int) -> bool:
        """Does a recheck's finding that the cell's own data give the current resonance still stand?

        Each recheck's fits carry their own noise: asking the same question every few tens of seconds until
        one answer differs would raise an alarm on a fault-free driveline whose estimate stays where a recheck
        accepted it.  The finding stands, and the alarm is withheld without another recheck, only where it can
        be the hop between minima it describes, and nothing since says otherwise: a frequency change within
        ``MINIMA_SPREAD_F`` of the baseline, at the same cell in the same visit, with the estimate within
        the recheck's tolerance of the value it accepted and no farther from the baseline than
        ``ACCEPTED_SIGMAS`` of its own standard deviations (over a long visit a healthy estimate wanders by
        more than one).  A larger change (a stiffness loss a first recheck withheld) or an estimate moving on
        towards the alarm's side is rechecked afresh each time.
        """
        done = self._accepted
        if kind != FREQUENCY or done is None or est is None or not math.isfinite(est.f0_hz):
            return False
        step = est.f0_hz / done["f0_hz"] - 1.0
        own = est.f0_std_hz / est.f0_hz if math.isfinite(est.f0_std_hz) else 0.0
        if (done["band"] != stats.band or done["visit"] != visit or abs(step) > done["tolerance"]
                or math.copysign(1.0, done["change"]) * step > ACCEPTED_SIGMAS * own):
            self._accepted = None
            return False
        self.events.append(Event(
            t_s, "withheld", f"{kind} alarm withheld: the estimate is where the recheck at {when_text(done['t_s'])} "
            f"found the cell's own data give it ({100 * step:+.2f} %, within its {100 * done['tolerance']:.1f} % "
            f"tolerance, no farther from the baseline than {ACCEPTED_SIGMAS:.0f} of its own standard deviations)",
            {"kind": kind, "change_pct": 100 * step, "recheck_t_s": done["t_s"]}))
        return True

    def _second_look(self, kind: str, stats: BandStats, t_s: float, model: OnlineDriveline, baseline: Baseline,
                     detector: ChangeDetector, visit_ref: VisitReference | None) -> bool | None:
        """Does a refit of the window from several starts still deviate?

        The starts include the solution the band's baseline was learned from
        (see :class:`~online_id.monitoring.detection.ChangeDetector`, *confirm*).
        None while the refit runs in the worker.
        """
        if of_visit(stats, kind) and visit_ref is not None:
            ref = visit_ref.solution  # the minimum the visit's first estimates sat in
        else:
            key = baseline.key(0.5 * (stats.band[0] + stats.band[1]))
            near = sorted(self.references, key=lambda k: abs(k - key))  # a pool: the nearest learned band's
            ref = self.references[near[0]] if near else None
        # where the baseline's own minimum fits the window nearly as well as the best, the data do not tell them
        # apart: a mismatched model (backlash) has nearly equal minima whose damping differs by 30-40 % and whose
        # resonance differs by 1-3 %, and the estimate may sit in either for minutes at a learned operating point
        if self.verify(("confirm", kind), t_s, model, (ref,), self._tie(kind)) is PENDING:
            return None
        est = model.estimate()
        if kind == FREQUENCY:  # beyond the bounds of a bracketed baseline
            change, width = stats.excess_f(est.f0_hz) / stats.mean_f, detector.min_change_f
        else:
            change, width = est.zeta / stats.mean_zeta - 1.0, detector.min_change_zeta
        if not math.isfinite(change) or abs(change) > width:
            return True
        self.events.append(Event(t_s, "withheld", f"{kind} alarm withheld: a refit of the window from other starts "
                                 f"is {100 * change:+.1f} % from the baseline, inside the "
                                 f"{100 * width:.1f} % dead band", {"kind": kind, "change_pct": 100 * change}))
        return False

    def _tie(self, kind: str) -> float:
        """The share of loss within which two minima are not told apart (``detection.*_tie_pct``), for ``kind``."""
        d = self.detection
        return (d.damping_tie_pct if kind == DAMPING else d.frequency_tie_pct) / 100.0

    def _reference_window(self, stats: BandStats, kind: str, baseline: Baseline, visit: int,
                          visit_ref: VisitReference | None) -> ReferenceWindow | None:
        """The window of the first estimates of the cell of ``stats``, where ``stats`` is a cell's own baseline
        (learned, learning or from a reference run), or of this visit's (kind ``"visit"``, or the damping of a
        bracket that holds the visit's, :attr:`BandStats.zeta_visit`)."""
        if of_visit(stats, kind):
            return visit_ref.window if visit_ref is not None and visit_ref.visit == visit else None
        if stats.kind not in ("learned", "learning", "reference"):
            return None
        windows = self.windows.get(baseline.key(0.5 * (stats.band[0] + stats.band[1])), [])
        return next((w for w in windows if in_cell(stats, w.speed_rpm, w.load_nm, baseline.load_band_nm)), None)

    def _recheck(self, kind: str, stats: BandStats, t_s: float, model: OnlineDriveline, baseline: Baseline,
                 detector: ChangeDetector, visit: int, visit_ref: VisitReference | None) -> bool | None:
        """The data the cell's baseline was learned from, refitted from the current window solution: is the
        change still there within one minimum of the criterion? (:mod:`~online_id.estimation.reference`)

        Withheld where the reference data in the current minimum give the
        current estimate again (within the dead band plus one standard
        deviation of the comparison) and fit there within the second look's
        tie of their own minimum: the estimate moved to another minimum, the
        driveline did not change. Raised where no window serves or a fit
        fails. A recheck the detector has not asked about again within
        ``RECHECK_WAIT_S`` (or asks about at another band) is dropped, and the
        next alarm starts with a second look.
        """
        check = self._rechecks.get(kind)
        if check is None:
            window, solution = self._reference_window(stats, kind, baseline, visit, visit_ref), model.solution
            est = model.estimate()
            if window is None or solution is None or est is None:
                return True
            # the tolerance: the dead band plus one standard deviation of the difference of two single estimates
            damping = kind == DAMPING
            value, own, spread = ((est.zeta, est.zeta_std, stats.std_zeta) if damping
                                  else (est.f0_hz, est.f0_std_hz, stats.std_f))
            noise = math.hypot(*(x if math.isfinite(x) else 0.0 for x in (own, spread))) / value if value > 0 else 0.0
            width = detector.min_change_zeta if damping else detector.min_change_f
            check = self._rechecks[kind] = {"t_s": t_s, "band": stats.band, "window": window, "f0_hz": est.f0_hz,
                                            "zeta": est.zeta, "solution": solution, "result": None,
                                            "submitted": False,
                                            "tolerance": width + (noise if math.isfinite(noise) else 0.0)}
        if not check["submitted"]:
            if self.worker.busy(WINDOW):
                return PENDING
            check["submitted"] = True
            window = check["window"]

            def finished(fits, error: str | None) -> None:
                check["result"] = (fits, error)

            self._submit_window(refit_each, (window.y, window.u, model.orders,
                                             (window.solution, check["solution"])), finished)
        if check["result"] is None:
            return PENDING
        del self._rechecks[kind]
        fits, error = check["result"]
        damping, tolerance = kind == DAMPING, check["tolerance"]
        r = judge(fits, model.dt, check["f0_hz"], check["zeta"], damping, tolerance, self._tie(kind)) \
            if error is None else None
        if r is None or not r.withhold:
            return True
        change = stats.excess_f(check["f0_hz"]) / stats.mean_f if stats.mean_f > 0 else math.nan
        if not damping and 0.0 < abs(change) <= MINIMA_SPREAD_F:
            self._accepted = {"band": stats.band, "visit": visit, "t_s": t_s, "tolerance": tolerance,
                              "f0_hz": check["f0_hz"], "change": change}
        window = check["window"]
        what = f"{r.zeta:.4f}" if damping else f"{r.f0_hz:.3f} Hz"
        whose = ("of this visit's first estimates" if of_visit(stats, kind) else
                 f"cell {window.speed_rpm:.0f} rpm, {window.load_nm:.1f} Nm was learned from")
        self.events.append(Event(
            t_s, "withheld", f"{kind} alarm withheld: the data {whose} ({when_text(window.t_s)}), refitted from "
            f"the current window solution, give {what}, {100 * r.change:+.1f} % from the current estimate, within the "
            f"{100 * tolerance:.1f} % tolerance (dead band and the comparison's noise; loss "
            f"{100 * r.loss_ratio:+.1f} % against their own solution): the estimate moved to another minimum "
            f"of the criterion, not the driveline",
            {"kind": kind, "change_pct": 100 * r.change, "tolerance_pct": 100 * tolerance,
             "loss_ratio_pct": 100 * r.loss_ratio, "reference_t_s": window.t_s}))
        return False
