"""What a run of the pipeline gives: the final estimate with its shaft parameters and quality, the state, the
alarms and baselines, the backlash tests, the pole tracks, the history of states and alerts, and the counters (the
document ``replay --json`` prints)."""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

import numpy as np

from online_id.errors import EstimationError

if TYPE_CHECKING:
    from online_id.service.pipeline import Pipeline


def run_summary(pipe: Pipeline) -> dict:
    """The final estimate of ``pipe`` and the history of its states and alerts (times from the stream start)."""
    est = pipe.last_estimate or pipe.estimator.estimate()
    inert = pipe.settings.inertias
    phys = None
    if np.isfinite(est.f0_hz):
        try:
            phys = pipe.estimator.physical(est, inert.J1, inert.J2, inert.J_total)
        except (EstimationError, FloatingPointError, ValueError):
            phys = None
    t0 = pipe.t_first or 0.0

    def fin(x):
        return float(x) if x is not None and math.isfinite(x) else None

    c = pipe.counters
    policy = pipe.policy
    return {
        "driveline": {
            "f0_hz": fin(est.f0_hz),
            "zeta": fin(est.zeta),
            "c_s": fin(phys.c_s) if phys else None,
            "d_s": fin(phys.d_s) if phys else None,
            "J1": fin(phys.J1) if phys else None,
            "J2": fin(phys.J2) if phys else None,
            "valid": bool(est.valid),
        },
        "quality": {"residual_rms": fin(est.residual_rms), "fpe": fin(est.fpe),
                    "excitation_nm": fin(est.excitation_nm), "samples_used": est.samples_used},
        "state": pipe.state.name,
        "active_alarm": pipe.detector.active.as_dict() if pipe.detector.active else None,
        "withheld_alarms": dict(pipe.detector.withheld),
        "baseline": [b.as_dict() for b in pipe.baseline.bands],
        "baseline_not_learned": policy.rejected,  # learning estimates that disagreed with the baselines
        "baseline_notes": [{"t_s": e.t_s - t0, "kind": e.kind, "message": e.message} for e in pipe.events
                           if e.kind in ("learned", "not_learned", "wide_baseline", "backlash")][-20:],
        "backlash": {"shown": pipe.baseline.backlash, "tests": policy.backlash_tests,
                     "last_test": policy.last_backlash_test.as_dict() if policy.last_backlash_test else None,
                     "engaged_flank": pipe.engaged.summary()},
        "tracks": [{"id": t.id, "f_hz": t.f_hz, "zeta": t.zeta, "class": t.cls, "confidence": t.confidence,
                    "order": t.order} for t in pipe.tracker.tracks],
        "status_changes": [{"t_s": e.t_s - t0, "state": e.data["state"], "why": e.message}
                           for e in pipe.events if e.kind == "state"],
        "alerts": [{"t_s": a.t_s - t0, "kind": a.kind.name, "severity": a.severity, "message": a.message}
                   for a in pipe.alerts],
        "counters": {
            "samples": c.samples, "gaps": c.gaps, "timeouts": c.timeouts, "time_jumps": c.time_jumps,
            "bad_frames": c.bad_frames, "missing_frames": c.missing_frames,
            "dropped_frames": pipe.dropped_frames,
            **{f"frames_{k.name.lower()}": v for k, v in c.faults.items()},
        },
    }

