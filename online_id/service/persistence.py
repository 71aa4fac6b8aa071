"""What a restart keeps of a pipeline: its state as a JSON-ready document, and its restoration."""

from __future__ import annotations


import numpy as np

from online_id.monitoring.baseline import Baseline
from online_id.monitoring.detection import ChangeDetector
from online_id.estimation.reference import ReferenceWindow
from online_id.monitoring.tracks import PoleTracker
from online_id.errors import EstimationError
from online_id.records import (
    AlertKind,
    AlertOut,
)


STATE_VERSION = 1


class PipelineState:
    """The state of a :class:`~online_id.service.pipeline.Pipeline` (a mixin: it reads and restores its parts)."""

    def get_state(self) -> dict:
        """Everything a restart must keep: estimator, learned baselines, detector (latched alarm), tracks."""
        return {"version": STATE_VERSION, "estimator": self.estimator.get_state(),
                "baseline": self.baseline.to_dict(), "detector": self.detector.to_dict(),
                "tracker": self.tracker.to_dict(), "healthy_rpm": self._healthy_rpm,
                "engaged": self.engaged.to_dict(),
                "references": {str(k): v.tolist() for k, v in self._references.items()},
                "windows": {str(k): [w.to_dict() for w in ws] for k, ws in self._windows.items()},
                "alerts": [a.__dict__ | {"kind": int(a.kind)} for a in self.alerts[-50:]]}

    def load_state(self, state: dict, new_run: bool = False) -> None:
        """Restore a state saved by :meth:`get_state`.

        ``new_run``: the state comes from an earlier run (another log, another
        day): the baselines, their reference solutions, the detector's
        statistics and latched alarms and the alerts are restored, the
        estimator and the pole tracks start afresh (their history belongs to
        the other run's time base and operating point).
        """
        if not isinstance(state, dict) or state.get("version") != STATE_VERSION:
            got = state.get("version") if isinstance(state, dict) else type(state).__name__
            raise EstimationError(f"state version {got!r} is not {STATE_VERSION}")
        if not new_run:
            self.estimator.load_state(state["estimator"])
        if "baseline" in state:
            self.baseline = Baseline.from_dict(state["baseline"])
        if "detector" in state:
            # statistics and latched alarms from the state, levels and dead bands from the config in force
            self.detector = ChangeDetector.from_dict({**state["detector"], "params": self.detector.params()})
            if new_run:
                self.detector.new_stream()
        if "tracker" in state and not new_run:
            self.tracker = PoleTracker.from_dict(state["tracker"])
        self.alerts = [AlertOut(**(a | {"kind": AlertKind(a["kind"])})) for a in state.get("alerts", [])]
        n = self.estimator.orders.n_params
        self._references = {int(k): np.asarray(v, dtype=float) for k, v in state.get("references", {}).items()
                            if isinstance(v, (list, np.ndarray)) and len(v) == n}
        windows = state.get("windows", {})
        self._windows = {}
        for k, v in windows.items() if isinstance(windows, dict) else ():
            saved = v if isinstance(v, list) and str(k).lstrip("-").isdigit() else []
            kept = [w for w in (ReferenceWindow.from_dict(x, n) for x in saved if isinstance(x, dict)) if w is not None]
            if kept:
                self._windows[int(k)] = kept
        self._rechecks = {}
        self._accepted = None
        self.engaged.load(state.get("engaged"))
        rpm = state.get("healthy_rpm")
        self._healthy_rpm = float(rpm) if isinstance(rpm, (int, float)) and not new_run else None
