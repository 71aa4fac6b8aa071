"""Evaluation of the bench diagnosis on randomised benches, with calibrated thresholds.

Each case (:mod:`online_id.bench.diagnose_cases`) is simulated and written
as the bench CSV ``online-id simulate --with-demand`` writes (time, both
speeds, dyno torque and the test-torque demand); the CSV is read back and prepared by
:func:`online_id.ingest.bench_series.bench_series`, the same reader and
arguments as ``online-id diagnose bench.csv``, and diagnosed twice:

- ``no_demand``: torque and both speeds only (the demand column ignored),
  what a bench CSV or a CAN log of the bench gives a user;
- ``demand``: with the recorded test-torque demand as the reference.

The best candidate of every kind (gain, t, parameters) is kept per path, so
that acceptance can be re-applied with any thresholds.  Thresholds are
calibrated per path on *clean* benches with seeds apart from the test
seeds: for each kind, the largest gain that a significant (``t >=
T_CRIT``) candidate reached on a clean calibration bench, times
``MARGIN``.  The test cases are then classified with them: the kind named
first is the accepted candidate with the largest ``gain / threshold``
(``clean`` when none is accepted), as :func:`diagnose_bench` names it.

It lives above ``bench``, ``diagnose`` and ``cli`` (the simulator and the
diagnosis may not import each other).
"""

from __future__ import annotations

import math
import tempfile
import time
from collections.abc import Callable
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path
from typing import Any

import numpy as np

from online_id.bench.diagnose_cases import KINDS, make_case, twist_passages
from online_id.bench.simulate import simulate_bench
from online_id.io.jsonout import dumps, plain

PATHS = ("no_demand", "demand")
MARGIN = 1.1
MIN_THRESHOLD = 0.005
MIN_THRESHOLDS: dict[str, float] = {}  # per kind where the floor differs from MIN_THRESHOLD
CALIBRATION_SEED0 = 100_000
SMALLEST_DECILE = 0.1
Z95 = 1.96
FAILED = "error"  # what a case whose diagnosis raised is named: a failure, never "clean"


def _job(args: tuple) -> tuple[str, int, str, tuple[str, ...]]:
    """A case's job ``(kind, seed[, family[, paths]])`` with its defaults: (kind, seed, family, paths)."""
    kind, seed = args[:2]
    return kind, seed, args[2] if len(args) > 2 else "bench", tuple(args[3]) if len(args) > 3 else PATHS


def _head(case, kind: str, seed: int, family: str, truth: dict) -> dict[str, Any]:
    """The head of a case's record: the case, its kind, seed, family, magnitude and ``truth``."""
    return {"case": case.case_id, "kind": kind, "seed": seed, "family": family, "magnitude": case.magnitude,
            "truth": plain(truth)}


def run_case(args: tuple) -> dict[str, Any]:
    """Simulate one case ``(kind, seed[, family[, paths]])``, write it as a bench CSV, diagnose it on the
    paths (default both)."""
    from online_id.ingest.bench_series import bench_series
    from online_id.offline.bench_files import write_csv
    from online_id.config import load_config
    from online_id.diagnose.bench_diagnosis import T_CRIT, diagnose_bench

    kind, seed, family, paths = _job(args)
    case = make_case(kind, seed, family=family)
    t0 = time.perf_counter()
    rec = simulate_bench(case.scenario)
    truth = dict(case.truth)
    if kind == "backlash":
        truth.update(twist_passages(case.scenario))
    out = _head(case, kind, seed, family, truth)
    settings = load_config(None)
    with tempfile.TemporaryDirectory(prefix="online-id-eval-") as tmp:
        csv = Path(tmp) / f"{case.case_id}.csv"
        write_csv(rec, csv, demand=True)
        for path in paths:
            t1 = time.perf_counter()
            try:
                series = bench_series(csv, settings, pulses_per_rev=case.scenario.n_cyl / 2.0,
                                      use_demand=path == "demand")
                result = diagnose_bench(series, max_effects=1)
            except Exception as err:  # noqa: BLE001 - recorded as a failed case, the run goes on
                out[path] = {"error": f"{type(err).__name__}: {err}", "best": {},
                             "seconds": time.perf_counter() - t1}
                continue
            best: dict[str, tuple] = {}
            for c in result.candidates[0]:
                if c.kind not in best or c.gain > best[c.kind][0].gain:
                    best[c.kind] = (c, {"gain": c.gain, "t": c.t_stat, "params": plain(c.params)})
            for c, doc in best.values():  # what re-applied thresholds may accept: its summary decides too
                if c.t_stat >= T_CRIT and hasattr(result, "summary_with"):  # (not in a diagnosis before it)
                    doc["summary_after"] = result.summary_with(c)
            out[path] = {"best": {k: doc for k, (_, doc) in best.items()}, "seconds": time.perf_counter() - t1,
                         "n_plateaus": len(series.plateaus), "demand": series.demand is not None}
    out["seconds"] = time.perf_counter() - t0
    return out


