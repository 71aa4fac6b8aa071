"""Every JSON the diagnosis and identification commands print or write is strict JSON (no NaN, no
Infinity: ``null`` where a figure is undefined), and the before/after figures are the summary."""

import json

import numpy as np
import pytest

from online_id.cli import main
from online_id.io.jsonout import dumps, plain


def strict_loads(text: str):
    """``json.loads`` that rejects NaN and +-Infinity, as strict parsers do."""
    def reject(name: str):
        raise ValueError(f"not JSON: {name}")
    return json.loads(text, parse_constant=reject)


def test_plain_turns_non_finite_numbers_into_null():
    doc = {"a": float("nan"), "b": [np.float64("inf"), -np.inf, np.float32(1.5)], "c": (np.int64(3), np.bool_(True)),
           "d": np.array([1.0, np.nan])}
    assert plain(doc) == {"a": None, "b": [None, None, 1.5], "c": [3, True], "d": [1.0, None]}
    assert strict_loads(dumps(doc)) == plain(doc)
    with pytest.raises(ValueError):
        strict_loads('{"x": NaN}')


def _generic_csv(path, seed=0):
    rng = np.random.default_rng(seed)
    u = np.sign(rng.standard_normal(3000))
    y = np.zeros_like(u)
    for t in range(2, u.size):
        y[t] = 1.5 * y[t - 1] - 0.7 * y[t - 2] + 0.5 * u[t - 1] + 0.02 * rng.standard_normal()
    y += 0.05 * np.sin(2 * np.pi * 7.3 * np.arange(u.size) / 100.0)  # a line: a candidate with a refit
    np.savetxt(path, np.column_stack((np.arange(u.size) / 100.0, u, y)), delimiter=",", header="t,U,Y",
               comments="", fmt="%.8g")


def test_generic_diagnose_json_and_report_are_strict(tmp_path, capsys, monkeypatch):
    from online_id.diagnose.diagnosis import Diagnosis

    as_dict = Diagnosis.as_dict
    # an undefined figure (a frequency where no pole pair is, a damping of a real pole) is written as null
    monkeypatch.setattr(Diagnosis, "as_dict", lambda self: {**as_dict(self), "undefined": float("nan")})
    f = tmp_path / "m.csv"
    _generic_csv(f)
    assert main(["diagnose", str(f), "--input-col", "U", "--output-col", "Y", "--time-col", "t", "--json",
                 "--report", str(tmp_path / "rep")]) == 0
    doc = strict_loads(capsys.readouterr().out)
    written = strict_loads((tmp_path / "rep" / "diagnosis.json").read_text())
    assert written == doc and doc["undefined"] is None
    # the summary: relative to the baseline's held-out one-step RMS, 1 before; every step lowers it
    assert doc["error_before"]["rms"] == 1.0
    assert doc["error_after"]["rms"] <= 1.0
    last = 1.0
    for e in doc["effects"]:
        assert e["error_after"]["rms"] < e["error_before"]["rms"] == pytest.approx(last)
        last = e["error_after"]["rms"]
    assert any(c["rms"] is None or np.isfinite(c["rms"]) for c in doc["candidates"])


