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
