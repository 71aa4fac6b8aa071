"""Scoring the diagnosis of chain cases against their truth (rules: docs/evaluation-chain.md).

The tool's stdout is read as strict JSON (``NaN`` and ``Infinity`` refused); a run that fails in any
way counts as a failure of its case, never as "clean".  :func:`score_case` scores one case,
:func:`summarise` the rates per truth kind with 95 % Wilson intervals.
"""

from __future__ import annotations

import json
import math
from collections import Counter

from online_id.evaluation.chain_effects import DELAY_TOLERANCE_S, FREQ_TOLERANCE, ORDER_TOLERANCE


class StrictJsonError(ValueError):
    """The document holds a constant that strict JSON does not have (NaN, Infinity)."""


def _refuse(name: str):
    raise StrictJsonError(f"non-strict JSON constant {name}")


def parse_strict(text: str) -> dict:
    """``text`` as a JSON object; raises :class:`StrictJsonError` on NaN/Infinity, ``ValueError`` otherwise."""
    doc = json.loads(text, parse_constant=_refuse)
    if not isinstance(doc, dict):
        raise ValueError("the JSON document is not an object")
    return doc


def failure_class(returncode: int | None, stdout: str, stderr: str) -> str | None:
    """Why a run failed (``timeout``, ``cli``, ``input``, ``crash``, ``json-nan``, ``json``), None if it did not."""
    if returncode is None:
        return "timeout"
    if returncode != 0:
        if "unrecognized arguments" in stderr or "usage:" in stderr:
            return "cli"
        if "Traceback" in stderr:
            return "crash"
        return "input" if "error:" in stderr else "crash"
    try:
        parse_strict(stdout)
    except StrictJsonError:
        return "json-nan"
    except ValueError:
        return "json"
    return None


def _close(a: float, b: float, rel: float) -> bool:
    return abs(a - b) <= rel * abs(b)


def _names(value) -> set[str]:
    return {str(value).strip().lower()} if value is not None else set()


def _check_params(expected: dict, effect: dict) -> tuple[bool, str]:
    """Whether the first effect's parameters meet the truth's tolerances, and what was compared."""
    params = effect.get("params") or {}
    notes, ok = [], True
    if "order" in expected:
        got = params.get("fundamental", params.get("order"))
        right = isinstance(got, (int, float)) and abs(float(got) - expected["order"]) <= ORDER_TOLERANCE
        shaft = params.get("shaft")
        shaft_ok = bool(_names(shaft) & {s.lower() for s in expected["shaft"]})
        ok &= right and shaft_ok
        notes.append(f"order {got} (want {expected['order']:g}), shaft {shaft} (want {expected['shaft'][0]})")
    if "freq_hz" in expected:
        got = params.get("freq_hz")
        right = isinstance(got, (int, float)) and math.isfinite(got) and any(
            _close(float(got), f, FREQ_TOLERANCE) for f in expected["freq_hz"])
        ok &= right
        notes.append(f"freq {got} Hz (want {' or '.join(f'{f:.2f}' for f in expected['freq_hz'])})")
    if "delay_s" in expected:
        got, sig = params.get("delay_s"), params.get("signal")
        right = isinstance(got, (int, float)) and abs(float(got) - expected["delay_s"]) <= DELAY_TOLERANCE_S
        sig_ok = bool(_names(sig) & {s.lower() for s in expected["signal"]})
        ok &= right and sig_ok
        notes.append(f"delay {got} s on {sig} (want {expected['delay_s'] * 1000:.2f} ms on {expected['signal'][0]})")
    return bool(ok), "; ".join(notes)


def _kind_right(expected: dict, named: str) -> bool:
    if not expected["kinds"]:
        return named == "none"
    return named in expected["kinds"] or ("kinds_containing" in expected and expected["kinds_containing"] in named)


def _rms(doc: dict, key: str) -> float | None:
    v = (doc.get(key) or {}).get("rms") if isinstance(doc.get(key), dict) else None
    return float(v) if isinstance(v, (int, float)) else None


