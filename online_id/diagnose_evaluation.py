"""Evaluation of the bench diagnosis on randomised benches, with calibrated thresholds.

Each case (:mod:`online_id.bench.diagnose_cases`) is simulated, passed
through the causal data path and diagnosed once; the best candidate of every
kind (gain, t, parameters) is kept, so that acceptance can be re-applied with
any thresholds.  Thresholds are calibrated on *clean* benches with seeds
apart from the test seeds: for each kind, the largest gain that a
significant (``t >= T_CRIT``) candidate reached on a clean calibration
bench, times ``MARGIN``.  The test cases are then classified with them:
the kind named first is the accepted candidate with the largest
``gain / threshold`` (``clean`` when none is accepted).

It lives above ``bench`` and ``diagnose`` (the simulator and the diagnosis
may not import each other).
"""

from __future__ import annotations

import json
import math
import time
from collections.abc import Callable
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path
from typing import Any

import numpy as np

from online_id.bench.diagnose_cases import KINDS, make_case
from online_id.bench.simulate import simulate_bench

MARGIN = 1.1
MIN_THRESHOLD = 0.005
# the sensor delay's score is its size in ms: clean benches show up to about 0.5 ms of bias
MIN_THRESHOLDS = {"sensor_delay": 0.5}
CALIBRATION_SEED0 = 100_000
SMALLEST_DECILE = 0.1
PLATEAU_S = (12.0, 15.0)


def run_case(args: tuple[str, int]) -> dict[str, Any]:
    """Simulate and diagnose one case; the best candidate of each kind."""
    from online_id.diagnose.bench_data import prepare
    from online_id.diagnose.bench_diagnosis import diagnose_bench

    kind, seed = args
    case = make_case(kind, seed, plateau_s=PLATEAU_S)
    t0 = time.perf_counter()
    rec = simulate_bench(case.scenario)
    d = rec.to_data(case.case_id)
    out: dict[str, Any] = {"case": case.case_id, "kind": kind, "seed": seed,
                           "magnitude": case.magnitude, "truth": _plain(case.truth)}
    try:
        series = prepare(d.time_s, d.dyno_torque_nm, d.dyno_speed_rad_s, d.engine_speed_rad_s,
                         source=case.case_id, pulses_per_rev=case.scenario.n_cyl / 2.0,
                         demand_nm=rec.test_torque_nm)
        result = diagnose_bench(series, max_effects=1)
    except Exception as err:  # noqa: BLE001 - recorded as a failed case, the run goes on
        out.update(error=f"{type(err).__name__}: {err}", best={}, seconds=time.perf_counter() - t0)
        return out
    best: dict[str, dict] = {}
    for c in result.candidates[0]:
        if c.kind not in best or c.gain > best[c.kind]["gain"]:
            best[c.kind] = {"gain": c.gain, "t": c.t_stat, "params": _plain(c.params)}
    out.update(best=best, seconds=time.perf_counter() - t0,
               n_plateaus=len(series.plateaus), rms_before=result.errors(result.baseline))
    return out


