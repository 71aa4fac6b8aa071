"""The diagnosis evaluations count a case whose diagnosis raised as a failure, never as "clean", and report
the rate over all cases beside the rate above the smallest decile of magnitudes."""

import pytest

from online_id.evaluation import diagnose_benches as de
from online_id.evaluation import diagnose_rigs as re_


def _case(kind, magnitude, best=None, error=None, i=0):
    res = {"best": best or {}, "seconds": 0.0}
    if error:
        res["error"] = error
    truth = {"kind": kind, "delay_s": 0.004, "signal": "dyno_speed"} if kind != "clean" else {"kind": "clean"}
    return {"case": f"{kind}-{i}", "kind": kind, "seed": i, "magnitude": magnitude, "truth": truth,
            "no_demand": res}


def test_a_clean_bench_whose_diagnosis_raised_is_a_failure_not_clean():
    thresholds = {k: 0.01 for k in de.KINDS if k != "clean"}
    delay = {"sensor_delay": {"gain": 1.0, "t": 99.0, "summary_after": 0.8,
                              "params": {"delay_s": 0.004, "signal": "dyno_speed"}}}
    results = [_case("clean", 0.0, error="ValueError: boom", i=1), _case("clean", 0.0, i=2),
               _case("sensor_delay", 0.05, best=delay, i=3), _case("sensor_delay", 0.5, best=delay, i=4),
               _case("sensor_delay", 0.6, error="LinAlgError: singular", i=5)]
    s = de.summarise(results, thresholds)
    named = {r["case"]: r["named"] for r in s["cases"]}
    assert named["clean-1"] == de.FAILED and named["clean-2"] == "clean"
    assert named["sensor_delay-5"] == de.FAILED
    assert s["false_effect_clean"]["k"] == 1 and s["failed_cases"] == 2
    assert s["per_kind"]["clean"]["right_first"]["k"] == 1
    # all effect cases (3: one small, one raised) beside those above the smallest decile (2: one raised)
    assert (s["overall_right_first_all"]["k"], s["overall_right_first_all"]["n"]) == (2, 3)
    assert (s["overall_right_first"]["k"], s["overall_right_first"]["n"]) == (1, 2)
    text = de.table(s)
    assert "all effect cases: 67 (" in text and "above the smallest decile of magnitudes: 50 (" in text
    assert "counted as failures" in text
    assert sum(map(sum, s["confusion"])) == len(results) and len(s["confusion"][0]) == len(de.KINDS) + 1


def test_a_rig_case_that_raises_is_a_failed_case(monkeypatch):
    def boom(*args, **kwargs):
        raise FloatingPointError("overflow in the fit")

    monkeypatch.setattr(re_, "run_case", boom)
    rows = [re_._task((11, None, 0.3)), re_._task((11, 0, 0.3))]
    assert [r["found_kind"] for r in rows] == ["error", "error"] and "overflow" in rows[0]["error"]
    s = re_.summarise(rows)
    assert s["failed_cases"] == 2 and s["clean"]["false_effect_pct"] == 100.0
    assert s["rotation_order"]["named_first_pct"] == 0.0 and s["all_cases"]["right_first_pct"] == 0.0
    assert s["clock"]["offset_err_max_ms"] == pytest.approx(0.0)