def path_result(result: dict, path: str) -> dict:
    """The diagnosis of ``result`` on ``path`` (``best``, ``error``, ...)."""
    return result.get(path, {"best": {}, "error": f"no {path} diagnosis in this case"})


def run_cases(jobs: list[tuple[str, int]], workers: int,
              progress: Callable[[int, int, dict], None] | None = None, *, dask: bool = False,
              scheduler: str | None = None) -> list[dict]:
    """Run cases on ``workers`` processes (1 = in this process), in order; with ``dask`` as tasks on a local
    Dask cluster of ``workers`` processes, with ``scheduler`` on that scheduler's workers. A task that fails on
    the cluster (its worker lost, the case raised outside the diagnosis) is a failed case (``error`` on every
    path), never left out."""
    out = []
    if dask or scheduler:
        from online_id.archive.runner import cluster, map_tasks

        done = 0

        def record(o) -> None:
            nonlocal done
            done += 1
            if progress:
                progress(done, len(jobs), o.value if o.ok else failed_case(jobs[o.index], o.error or "task lost"))

        with cluster(scheduler, workers) as client:
            outcomes = map_tasks(client, run_case, jobs, label="evaluate-diagnose", on_done=record, quiet=True)
        return [o.value if o.ok else failed_case(jobs[o.index], o.error or "the task was lost (its worker died)")
                for o in outcomes]
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


def failed_case(job: tuple, error: str) -> dict[str, Any]:
    """The record of case ``job`` that gave no result: a failure on every path it was to run."""
    kind, seed, family, paths = _job(job)
    try:
        case = make_case(kind, seed, family=family)
        out = _head(case, kind, seed, family, dict(case.truth))
    except Exception as err:  # noqa: BLE001 - the case cannot even be made: still a failed case
        out = {"case": f"{kind}-{seed}", "kind": kind, "seed": seed, "family": family, "magnitude": None,
               "truth": {}, "error": f"{type(err).__name__}: {err}"}
    for path in paths:
        out[path] = {"error": error, "best": {}, "seconds": 0.0}
    return out


def calibrate(clean: list[dict], path: str = "no_demand") -> dict[str, float]:
    """Per-kind thresholds of ``path`` from clean calibration benches (see module notes)."""
    from online_id.diagnose.bench_diagnosis import T_CRIT, THRESHOLDS

    thr = {}
    for kind in THRESHOLDS:
        gains = [b[kind]["gain"] for b in (path_result(r, path)["best"] for r in clean)
                 if kind in b and b[kind]["t"] >= T_CRIT]
        thr[kind] = max(MIN_THRESHOLDS.get(kind, MIN_THRESHOLD), MARGIN * max(gains, default=0.0))
    return thr


def calibrate_paths(clean: list[dict]) -> dict[str, dict[str, float]]:
    """Thresholds of every path, each calibrated on its own diagnoses of the clean benches."""
    return {path: calibrate(clean, path) for path in PATHS}