def _score_doc(doc: dict, exp: dict) -> dict:
    """The scored fields of a parsed diagnosis document against the expectation ``exp``."""
    effects = doc.get("effects") or []
    named = str(effects[0].get("kind", "?")) if effects else "none"
    rec: dict = {"named": named, "effects": [{"kind": e.get("kind"), "params": e.get("params")} for e in effects]}
    rec["kind_right"] = _kind_right(exp, named)
    if len(exp) > 1 and exp["kinds"]:
        ok, note = _check_params(exp, effects[0]) if rec["kind_right"] else (False, "")
        rec["params_right"], rec["params_note"] = ok, note
    else:
        rec["params_right"] = None
    before, after = _rms(doc, "error_before"), _rms(doc, "error_after")
    rec["rms_before"], rec["rms_after"] = before, after
    rec["error_lower"] = (before is not None and after is not None and after < before) if exp["kinds"] else None
    rec["false_effect"] = bool(effects) if not exp["kinds"] else None
    return rec


def score_case(truth: dict, returncode: int | None, stdout: str, stderr: str) -> dict:
    """The score record of one case (see module notes).

    A document that is JSON but for NaN/Infinity fails; what it would have scored with those read as
    null is kept apart in ``if_nan_were_null`` (reported beside the rates, never counted in them).
    """
    rec = {"seed": truth["seed"], "kind": truth["kind"], "variant": truth["variant"], "layout": truth["layout"],
           "magnitude": truth["magnitude"], "decile": truth["decile"],
           "failure": failure_class(returncode, stdout, stderr)}
    exp = truth["expected"]
    if rec["failure"]:
        tail = [ln for ln in stderr.strip().splitlines() if ln.strip()][-1:] or ["(no message)"]
        rec.update(named="error", kind_right=False, params_right=False if len(exp) > 1 else None,
                   error_lower=False if exp["kinds"] else None, false_effect=None, message=tail[0][:300])
        if rec["failure"] == "json-nan":
            rec["message"] = "stdout holds NaN or Infinity (not strict JSON)"
            rec["if_nan_were_null"] = _score_doc(json.loads(stdout), exp)
        return rec
    rec.update(_score_doc(parse_strict(stdout), exp))
    return rec


def wilson(k: int, n: int, z: float = 1.96) -> tuple[float, float]:
    """95 % Wilson score interval of ``k`` successes in ``n`` (0..1)."""
    if n == 0:
        return (0.0, 1.0)
    p = k / n
    den = 1 + z * z / n
    mid = (p + z * z / (2 * n)) / den
    half = z * math.sqrt(p * (1 - p) / n + z * z / (4 * n * n)) / den
    return (max(0.0, mid - half), min(1.0, mid + half))


def _rate(flags: list[bool]) -> dict:
    k, n = sum(flags), len(flags)
    lo, hi = wilson(k, n)
    return {"k": k, "n": n, "rate": k / n if n else None, "low": lo, "high": hi}


def _lenient(rec: dict) -> dict:
    """The record as scored with NaN/Infinity read as null (the same record when its JSON was strict)."""
    return rec.get("if_nan_were_null") or rec


def truth_label(rec: dict) -> str:
    return rec["kind"] + (f"/{rec['variant']}" if rec["variant"] else "")


def summarise(records: list[dict]) -> dict:
    """Rates per truth kind and overall (see docs/evaluation-chain.md, "The figures")."""
    out: dict = {"kinds": {}, "failures": dict(Counter(r["failure"] for r in records if r["failure"]))}
    groups = sorted({r["kind"] for r in records}, key=lambda k: (k != "clean", k))
    for kind in groups + ["all effects"]:
        rs = [r for r in records if (r["kind"] == kind if kind != "all effects" else r["kind"] != "clean")]
        if not rs:
            continue
        above = [r for r in rs if r["decile"] is None or r["decile"] > 0]
        entry = {"cases": len(rs), "above": len(above),
                 "kind_right": _rate([r["kind_right"] for r in rs]),
                 "kind_right_above": _rate([r["kind_right"] for r in above]),
                 "failed": sum(1 for r in rs if r["failure"]),
                 "kind_right_if_nan_were_null": _rate([_lenient(r)["kind_right"] for r in rs]),
                 "named": dict(Counter(r["named"] for r in rs))}
        with_params = [r for r in rs if r.get("params_right") is not None]
        if with_params:
            entry["params_right"] = _rate([bool(r["params_right"]) for r in with_params])
            entry["params_right_when_named"] = _rate([bool(r["params_right"]) for r in with_params if r["kind_right"]])
        if kind != "clean":
            entry["error_lower"] = _rate([bool(r["error_lower"]) for r in rs])
        else:
            entry["false_effect"] = _rate([bool(r["false_effect"]) for r in rs if r["failure"] is None])
        out["kinds"][kind] = entry
    out["all_cases"] = _rate([r["kind_right"] for r in records])
    out["all_cases_if_nan_were_null"] = _rate([_lenient(r)["kind_right"] for r in records])
    for layout in sorted({r["layout"] for r in records}):
        out[f"layout_{layout}"] = _rate([r["kind_right"] for r in records if r["layout"] == layout])
    return out


