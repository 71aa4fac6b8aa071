"""The chain family's scorer: strict JSON, failures never clean, the parameter tolerances, the intervals."""

import json

import pytest

from online_id.evaluation.chain_score import (StrictJsonError, confusion, parse_strict, score_case, summarise,
                                              table_markdown, wilson)


def _truth(kind="clean", expected=None, seed=1, decile=None, variant=""):
    return {"seed": seed, "kind": kind, "variant": variant, "layout": "bench", "magnitude": None,
            "decile": decile, "expected": expected or {"kinds": []}}


def _doc(effects=(), before=1.0, after=1.0, **extra):
    return json.dumps({"effects": list(effects), "error_before": {"rms": before}, "error_after": {"rms": after},
                       **extra})


@pytest.mark.parametrize("constant", ["NaN", "Infinity", "-Infinity"])
def test_strict_parsing_refuses_nan_and_infinity(constant):
    text = '{"effects": [], "candidates": [{"sim_gain": %s}]}' % constant
    with pytest.raises(StrictJsonError):
        parse_strict(text)
    assert json.loads(text)  # what a lenient reader would have taken
    assert parse_strict('{"effects": [], "x": null}') == {"effects": [], "x": None}


def test_a_document_with_nan_fails_its_case_and_is_never_clean():
    text = '{"effects": [], "error_before": {"rms": 1.0}, "error_after": {"rms": 1.0}, "c": NaN}'
    rec = score_case(_truth(), 0, text, "")
    assert rec["failure"] == "json-nan" and rec["named"] == "error" and rec["kind_right"] is False
    assert rec["false_effect"] is None  # not counted as a clean bench that reported nothing
    assert rec["if_nan_were_null"]["kind_right"] is True  # kept apart, never in the rates
    s = summarise([rec])
    assert s["kinds"]["clean"]["kind_right"]["k"] == 0 and s["kinds"]["clean"]["failed"] == 1
    assert s["all_cases_if_nan_were_null"]["k"] == 1


@pytest.mark.parametrize("rc, stderr, failure", [
    (2, "usage: online-id ...\nonline-id: error: unrecognized arguments: --same-clock", "cli"),
    (2, "error: bench.csv: no column 'x'", "input"),
    (1, "Traceback (most recent call last):\n  ...\nValueError: boom", "crash"),
    (None, "timeout after 10 s", "timeout"),
])
def test_failed_runs_are_failures_of_their_class(rc, stderr, failure):
    for truth in (_truth(), _truth("backlash", {"kinds": ["backlash"]}, decile=3)):
        rec = score_case(truth, rc, "", stderr)
        assert rec["failure"] == failure and rec["kind_right"] is False and rec["named"] == "error"
    assert score_case(_truth(), 0, "not json", "")["failure"] == "json"
    assert score_case(_truth(), 0, "[1, 2]", "")["failure"] == "json"


def test_clean_benches_right_only_when_nothing_is_reported():
    assert score_case(_truth(), 0, _doc(), "")["kind_right"] is True
    rec = score_case(_truth(), 0, _doc([{"kind": "backlash", "params": {}}], 1.0, 0.9), "")
    assert rec["kind_right"] is False and rec["false_effect"] is True and rec["error_lower"] is None


def test_order_must_be_exact_and_on_the_right_shaft():
    exp = {"kinds": ["rotation_order_disturbance"], "order": 3.0, "shaft": ["dyno", "N_Bremse"]}
    t = _truth("rotation_order", exp, decile=4)

    def named(params, before=1.0, after=0.8):
        return score_case(t, 0, _doc([{"kind": "rotation_order_disturbance", "params": params}], before, after), "")

    assert named({"order": 3.0, "shaft": "dyno"})["params_right"] is True
    assert named({"order": 3.0, "shaft": "N_Bremse"})["params_right"] is True
    assert named({"order": 3.5, "shaft": "dyno"})["params_right"] is False
    assert named({"order": 3.0, "shaft": "engine"})["params_right"] is False
    assert named({"order": 3.0, "shaft": "undetermined"})["params_right"] is False
    assert named({"order": 3.0, "shaft": "dyno"}, 1.0, 1.1)["error_lower"] is False
    assert named({"order": 3.0, "shaft": "dyno"})["error_lower"] is True
    family = {"kinds": ["rotation_order_disturbance"], "kinds_containing": "order", "order": 0.5, "shaft": ["engine"]}
    ft = _truth("cylinder_family", family, decile=2, variant="imbalance")
    rec = score_case(ft, 0, _doc([{"kind": "order_family", "params": {"fundamental": 0.5, "order": 1.5,
                                                                        "shaft": "engine"}}]), "")
    assert rec["kind_right"] and rec["params_right"]
    rec = score_case(ft, 0, _doc([{"kind": "rotation_order_disturbance", "params": {"order": 1.5,
                                                                                    "shaft": "engine"}}]), "")
    assert rec["kind_right"] and not rec["params_right"]