def _plain(x: Any) -> Any:
    if isinstance(x, dict):
        return {str(k): _plain(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_plain(v) for v in x]
    if isinstance(x, (np.floating, np.integer)):
        return x.item()
    return x


def run_cases(jobs: list[tuple[str, int]], workers: int,
              progress: Callable[[int, int, dict], None] | None = None) -> list[dict]:
    """Run cases on ``workers`` processes (1 = in this process), in order."""
    out = []
    if workers <= 1:
        for i, j in enumerate(jobs):
            out.append(run_case(j))
            if progress:
                progress(i + 1, len(jobs), out[-1])
        return out
    with ProcessPoolExecutor(max_workers=workers) as pool:
        for i, r in enumerate(pool.map(run_case, jobs)):
            out.append(r)
            if progress:
                progress(i + 1, len(jobs), r)
    return out


def calibrate(clean: list[dict]) -> dict[str, float]:
    """Per-kind thresholds from clean calibration benches (see module notes)."""
    from online_id.diagnose.bench_diagnosis import T_CRIT, THRESHOLDS

    thr = {}
    for kind in THRESHOLDS:
        gains = [r["best"][kind]["gain"] for r in clean
                 if kind in r.get("best", {}) and r["best"][kind]["t"] >= T_CRIT]
        thr[kind] = max(MIN_THRESHOLDS.get(kind, MIN_THRESHOLD), MARGIN * max(gains, default=0.0))
    return thr


def classify(result: dict, thresholds: dict[str, float]) -> tuple[str, dict | None]:
    """The kind named first (``clean`` = no significant effect) and its candidate."""
    from online_id.diagnose.bench_diagnosis import T_CRIT

    ok = [(c["gain"] / thresholds[k], k, c) for k, c in result.get("best", {}).items()
          if c["gain"] >= thresholds[k] and c["t"] >= T_CRIT]
    if not ok:
        return "clean", None
    _, kind, cand = max(ok, key=lambda x: x[0])
    return kind, cand


def parameter_check(kind: str, truth: dict, cand: dict | None) -> dict[str, Any]:
    """Whether the named effect's parameters match the truth (kind named right only)."""
    if cand is None or truth["kind"] != kind:
        return {}
    p = cand["params"]
    if kind == "rotation_order_disturbance":
        return {"order_exact": p["order"] == truth["order"], "shaft_right": p["shaft"] == truth["shaft"]}
    if kind in ("fixed_frequency_disturbance", "additional_mode"):
        err = abs(p["freq_hz"] - truth["freq_hz"]) / truth["freq_hz"]
        return {"freq_err_pct": 100 * err, "freq_within_2pct": err <= 0.02}
    if kind == "sensor_delay":
        err = abs(p["delay_s"] - truth["delay_s"])
        return {"delay_err_ms": 1000 * err, "delay_within_1ms": err <= 1e-3,
                "signal_right": p["signal"] == truth["signal"]}
    if kind == "backlash":
        return {"gap_err_pct": 100 * (p["gap_rad"] - truth["gap_rad"]) / truth["gap_rad"]}
    return {}


def summarise(results: list[dict], thresholds: dict[str, float]) -> dict[str, Any]:
    """Confusion matrix, right-kind rates, parameter figures and the clean false-effect rate."""
    labels = list(KINDS)
    conf = np.zeros((len(labels), len(labels)), dtype=int)
    rows = []
    for r in results:
        named, cand = classify(r, thresholds)
        checks = parameter_check(named, r["truth"], cand)
        # held-out one-step gain (the delay's score is its size in ms, its held-out gain a parameter)
        gain = cand["params"].get("heldout_gain", cand["gain"]) if cand else 0.0
        rows.append({"case": r["case"], "kind": r["kind"], "named": named, "magnitude": r["magnitude"],
                     "gain": gain, **checks, "error": r.get("error")})
        conf[labels.index(r["kind"]), labels.index(named)] += 1

    def rate(sel: list[dict], key: str) -> float | None:
        vals = [x[key] for x in sel if key in x]
        return float(np.mean(vals)) if vals else None

    per_kind = {}
    for kind in labels:
        sel = [x for x in rows if x["kind"] == kind]
        big = [x for x in sel if x["magnitude"] >= SMALLEST_DECILE or kind == "clean"]
        right = [x for x in big if x["named"] == kind]
        per_kind[kind] = {
            "n": len(sel), "n_above_decile": len(big),
            "right_first_pct": 100 * len(right) / len(big) if big else None,
            "right_first_all_pct": 100 * sum(x["named"] == kind for x in sel) / len(sel) if sel else None,
            "error_lower_pct": (100 * sum(x["gain"] > 0 for x in big if x["named"] != "clean") / len(big)
                                if big and kind != "clean" else None),
            **{k: rate(right, k) for k in ("order_exact", "shaft_right", "freq_within_2pct",
                                           "delay_within_1ms", "signal_right")},
            "median_freq_err_pct": _median(right, "freq_err_pct"),
            "median_delay_err_ms": _median(right, "delay_err_ms"),
            "median_gap_err_pct": _median(right, "gap_err_pct"),
        }
    effect = [x for x in rows if x["kind"] != "clean" and x["magnitude"] >= SMALLEST_DECILE]
    clean = [x for x in rows if x["kind"] == "clean"]
    return {
        "labels": labels, "confusion": conf.tolist(), "per_kind": per_kind,
        "overall_right_first_pct": 100 * float(np.mean([x["named"] == x["kind"] for x in effect])) if effect else None,
        "false_effect_clean_pct": 100 * float(np.mean([x["named"] != "clean" for x in clean])) if clean else None,
        "error_lower_pct": 100 * float(np.mean([x["gain"] > 0 and x["named"] != "clean" for x in effect])) if effect else None,
        "thresholds": thresholds, "cases": rows,
    }


def _median(rows: list[dict], key: str) -> float | None:
    vals = [abs(x[key]) for x in rows if key in x and x[key] is not None and math.isfinite(x[key])]
    return float(np.median(vals)) if vals else None


def table(summary: dict) -> str:
    """Markdown table of the per-kind figures."""
    def f(x: Any, fmt: str = "{:.0f}") -> str:
        return "-" if x is None else fmt.format(x * 100 if isinstance(x, float) and fmt == "{:.0%}" else x)

    lines = ["| true kind | cases (above smallest decile) | right kind first % | held-out error lower % | "
             "parameters |", "|---|---|---|---|---|"]
    for kind, s in summary["per_kind"].items():
        par = []
        if s["order_exact"] is not None:
            par.append(f"order exact {100 * s['order_exact']:.0f} %, shaft right {100 * s['shaft_right']:.0f} %")
        if s["freq_within_2pct"] is not None:
            par.append(f"freq within 2 % {100 * s['freq_within_2pct']:.0f} % (median {s['median_freq_err_pct']:.2f} %)")
        if s["delay_within_1ms"] is not None:
            par.append(f"delay within 1 ms {100 * s['delay_within_1ms']:.0f} %, signal right "
                       f"{100 * s['signal_right']:.0f} % (median {s['median_delay_err_ms']:.2f} ms)")
        if s["median_gap_err_pct"] is not None:
            par.append(f"gap error median {s['median_gap_err_pct']:.0f} %")
        lines.append(f"| {kind} | {s['n']} ({s['n_above_decile']}) | {f(s['right_first_pct'])} | "
                     f"{f(s['error_lower_pct'])} | {'; '.join(par)} |")
    lines += ["", f"overall right kind first (effects above the smallest decile): "
              f"{f(summary['overall_right_first_pct'], '{:.1f}')} %",
              f"held-out error lower (same cases): {f(summary['error_lower_pct'], '{:.1f}')} %",
              f"clean benches reporting an effect: {f(summary['false_effect_clean_pct'], '{:.1f}')} %"]
    return "\n".join(lines)


def plot_confusion(summary: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    conf = np.array(summary["confusion"], dtype=float)
    labels = [lab.replace("_disturbance", "").replace("_", " ") for lab in summary["labels"]]
    norm = conf / np.maximum(conf.sum(axis=1, keepdims=True), 1)
    fig, ax = plt.subplots(figsize=(7.5, 6.5))
    ax.imshow(norm, cmap="Blues", vmin=0, vmax=1)
    for i in range(conf.shape[0]):
        for j in range(conf.shape[1]):
            if conf[i, j]:
                ax.text(j, i, f"{int(conf[i, j])}", ha="center", va="center",
                        color="white" if norm[i, j] > 0.5 else "black")
    ax.set_xticks(range(len(labels)), labels, rotation=40, ha="right")
    ax.set_yticks(range(len(labels)), labels)
    ax.set_xlabel("named first (clean = no significant effect)")
    ax.set_ylabel("true effect")
    ax.set_title("online-id diagnose on randomised benches")
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def write_outputs(out: Path, summary: dict, calibration: list[dict], results: list[dict]) -> list[Path]:
    out.mkdir(parents=True, exist_ok=True)
    files = [out / "diagnose_evaluation.json", out / "confusion.png", out / "diagnose_evaluation.md"]
    doc = {"summary": summary, "calibration_cases": calibration, "test_cases": results}
    files[0].write_text(json.dumps(doc, indent=1, default=float) + "\n", encoding="utf-8")
    plot_confusion(summary, files[1])
    files[2].write_text(table(summary) + "\n", encoding="utf-8")
    return files