def classify(best: dict, thresholds: dict[str, float]) -> tuple[str, dict | None]:
    """The kind named first (``clean`` = no significant effect) and its candidate.

    As :func:`~online_id.diagnose.bench_diagnosis.diagnose_bench` names it: accepted (score at the
    threshold, significant, and the summary of the held-out error falls with it), the largest score over
    threshold.
    """
    from online_id.diagnose.bench_diagnosis import is_accepted

    ok = [(c["gain"] / thresholds[k], k, c) for k, c in best.items()
          if is_accepted(k, c["gain"], c["t"], thresholds) and c.get("summary_after", 0.0) < 1.0]
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
        return {"order_exact": p["order"] == truth["order"], "shaft_right": p["shaft"] == truth["shaft"],
                "order_and_shaft": p["order"] == truth["order"] and p["shaft"] == truth["shaft"]}
    if kind in ("fixed_frequency_disturbance", "additional_mode"):
        err = abs(p["freq_hz"] - truth["freq_hz"]) / truth["freq_hz"] if np.isfinite(p["freq_hz"] or np.nan) else 1.0
        out = {"freq_err_pct": 100 * err, "freq_within_2pct": err <= 0.02}
        if kind == "additional_mode" and "location" in truth and "location" in p:
            out["location_right"] = p["location"] == truth["location"]
        return out
    if kind == "sensor_delay":
        err = abs(p["delay_s"] - truth["delay_s"])
        return {"delay_err_ms": 1000 * err, "delay_within_1ms": err <= 1e-3,
                "signal_right": p["signal"] == truth["signal"]}
    if kind == "backlash":
        return {"gap_err_pct": 100 * (p["gap_rad"] - truth["gap_rad"]) / truth["gap_rad"]}
    return {}


def wilson(k: int, n: int) -> tuple[float, float] | None:
    """95 % Wilson score interval [%] of a rate of ``k`` in ``n``."""
    if n == 0:
        return None
    p, z2 = k / n, Z95 * Z95
    centre = (p + z2 / (2 * n)) / (1 + z2 / n)
    half = Z95 * math.sqrt(p * (1 - p) / n + z2 / (4 * n * n)) / (1 + z2 / n)
    return 100 * max(0.0, centre - half), 100 * min(1.0, centre + half)


def _rate(sel: list[dict], key: str) -> dict | None:
    vals = [bool(x[key]) for x in sel if key in x]
    if not vals:
        return None
    k, n = sum(vals), len(vals)
    return {"pct": 100 * k / n, "k": k, "n": n, "ci95": wilson(k, n)}


def _count(sel: list[dict], pred: Callable[[dict], bool]) -> dict | None:
    if not sel:
        return None
    k, n = sum(bool(pred(x)) for x in sel), len(sel)
    return {"pct": 100 * k / n, "k": k, "n": n, "ci95": wilson(k, n)}


