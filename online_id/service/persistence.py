"""What a restart keeps of a pipeline: its state as a JSON-ready document, and its restoration.

The document holds the estimator's state, the detection policy's items
(:meth:`~online_id.service.policy.DetectionPolicy.to_dict`: baselines,
detector, tracks, engaged flank, reference solutions and windows) and the
last alerts, under a version number::

    {"version": 1, "estimator": {...}, "baseline": {...}, "detector": {...}, "tracker": {...},
     "healthy_rpm": ..., "engaged": {...}, "references": {...}, "windows": {...}, "alerts": [...]}
"""

from __future__ import annotations

from online_id.errors import EstimationError
from online_id.estimation.online import OnlineDriveline
from online_id.records import AlertKind, AlertOut
from online_id.service.policy import DetectionPolicy

STATE_VERSION = 1
KEPT_ALERTS = 50  # the alerts a state keeps (the latest)


def state_document(estimator: OnlineDriveline, policy: DetectionPolicy, alerts: list[AlertOut]) -> dict:
    """Everything a restart must keep: estimator, learned baselines, detector (latched alarm), tracks, alerts."""
    return {"version": STATE_VERSION, "estimator": estimator.get_state(), **policy.to_dict(),
            "alerts": [a.__dict__ | {"kind": int(a.kind)} for a in alerts[-KEPT_ALERTS:]]}


def restore_state(state: dict, estimator: OnlineDriveline, policy: DetectionPolicy,
                  new_run: bool = False) -> list[AlertOut]:
    """Restore a document of :func:`state_document` into ``estimator`` and ``policy``: its alerts.

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
        estimator.load_state(state["estimator"])
    alerts = [AlertOut(**(a | {"kind": AlertKind(a["kind"])})) for a in state.get("alerts", [])]
    policy.load(state, estimator.orders.n_params, new_run)
    return alerts