@pytest.mark.slow
def test_bench_diagnose_and_identify_json_are_strict(tmp_path, capsys):
    """A bench CSV: ``diagnose --json`` (with and without the demand), its report, and ``identify --json``."""
    cfg = tmp_path / "b.yaml"
    cfg.write_text("operating_points: [{speed_rpm: 1200, duration_s: 14}, {speed_rpm: 1700, duration_s: 14}, "
                   "{speed_rpm: 2200, duration_s: 14}]\nseed: 5\n"
                   "effects: {sensor_delay: {signal: dyno_speed, delay_s: 0.004}}\n")
    csv = tmp_path / "b.csv"
    assert main(["simulate", "--config", str(cfg), "--out", str(csv), "--with-demand"]) == 0
    capsys.readouterr()
    assert main(["diagnose", str(csv), "--json", "--max-effects", "2", "--no-demand",
                 "--report", str(tmp_path / "rep")]) == 0
    doc = strict_loads(capsys.readouterr().out)
    assert strict_loads((tmp_path / "rep" / "diagnosis.json").read_text()) == doc
    assert doc["result"] == "sensor_delay"
    # the reported error is the summary over every channel (torque balance included), relative to the
    # baseline; it falls with every accepted step, on the figure the step was accepted on as well
    before, after = doc["error_before"], doc["error_after"]
    assert before["rms"] == 1.0 and after["rms"] < 1.0
    assert set(before) >= {"dyno", "engine", "balance", "transfer"}
    last = 1.0
    for e in doc["effects"]:
        assert e["error_before"]["rms"] == pytest.approx(last) and e["error_after"]["rms"] < last
        assert e["accepted_on"]["after"] < e["accepted_on"]["before"]
        last = e["error_after"]["rms"]
    # the late dyno speed's own equation is not made worse by the correction
    assert after["dyno"]["rms_rpm"] <= before["dyno"]["rms_rpm"] * 1.001
    assert main(["diagnose", str(csv), "--json", "--max-effects", "1"]) == 0
    strict_loads(capsys.readouterr().out)
    assert main(["identify", str(csv), "--json"]) == 0
    strict_loads(capsys.readouterr().out)


def test_evaluation_writers_are_strict():
    """Every module that writes the diagnosis' or an evaluation's JSON writes it through the strict writer
    (a NaN raises there, or becomes null), never with ``json.dump``'s default ``allow_nan=True``."""
    import ast
    from pathlib import Path

    root = Path(__file__).resolve().parent.parent / "online_id"
    modules = ["evaluation/diagnose_benches.py", "evaluation/diagnose_rigs.py", "evaluation/chain.py", "evaluation/chain_files.py",
               "offline/diagnose.py", "offline/diagnose_report.py", "offline/identify.py", "cli/evaluate_diagnose.py",
               "cli/evaluate_rig.py", "cli/evaluate_chain.py"]
    loose = []
    for name in modules:
        for node in ast.walk(ast.parse((root / name).read_text(encoding="utf-8"))):
            if (isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute)
                    and node.func.attr in ("dump", "dumps") and getattr(node.func.value, "id", "") == "json"
                    and not any(k.arg == "allow_nan" and getattr(k.value, "value", True) is False
                                for k in node.keywords)):
                loose.append(f"{name}:{node.lineno}")
    assert not loose, f"json.dump(s) without allow_nan=False: {loose}"


def test_chain_family_results_are_strict_with_an_undefined_figure(tmp_path, monkeypatch):
    """The chain family's records, summary and results file stay strict JSON where a record holds NaN."""
    from online_id.evaluation import chain

    def fake_case(seed, quick, out, *args):
        return {"seed": seed, "kind": "clean", "variant": "", "layout": "bench", "magnitude": float("nan"),
                "decile": None, "failure": None, "named": "none", "kind_right": True, "params_right": None,
                "error_lower": None, "false_effect": False, "simulate_s": 0.0, "diagnose_s": float("inf")}

    monkeypatch.setattr(chain, "run_case", fake_case)
    monkeypatch.setattr(chain, "ProcessPoolExecutor", _InProcessPool)
    monkeypatch.setattr(chain, "confusion_png", lambda records, path: None)
    chain.run_family([1, 2], tmp_path, jobs=1, report=lambda s: None)
    doc = strict_loads((tmp_path / "results.json").read_text())
    assert doc["cases"][0]["magnitude"] is None and doc["cases"][0]["diagnose_s"] is None
    for line in (tmp_path / "results.jsonl").read_text().splitlines():
        strict_loads(line)


class _InProcessPool:
    """A ``ProcessPoolExecutor`` stand-in that runs each call at once in this process."""

    def __init__(self, max_workers=None):
        pass

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        return False

    def submit(self, fn, *args):
        from concurrent.futures import Future
        fut = Future()
        fut.set_result(fn(*args))
        return fut