def summarise(results: list[dict], thresholds: dict[str, float], path: str = "no_demand") -> dict[str, Any]:
    """Confusion matrix, right-kind rates (with 95 % intervals), parameter figures, false effects."""
    labels = list(KINDS)
    named_labels = labels + [FAILED]
    conf = np.zeros((len(labels), len(named_labels)), dtype=int)
    rows = []
    for r in results:
        res = path_result(r, path)
        # a diagnosis that raised named nothing: a failure of the case, never "clean"
        named, cand = (FAILED, None) if res.get("error") else classify(res["best"], thresholds)
        checks = parameter_check(named, r["truth"], cand)
        # held-out error of the named effect's own measure (the delay's score is its size in ms and
        # the mode's the transfer gain: their held-out transfer gain is a parameter)
        gain = cand["params"].get("heldout_gain", cand["gain"]) if cand else 0.0
        # the reported error (the summary over every channel) lower after the named effect (cases of an
        # earlier run without the summary: the named effect's own held-out figure)
        lower = cand is not None and (cand["summary_after"] < 1.0 if "summary_after" in cand else gain > 0)
        row = {"case": r["case"], "kind": r["kind"], "named": named, "magnitude": r["magnitude"],
               "gain": gain, "summary_after": cand.get("summary_after") if cand else None,
               "error_lower": lower, **checks, "error": res.get("error")}
        if r["kind"] == "backlash" and "passages" in r["truth"]:
            row["passages"] = r["truth"]["passages"]
        rows.append(row)
        conf[labels.index(r["kind"]), named_labels.index(named)] += 1

    per_kind = {}
    for kind in labels:
        sel = [x for x in rows if x["kind"] == kind]
        big = [x for x in sel if x["magnitude"] >= SMALLEST_DECILE or kind == "clean"]
        right = [x for x in big if x["named"] == kind]
        per_kind[kind] = {
            "n": len(sel), "n_above_decile": len(big),
            "right_first": _count(big, lambda x: x["named"] == kind),
            "right_first_all": _count(sel, lambda x: x["named"] == kind),
            "error_lower": (_count(big, lambda x: x["error_lower"])
                            if kind != "clean" else None),
            **{k: _rate(right, k) for k in ("order_exact", "shaft_right", "order_and_shaft",
                                           "freq_within_2pct", "delay_within_1ms", "signal_right",
                                           "location_right")},
            "median_freq_err_pct": _median(right, "freq_err_pct"),
            "median_delay_err_ms": _median(right, "delay_err_ms"),
            "median_gap_err_pct": _median(right, "gap_err_pct"),
            "named_as": {k: sum(x["named"] == k for x in big) for k in named_labels
                         if any(x["named"] == k for x in big)},
        }
        if kind == "backlash":
            moving = [x for x in big if x.get("passages", 1) > 0]
            per_kind[kind]["right_first_with_passages"] = _count(moving, lambda x: x["named"] == kind)
            per_kind[kind]["without_passages"] = len(big) - len(moving)
    effect = [x for x in rows if x["kind"] != "clean" and x["magnitude"] >= SMALLEST_DECILE]
    effect_all = [x for x in rows if x["kind"] != "clean"]
    clean = [x for x in rows if x["kind"] == "clean"]
    return {
        "path": path, "labels": labels, "named_labels": named_labels, "confusion": conf.tolist(),
        "per_kind": per_kind,
        "overall_right_first": _count(effect, lambda x: x["named"] == x["kind"]),
        "overall_right_first_all": _count(effect_all, lambda x: x["named"] == x["kind"]),
        "error_lower_all": _count(effect_all, lambda x: x["error_lower"]),
        "false_effect_clean": _count(clean, lambda x: x["named"] != "clean"),
        "error_lower": _count(effect, lambda x: x["error_lower"]),
        "failed_cases": sum(1 for x in rows if x["error"]),
        "thresholds": thresholds, "cases": rows,
    }


def _median(rows: list[dict], key: str) -> float | None:
    vals = [abs(x[key]) for x in rows if key in x and x[key] is not None and math.isfinite(x[key])]
    return float(np.median(vals)) if vals else None


def _pct(r: dict | None, ci: bool = True) -> str:
    if r is None:
        return "-"
    text = f"{r['pct']:.0f}"
    if ci and r["ci95"] is not None:
        text += f" ({r['ci95'][0]:.0f}-{r['ci95'][1]:.0f})"
    return text