def test_frequency_within_two_percent_and_delay_within_a_millisecond():
    t = _truth("fixed_frequency", {"kinds": ["fixed_frequency_disturbance"], "freq_hz": [100.0]}, decile=5)
    for f, ok in ((101.9, True), (98.1, True), (102.1, False), (float("nan"), False)):
        eff = [{"kind": "fixed_frequency_disturbance", "params": {"freq_hz": f}}]
        text = json.dumps({"effects": eff, "error_before": {"rms": 1}, "error_after": {"rms": 0.5}})
        rec = score_case(t, 0, text.replace("NaN", "null"), "")
        assert rec["params_right"] is ok
    t = _truth("sensor_delay", {"kinds": ["sensor_delay"], "delay_s": 0.004, "signal": ["dyno_speed", "n_dyno"]}, 1, 5)
    for d, sig, ok in ((0.0049, "dyno_speed", True), (0.0031, "n_dyno", True), (0.0051, "dyno_speed", False),
                       (0.004, "engine_speed", False), (-0.004, "dyno_speed", False)):
        rec = score_case(t, 0, _doc([{"kind": "sensor_delay", "params": {"delay_s": d, "signal": sig}}]), "")
        assert rec["params_right"] is ok, (d, sig)


def test_wilson_intervals_and_the_summary_above_the_smallest_decile():
    assert wilson(0, 10) == pytest.approx((0.0, 0.2775), abs=1e-4)
    assert wilson(10, 10) == pytest.approx((0.7225, 1.0), abs=1e-4)
    assert wilson(5, 10) == pytest.approx((0.2366, 0.7634), abs=1e-4)
    exp = {"kinds": ["backlash"]}
    recs = [score_case(_truth("backlash", exp, seed=s, decile=d), 0,
                       _doc([{"kind": k, "params": {}}], 1.0, 0.9), "")
            for s, (d, k) in enumerate([(0, "coulomb_friction"), (3, "backlash"), (9, "backlash")])]
    recs.append(score_case(_truth(seed=9), 0, _doc(), ""))
    s = summarise(recs)
    b = s["kinds"]["backlash"]
    assert (b["kind_right"]["k"], b["kind_right"]["n"]) == (2, 3)
    assert (b["kind_right_above"]["k"], b["kind_right_above"]["n"]) == (2, 2)
    assert s["kinds"]["clean"]["false_effect"]["k"] == 0
    assert s["all_cases"]["k"] == 3
    rows, cols, counts = confusion(recs)
    assert rows == ["clean", "backlash"] and cols[0] == "none" and cols[-1] == "error"
    assert counts[1][cols.index("coulomb_friction")] == 1
    assert "| backlash | 3 (2) | 67 %" in table_markdown(s)


def test_the_command_refuses_bad_settings_in_one_line(tmp_path, capsys):
    from online_id.cli import main

    assert main(["evaluate-diagnose-chain", "--program", str(tmp_path / "nothing"), "--out", str(tmp_path)]) == 2
    assert capsys.readouterr().err.strip() == f"error: --program {tmp_path / 'nothing'}: no such file"
    assert main(["evaluate-diagnose-chain", "--cases", "0", "--out", str(tmp_path)]) == 2
    assert main(["evaluate-diagnose-chain", "--seed", "108", "--cases", "1", "--layout", "rig", "--quick",
                 "--out", str(tmp_path)]) == 2  # seed 108 draws a bench
    assert "no rig case among seeds 108..108" in capsys.readouterr().err
