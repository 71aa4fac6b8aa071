"""Evaluation of the generic diagnosis on randomised multi-shaft rigs.

Each case simulates a rig (:mod:`online_id.bench.rig`: 2-3 gear stages,
two recorders on drifting clocks, encoder angles, jitter), puts the records
through the same path as ``online-id diagnose --second-file``
(:func:`online_id.diagnose.layouts.assemble`: resampling, clocks estimated where they
plainly differ, shafts from angles, torsion, decimation) and diagnoses the motor
speed from the torque demand.  True effects: a rotation-order disturbance on
each shaft in turn, at an order that is identifiable (no faster shaft turns
at an integer fraction of it, see :func:`identifiable_orders`); clean rigs
measure the false-effect rate.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from concurrent.futures import ProcessPoolExecutor
from dataclasses import replace
from pathlib import Path

import numpy as np

from online_id.bench.rig import OrderDisturbance, RigSpec, random_rig, simulate_rig
from online_id.diagnose import DiagnoseData, diagnose
from online_id.diagnose.align import resample_uniform
from online_id.diagnose.residual_tests import RIG_LINE_RATIO, RIG_SPLIT_RATIO
from online_id.diagnose.layouts import Column, Layout, ShaftColumn, assemble
from online_id.io.jsonout import dumps

SAMPLE_RATE_HZ = 200.0
SIM_HORIZON_S = 0.1  # the load loop's set point is unmeasured: longer simulations judge it, not the model
ORDERS_TO_DRAW = (1, 2, 3, 4, 5)
NC = 8  # noise model: the encoder-derived speed's noise is far from white


def identifiable_orders(spec: RigSpec, shaft: int) -> list[int]:
    """Orders ``k`` of shaft ``shaft`` that are not an integer order of a faster shaft.

    A line at order ``k`` of shaft ``s`` is order ``k f_s / f_j`` of a faster
    shaft ``j``; when that is an integer the line is, by the smallest-order
    rule, the faster shaft's, and the data cannot say otherwise.
    """
    f = spec.speed_factors()
    out = []
    for k in ORDERS_TO_DRAW:
        if all(abs(k * f[shaft] / f[j] - round(k * f[shaft] / f[j])) > 1e-6 for j in range(shaft)):
            out.append(k)
    return out


def rig_spec(seed: int, shaft: int | None, magnitude: float, order: int | None = None) -> RigSpec:
    """The randomised rig of one case; ``shaft=None`` is a clean rig.

    ``magnitude`` scales the disturbance torque against the PRBS torque
    reflected to that shaft (``torque_prbs * prod(ratios up to it)``);
    ``order`` overrides the order drawn (the rest of the case is unchanged).
    """
    rng = np.random.default_rng(seed)
    spec = random_rig(rng)
    if shaft is None:
        return spec
    shaft = min(shaft, spec.n_shafts - 1)
    drawn = int(rng.choice(identifiable_orders(spec, shaft)))
    order = drawn if order is None else int(order)
    reflect = 1.0 / spec.speed_factors()[shaft]
    dist = OrderDisturbance(shaft, float(order), magnitude * spec.torque_prbs_nm * reflect,
                            float(rng.uniform(0, 2 * np.pi)))
    return replace(spec, disturbance=dist)


def rig_layout(spec: RigSpec, clock: str = "auto") -> Layout:
    """The layout a user would give ``online-id diagnose`` for this rig's two files (angles, no ratios,
    the clocks estimated where they plainly differ): what :func:`online_id.diagnose.layouts.assemble` reads."""
    shafts = tuple(ShaftColumn(n, "angle", Column(0 if i == 0 else 1, f"{n}_angle_{spec.angle_suffix}"),
                               1.0 / spec.angle_scale, spec.angle_suffix) for i, n in enumerate(spec.names))
    return Layout(Column(0, "torque_demand_nm"), shafts[0].column, shafts, differentiate_output=True,
                  clock=clock, sample_rate_hz=SAMPLE_RATE_HZ)


def rig_data(spec: RigSpec, seed: int, clock: str = "auto") -> DiagnoseData:
    """Simulate the rig and read its two records as ``online-id diagnose --second-file`` does."""
    rec = simulate_rig(spec, seed)
    drive, sensor = dict(rec.drive), dict(rec.sensor)
    r1 = resample_uniform(drive.pop("time_s"), drive, "drive", "time_s")
    r2 = resample_uniform(sensor.pop("time_s"), sensor, "sensor", "time_s")
    return assemble([r1, r2], rig_layout(spec, clock), ["drive", "sensor"])


def run_case(seed: int, shaft: int | None, magnitude: float, na: int | None = None, nb: int | None = None,
             nc: int = NC, max_effects: int = 2, plateau_s: float | None = None, order: int | None = None) -> dict:
    """Simulate, assemble, diagnose and score one case (``plateau_s`` shortens the plateaus and ``order``
    sets the disturbance's order, for tests)."""
    t0 = time.perf_counter()
    spec = rig_spec(seed, shaft, magnitude, order)
    if plateau_s is not None:
        spec = replace(spec, plateau_s=float(plateau_s))
    data = rig_data(spec, seed)
    d = diagnose(data, na=na, nb=nb, nc=nc, nk=1, max_effects=max_effects, sim_horizon_s=SIM_HORIZON_S)
    clock = data.notes["clock"]
    truth = spec.disturbance
    first = d.effects[0] if d.effects else None
    rig_test = next((t for t in d.tests_before if t.name.startswith("rotation orders")), None)
    out = {"seed": seed, "ratios": list(spec.ratios), "names": list(spec.names),
           "true_kind": "clean" if truth is None else "rotation_order_disturbance",
           "true_shaft": None if truth is None else spec.names[truth.shaft],
           "true_order": None if truth is None else truth.order, "magnitude": magnitude,
           "found_kind": first.kind if first else "clean",
           "found_shaft": first.params.get("shaft") if first else None,
           "found_order": first.params.get("order") if first else None,
           "effects": [e.as_dict() for e in d.effects],
           "rms_before": d.error_before.rms, "rms_after": d.error_after.rms,
           "fit_before": d.error_before.fit_pct, "fit_after": d.error_after.fit_pct,
           "offset_true_s": spec.clock_offset_s, "offset_est_s": clock["offset_s"],
           "drift_true_ppm": spec.clock_drift_ppm, "drift_est_ppm": clock["drift_ppm"],
           "clock_mode": clock["mode"], "torsion": data.notes["layout"]["torsion"],
           "max_line_ratio": rig_test.curve.get("max_ratio", 0.0) if rig_test else None,
           "max_split_ratio": rig_test.curve.get("max_split_ratio", 0.0) if rig_test else None,
           "baseline": [d.baseline.na, d.baseline.nb + d.baseline.delay, d.baseline.nc],
           "candidates": [{k: v for k, v in c.__dict__.items() if k != "params"} | {"params": c.params}
                          for c in d.candidates],
           "warnings": d.warnings, "seconds": time.perf_counter() - t0}
    out["found_in_any_step"] = truth is not None and any(
        e["kind"] == "rotation_order_disturbance" and e["params"].get("shaft") == out["true_shaft"]
        and e["params"].get("order") == truth.order for e in out["effects"])
    out["wrong_shaft_or_order"] = truth is not None and any(
        e["kind"] == "rotation_order_disturbance" and (e["params"].get("shaft") != out["true_shaft"]
                                                       or e["params"].get("order") != truth.order)
        for e in out["effects"])
    out["order_exact"] = truth is not None and out["found_order"] == truth.order
    out["shaft_right"] = truth is not None and out["found_shaft"] == out["true_shaft"]
    return out


def _task(args: tuple) -> dict:
    """``run_case(*args)``; a case whose simulation or diagnosis raised is a failed case (named
    ``error``, never clean), and the run goes on."""
    try:
        return run_case(*args)
    except Exception as err:  # noqa: BLE001 - recorded as a failed case
        return failed_case(args[0], args[1], args[2], f"{type(err).__name__}: {err}")


def failed_case(seed: int, shaft: int | None, magnitude: float, message: str) -> dict:
    """The row of a case that raised: every rate counts it as wrong."""
    spec = rig_spec(seed, shaft, magnitude)
    truth = spec.disturbance
    return {"seed": seed, "ratios": list(spec.ratios), "names": list(spec.names),
            "true_kind": "clean" if truth is None else "rotation_order_disturbance",
            "true_shaft": None if truth is None else spec.names[truth.shaft],
            "true_order": None if truth is None else truth.order, "magnitude": magnitude,
            "found_kind": "error", "found_shaft": None, "found_order": None, "effects": [],
            "rms_before": None, "rms_after": None, "error": message, "found_in_any_step": False,
            "wrong_shaft_or_order": False, "order_exact": False, "shaft_right": False,
            "max_line_ratio": None, "max_split_ratio": None, "seconds": 0.0}


def _run_all(tasks: list[tuple], jobs: int, progress: Callable[[int, int, dict], None] | None = None) -> list[dict]:
    """``_task`` of every task, in order, on ``jobs`` processes (in this one when ``jobs`` is 1);
    ``progress(done, total, case)`` after each."""
    out: list[dict] = []

    def done(r: dict) -> None:
        out.append(r)
        if progress is not None:
            progress(len(out), len(tasks), r)

    if jobs > 1:
        with ProcessPoolExecutor(jobs) as pool:
            for r in pool.map(_task, tasks):
                done(r)
    else:
        for t in tasks:
            done(_task(t))
    return out


def evaluate(cases: int, seed: int, magnitude: float, jobs: int = 1, out: Path | None = None,
             progress: Callable[[int, int, dict], None] | None = None) -> dict:
    """``cases`` clean rigs and ``cases`` rigs per disturbed shaft position (motor, second, last)."""
    tasks = []
    for i in range(cases):
        s = seed + i
        tasks.append((s, None, magnitude))
        for shaft in range(rig_spec(s, None, magnitude).n_shafts):
            tasks.append((s, shaft, magnitude))
    rows = [r for r in _run_all(tasks, jobs, progress) if r["true_kind"] == "clean" or r["true_shaft"] is not None]
    # shaft index 3 on a 3-shaft rig is the load again: keep each (seed, shaft) once
    seen, uniq = set(), []
    for r in rows:
        key = (r["seed"], r["true_shaft"])
        if key not in seen:
            seen.add(key)
            uniq.append(r)
    summary = summarise(uniq)
    if out is not None:
        out.mkdir(parents=True, exist_ok=True)
        (out / "rig-evaluation.json").write_text(dumps({"summary": summary, "cases": uniq}, indent=1) + "\n", encoding="utf-8")
    return summary


def calibrate(cases: int, seed: int, jobs: int = 1, out: Path | None = None,
              progress: Callable[[int, int, dict], None] | None = None) -> dict:
    """Largest line ratio on the order grid of the baseline residual of ``cases`` clean rigs.

    The rig line test (:data:`online_id.diagnose.residual_tests.RIG_LINE_RATIO`) is set above the
    95th percentile of these maxima (no effect is fitted: ``max_effects=0``).  Use seeds apart from the
    evaluation's.
    """
    rows = _run_all([(seed + i, None, 0.0, None, None, NC, 0) for i in range(cases)], jobs, progress)
    r = np.array([x["max_line_ratio"] for x in rows if x["max_line_ratio"] is not None], dtype=float)
    r2 = np.array([x["max_split_ratio"] for x in rows if x["max_split_ratio"] is not None], dtype=float)

    def dist(x: np.ndarray) -> dict:
        return {"median": float(np.median(x)), "p95": float(np.percentile(x, 95)), "max": float(np.max(x))}

    summary = {"clean_rigs": len(rows), "seeds": [seed, seed + cases - 1],
               "max_line_ratio": dist(r), "max_split_ratio": dist(r2),
               "thresholds_in_use": {"line": RIG_LINE_RATIO, "both_parts": RIG_SPLIT_RATIO},
               "clean_over_threshold_pct": 100.0 * float(np.mean((r >= RIG_LINE_RATIO) | (r2 >= RIG_SPLIT_RATIO))),
               "seconds_per_case": float(np.mean([x["seconds"] for x in rows]))}
    if out is not None:
        out.mkdir(parents=True, exist_ok=True)
        (out / "rig-calibration.json").write_text(dumps({"summary": summary, "max_line_ratio": r.tolist(),
                                                              "max_split_ratio": r2.tolist()},
                                                             indent=1) + "\n", encoding="utf-8")
    return summary


def summarise(rows: list[dict]) -> dict:
    clean = [r for r in rows if r["true_kind"] == "clean"]
    dist = [r for r in rows if r["true_kind"] != "clean"]
    by_pos: dict[str, list[dict]] = {}
    for r in dist:
        pos = "motor" if r["true_shaft"] == r["names"][0] else ("load" if r["true_shaft"] == r["names"][-1]
                                                                 else "intermediate")
        by_pos.setdefault(pos, []).append(r)

    def rates(rs: list[dict]) -> dict:
        n = max(len(rs), 1)
        return {"cases": len(rs),
                "named_first_pct": 100.0 * sum(r["found_kind"] == r["true_kind"] for r in rs) / n,
                "first_exact_pct": 100.0 * sum(r["found_kind"] == r["true_kind"] and r["order_exact"]
                                               and r["shaft_right"] for r in rs) / n,
                "steps_improve_both_pct": 100.0 * sum(all(
                    e["error_after"]["rms"] < e["error_before"]["rms"]
                    and e["error_after"]["fit_pct"] > e["error_before"]["fit_pct"] for e in r["effects"])
                    for r in rs) / n,
                "order_exact_pct": 100.0 * sum(r["order_exact"] for r in rs) / n,
                "shaft_right_pct": 100.0 * sum(r["shaft_right"] for r in rs) / n,
                "found_in_any_step_pct": 100.0 * sum(r["found_in_any_step"] for r in rs) / n,
                "wrong_shaft_or_order_pct": 100.0 * sum(r["wrong_shaft_or_order"] for r in rs) / n,
                "error_lower_pct": 100.0 * sum(r["rms_after"] is not None and r["rms_after"] < r["rms_before"]
                                               for r in rs) / n,
                "failed": sum(r["found_kind"] == "error" for r in rs)}

    ran = [r for r in rows if r["found_kind"] != "error"] or [{"offset_est_s": 0.0, "offset_true_s": 0.0,
                                                               "drift_est_ppm": 0.0, "drift_true_ppm": 0.0}]
    off = [abs(r["offset_est_s"] - r["offset_true_s"]) for r in ran]
    drift = [abs(r["drift_est_ppm"] - r["drift_true_ppm"]) for r in ran]
    return {"rotation_order": rates(dist), "by_position": {k: rates(v) for k, v in sorted(by_pos.items())},
            "clean": {"cases": len(clean),
                      "false_effect_pct": 100.0 * sum(r["found_kind"] != "clean" for r in clean) / max(len(clean), 1)},
            "failed_cases": sum(r["found_kind"] == "error" for r in rows),
            "all_cases": {"cases": len(rows), "right_first_pct": 100.0 * sum(
                r["found_kind"] == r["true_kind"] and (r["true_kind"] == "clean" or r["order_exact"] and r["shaft_right"])
                for r in rows) / max(len(rows), 1)},
            "clock": {"estimated_pct": 100.0 * sum(r.get("clock_mode", "estimated") == "estimated" for r in rows)
                      / max(len(rows), 1),
                      "offset_err_max_ms": 1e3 * max(off), "offset_err_median_ms": 1e3 * float(np.median(off)),
                      "drift_err_max_ppm": max(drift), "drift_err_median_ppm": float(np.median(drift))},
            "seconds_per_case": float(np.mean([r["seconds"] for r in rows]))}