def _pct(rate: dict) -> str:
    if not rate or not rate["n"]:
        return "-"
    return f"{100 * rate['rate']:.0f} % ({100 * rate['low']:.0f}-{100 * rate['high']:.0f}) {rate['k']}/{rate['n']}"


def table_markdown(summary: dict) -> str:
    """The summary as a markdown table."""
    lines = ["| truth kind | cases (above smallest decile) | right kind first, all | right kind first, above "
             "smallest decile | parameters right (of all; of named right) | error after < before | "
             "clean: reported an effect | failed runs | (not counted) right kind first if NaN were null |",
             "|---|---|---|---|---|---|---|---|---|"]
    for kind, e in summary["kinds"].items():
        params = (f"{_pct(e['params_right'])}; {_pct(e['params_right_when_named'])}" if "params_right" in e else "-")
        lines.append(f"| {kind} | {e['cases']} ({e['above']}) | {_pct(e['kind_right'])} | "
                     f"{_pct(e['kind_right_above'])} | {params} | {_pct(e.get('error_lower'))} | "
                     f"{_pct(e.get('false_effect'))} | {e['failed']} | {_pct(e['kind_right_if_nan_were_null'])} |")
    lines.append("")
    lines.append(f"All cases, right kind first (clean: nothing reported): {_pct(summary['all_cases'])}")
    lines.append("(not counted: the same if NaN/Infinity in the JSON were read as null: "
                 f"{_pct(summary['all_cases_if_nan_were_null'])})")
    for key in sorted(k for k in summary if k.startswith("layout_")):
        lines.append(f"- {key[7:]}: {_pct(summary[key])}")
    if summary["failures"]:
        lines.append("Failed runs by class: " + ", ".join(f"{k} {v}" for k, v in sorted(summary["failures"].items())))
    return "\n".join(lines) + "\n"


def confusion(records: list[dict]) -> tuple[list[str], list[str], list[list[int]]]:
    """Rows (truth kind/variant), columns (named first: ``none``, kinds, ``error``) and counts."""
    rows = sorted({truth_label(r) for r in records}, key=lambda k: (not k.startswith("clean"), k))
    named = sorted({r["named"] for r in records} - {"none", "error"})
    cols = ["none"] + named + ["error"]
    counts = [[sum(1 for r in records if truth_label(r) == row and r["named"] == col) for col in cols] for row in rows]
    return rows, cols, counts


def confusion_png(records: list[dict], path) -> None:
    """The confusion matrix as a PNG (matplotlib, headless)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rows, cols, counts = confusion(records)
    fig, ax = plt.subplots(figsize=(1.1 * len(cols) + 3, 0.5 * len(rows) + 2))
    ax.imshow(counts, cmap="Blues")
    ax.set_xticks(range(len(cols)), cols, rotation=35, ha="right")
    ax.set_yticks(range(len(rows)), rows)
    for i, row in enumerate(counts):
        for j, v in enumerate(row):
            if v:
                ax.text(j, i, str(v), ha="center", va="center", color="black")
    ax.set_xlabel("named first by online-id diagnose")
    ax.set_ylabel("truth")
    ax.set_title("chain family: truth against the effect named first")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