def table(summary: dict) -> str:
    """Markdown table of the per-kind figures, rates with their 95 % (Wilson) intervals."""
    lines = [f"path: {summary['path']}", "",
             "| true kind | cases (above smallest decile) | right kind first % (95 % interval) | "
             "right kind first %, all cases | held-out error lower % | parameters | named instead |",
             "|---|---|---|---|---|---|---|"]
    for kind, s in summary["per_kind"].items():
        par = []
        if s["order_exact"] is not None:
            par.append(f"order exact and shaft right {_pct(s['order_and_shaft'], False)} % "
                       f"(order {_pct(s['order_exact'], False)} %, shaft {_pct(s['shaft_right'], False)} %)")
        if s["freq_within_2pct"] is not None:
            par.append(f"freq within 2 % {_pct(s['freq_within_2pct'], False)} % "
                       f"(median {s['median_freq_err_pct']:.2f} %)")
        if s["delay_within_1ms"] is not None:
            par.append(f"delay within 1 ms {_pct(s['delay_within_1ms'], False)} %, signal right "
                       f"{_pct(s['signal_right'], False)} % (median {s['median_delay_err_ms']:.2f} ms)")
        if s["median_gap_err_pct"] is not None:
            par.append(f"gap error median {s['median_gap_err_pct']:.0f} %")
        if "right_first_with_passages" in s:
            par.append(f"{s['without_passages']} without a torque reversal through the gap; with: "
                       f"{_pct(s['right_first_with_passages'], False)} %")
        other = ", ".join(f"{k} {v}" for k, v in s["named_as"].items() if k != kind)
        lines.append(f"| {kind} | {s['n']} ({s['n_above_decile']}) | {_pct(s['right_first'])} | "
                     f"{_pct(s.get('right_first_all'), False)} | "
                     f"{_pct(s['error_lower'], False)} | {'; '.join(par)} | {other} |")
    ov, fe, el = summary["overall_right_first"], summary["false_effect_clean"], summary["error_lower"]
    ova, ela = summary.get("overall_right_first_all"), summary.get("error_lower_all")
    lines += ["", f"overall right kind first, all effect cases: {_pct(ova)} % "
              f"({ova['k'] if ova else 0} of {ova['n'] if ova else 0}); above the smallest decile of "
              f"magnitudes: {_pct(ov)} % ({ov['k'] if ov else 0} of {ov['n'] if ov else 0})",
              f"held-out error lower: all effect cases {_pct(ela)} %, above the smallest decile {_pct(el)} %",
              f"clean benches reporting an effect: {_pct(fe)} % ({fe['k'] if fe else 0} of {fe['n'] if fe else 0})"]
    if summary.get("failed_cases"):
        lines.append(f"cases whose diagnosis raised (counted as failures, named '{FAILED}'): "
                     f"{summary['failed_cases']}")
    return "\n".join(lines)


def plot_confusion(summary: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    conf = np.array(summary["confusion"], dtype=float)
    labels = [lab.replace("_disturbance", "").replace("_", " ") for lab in summary["labels"]]
    named = [lab.replace("_disturbance", "").replace("_", " ")
             for lab in summary.get("named_labels", summary["labels"])]
    norm = conf / np.maximum(conf.sum(axis=1, keepdims=True), 1)
    fig, ax = plt.subplots(figsize=(7.5, 6.5))
    ax.imshow(norm, cmap="Blues", vmin=0, vmax=1)
    for i in range(conf.shape[0]):
        for j in range(conf.shape[1]):
            if conf[i, j]:
                ax.text(j, i, f"{int(conf[i, j])}", ha="center", va="center",
                        color="white" if norm[i, j] > 0.5 else "black")
    ax.set_xticks(range(len(named)), named, rotation=40, ha="right")
    ax.set_yticks(range(len(labels)), labels)
    ax.set_xlabel("named first (clean = no significant effect)")
    ax.set_ylabel("true effect")
    what = "torque and both speeds only" if summary["path"] == "no_demand" else "with the recorded demand"
    ax.set_title(f"online-id diagnose on randomised benches ({what})", fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def write_outputs(out: Path, summaries: dict[str, dict], calibration: list[dict],
                  results: list[dict]) -> list[Path]:
    """``diagnose_evaluation.json``, a confusion matrix PNG per path and ``diagnose_evaluation.md``."""
    out.mkdir(parents=True, exist_ok=True)
    files = [out / "diagnose_evaluation.json", out / "diagnose_evaluation.md"]
    doc = {"summary": summaries, "calibration_cases": calibration, "test_cases": results}
    files[0].write_text(dumps(doc, indent=1) + "\n", encoding="utf-8")
    files[1].write_text("\n\n".join(table(s) for s in summaries.values()) + "\n", encoding="utf-8")
    for path, s in summaries.items():
        png = out / ("confusion.png" if path == "no_demand" else f"confusion_{path}.png")
        plot_confusion(s, png)
        files.append(png)
    return files
