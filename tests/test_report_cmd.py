"""``online-id report``: figures and summary from a replayed CAN log or a saved state, and bad input."""

import json
import struct

import numpy as np
import pytest

from online_id.cli import main
from online_id.config import Settings
from online_id.analysis.poles import Pole
from online_id.io.statefile import save_state
from online_id.service.pipeline import Pipeline
from online_id.records import AlertKind, AlertOut

SHORT_BENCH = """
operating_points:
  - {speed_rpm: 1200, duration_s: 8}
  - {speed_rpm: 1700, duration_s: 8}
seed: 4
"""
FIGURES = ("frequency_vs_speed.png", "damping_vs_speed.png", "tracks_over_time.png")
PNG_MAGIC = b"\x89PNG\r\n\x1a\n"


@pytest.fixture(scope="module")
def bench_log(tmp_path_factory):
    d = tmp_path_factory.mktemp("bench")
    cfg = d / "scenario.yaml"
    cfg.write_text(SHORT_BENCH)
    assert main(["simulate", "--config", str(cfg), "--out", str(d / "bench.csv"), "--can-log",
                 str(d / "bench.log")]) == 0
    return d / "bench.log"


def _png_size(path):
    """(width, height) of a PNG file, after checking its signature and header chunk."""
    head = path.read_bytes()[:24]
    assert head[:8] == PNG_MAGIC and head[12:16] == b"IHDR", path
    return struct.unpack(">II", head[16:24])


def _check_figures(out):
    for name in FIGURES:
        path = out / name
        assert path.stat().st_size > 10_000, name
        width, height = _png_size(path)
        assert width >= 600 and height >= 400, (name, width, height)


def test_report_from_a_can_log(bench_log, tmp_path, capsys):
    out = tmp_path / "new" / "report"  # created with its parents
    capsys.readouterr()
    assert main(["report", str(bench_log), "--out", str(out)]) == 0
    printed = capsys.readouterr().out
    for name in FIGURES + ("report.json", "report.md"):
        assert f"wrote {out / name}" in printed
    _check_figures(out)
    doc = json.loads((out / "report.json").read_text())
    assert {"source", "kind", "counts", "estimates", "baselines", "tracks", "alerts", "active_alarm",
            "final_estimate", "figures", "counters", "status_changes"} <= doc.keys()
    assert doc["kind"] == "can_log" and doc["source"] == str(bench_log)
    # one estimate per publication at publish.rate_hz over the log (the first at the first sample)
    truth_s = float(np.loadtxt(bench_log.with_suffix(".csv"), delimiter=",", skiprows=1, usecols=0)[-1])
    rate = Settings().publish.rate_hz
    n = doc["counts"]["estimates"]
    assert abs(n - (rate * truth_s + 1)) <= 2, (n, truth_s)
    e = doc["estimates"]
    assert e["t_first_s"] == pytest.approx(0.0, abs=1e-6)
    assert e["t_last_s"] == pytest.approx(truth_s, abs=2.0 / rate)
    assert 0 <= doc["counts"]["valid_estimates"] <= n
    if doc["counts"]["valid_estimates"]:
        assert 20.0 < e["f0_hz"]["median"] < 30.0  # truth 24.98 Hz
        assert 1000.0 < e["speed_rpm"]["median"] < 1900.0
    assert doc["counts"]["tracks"] == len(doc["tracks"]) > 0
    assert doc["alerts"] == [] and doc["active_alarm"] is None
    assert doc["status_changes"][0]["state"] == "LEARNING"
    md = (out / "report.md").read_text()
    assert md.startswith("# online-id report: bench.log")
    for name in FIGURES:
        assert f"]({name})" in md
    assert "## Baselines" in md and "## Alerts" in md and "No alerts." in md


def _state_with_alarm() -> dict:
    """A pipeline state with tracks over a speed sweep, a learned baseline and a latched frequency fault."""
    pipe = Pipeline(Settings())
    rng = np.random.default_rng(3)
    for k in range(300):  # 30 s at 10 Hz, engine speed sweeping 1000-2000 rpm
        t = 0.1 * k
        rpm = 1500.0 + 500.0 * np.sin(2 * np.pi * t / 30.0)
        poles = []
        for f, zeta in ((25.0 * (1 + 0.002 * rng.standard_normal()), 0.05), (2 * rpm / 60.0, 0.005)):
            s = 2 * np.pi * f * complex(-zeta, np.sqrt(1 - zeta**2))
            poles.append(Pole(complex(np.exp(s * pipe.estimator.dt)), f, zeta, "complex"))
        pipe.tracker.update(t_s=t, speed_rpm=rpm, poles=poles)
    for _ in range(80):
        pipe.baseline.learn(speed_rpm=1500.0, f0_hz=25.0 * (1 + 0.002 * rng.standard_normal()), zeta=0.05)
    stats = pipe.baseline.lookup(1500.0)
    t = 30.0
    while pipe.detector.active is None or pipe.detector.active.level < 2:
        t += 0.1
        alarm = pipe.detector.update(t_s=t, speed_rpm=1500.0, f0_hz=0.93 * 25.0, zeta=0.05, f0_std_hz=0.02,
                                     zeta_std=0.002, baseline=stats, suppressed=False)
        if alarm is not None:
            pipe.alerts.append(AlertOut(alarm.detected_t_s, AlertKind.FREQ_DRIFT, alarm.level, alarm.change_pct,
                                        alarm.speed_rpm, alarm.message))
        assert t < 200
    return pipe.get_state()


def test_report_from_a_state_file(tmp_path, capsys):
    state = tmp_path / "state" / "online-id-state.json"
    save_state(state, _state_with_alarm())
    out = tmp_path / "report"
    assert main(["report", str(state), "--out", str(out)]) == 0
    _check_figures(out)
    doc = json.loads((out / "report.json").read_text())
    assert doc["kind"] == "state" and "estimates" not in doc
    assert doc["counts"]["estimates"] == 0
    classes = {t["class"] for t in doc["tracks"]}
    assert {"driveline", "speed_dependent"} <= classes
    assert doc["final_estimate"]["f0_hz"] == pytest.approx(25.0, rel=0.02)
    (band,) = doc["baselines"]
    assert band["band_rpm"] == [1375.0, 1625.0] and band["count"] == 80 and band["learned"]
    assert band["f0_hz"] == pytest.approx(25.0, rel=0.005)
    levels = [a["level"] for a in doc["alerts"]]
    assert levels[-1] == "fault" and set(levels) <= {"warning", "fault"}
    alarm = doc["active_alarm"]
    assert alarm["kind"] == "frequency" and alarm["level"] == 2 and alarm["change_pct"] < -5
    md = (out / "report.md").read_text()
    assert "## Active alarm" in md and "fault: driveline frequency" in md and "| 1375-1625 |" in md
    # a state file without the .json suffix is recognised by its content
    other = tmp_path / "saved-state"
    other.write_bytes(state.read_bytes())
    assert main(["report", str(other), "--out", str(tmp_path / "r2")]) == 0


def test_bad_input_one_line_errors(tmp_path, cli_error):
    out = str(tmp_path / "out")
    missing = tmp_path / "missing.log"
    err = cli_error(["report", str(missing), "--out", out])
    assert str(missing) in err and "no such file" in err
    garbage = tmp_path / "garbage.blf"
    garbage.write_bytes(bytes(np.random.default_rng(1).integers(0, 256, 4096, dtype=np.uint8)))
    assert str(garbage) in cli_error(["report", str(garbage), "--out", out])
    text = tmp_path / "garbage.log"
    text.write_text("this is not a candump log\n" * 20)
    assert str(text) in cli_error(["report", str(text), "--out", out])
    no_inputs = tmp_path / "foreign.log"
    no_inputs.write_text("".join(f"({k * 0.001:.6f}) can0 7E0#0011223344556677\n" for k in range(100)))
    err = cli_error(["report", str(no_inputs), "--out", out])
    assert str(no_inputs) in err and "no estimate" in err and "unknown_id 100" in err
    unknown = tmp_path / "bench.mf4"
    unknown.write_text("MDF 4.10")
    err = cli_error(["report", str(unknown), "--out", out])
    assert str(unknown) in err and "cannot read the MDF 4 file" in err  # .mf4 is read since issue 17
    broken = tmp_path / "state.json"
    broken.write_text("{not json")
    err = cli_error(["report", str(broken), "--out", out])
    assert str(broken) in err and "cannot read saved state" in err
    alien = tmp_path / "other.json"
    alien.write_text(json.dumps({"version": 1, "foo": 2}))
    err = cli_error(["report", str(alien), "--out", out])
    assert str(alien) in err and '"tracker"' in err and "foo" in err
    err = cli_error(["report", str(tmp_path), "--out", out])
    assert str(tmp_path) in err and "directory" in err
    assert not (tmp_path / "out").exists()  # nothing is written for bad input


def test_out_is_a_file(tmp_path, cli_error):
    state = tmp_path / "s.json"
    save_state(state, Pipeline(Settings()).get_state())
    blocker = tmp_path / "file"
    blocker.write_text("x")
    err = cli_error(["report", str(state), "--out", str(blocker)])
    assert str(blocker) in err and "cannot create the report directory" in err
    # an empty state (nothing learned or tracked) still gives the figures and the summary
    assert main(["report", str(state), "--out", str(tmp_path / "empty")]) == 0
    doc = json.loads((tmp_path / "empty" / "report.json").read_text())
    assert doc["counts"]["tracks"] == 0 and doc["baselines"] == [] and doc["active_alarm"] is None


def test_final_estimate_is_not_valid_when_the_service_ended_in_input_timeout():
    from online_id.offline.report import final_estimate
    from online_id.report.figures import EstimateSeries

    t = np.arange(5.0)
    est = EstimateSeries(t, np.full(5, 1500.0), np.full(5, 25.0), np.full(5, 0.05), np.array([1, 1, 1, 0, 0], bool))
    drive = {"f0_hz": 25.0, "zeta": 0.05, "valid": True}
    final = final_estimate({"driveline": drive, "state": "INPUT_TIMEOUT"}, est)
    assert final["valid"] is False and "INPUT_TIMEOUT" in final["why"] and "t = 2.0 s" in final["why"]
    assert final_estimate({"driveline": drive, "state": "TRACKING"}, est)["valid"] is True


def test_state_report_units_and_no_validity_claim(tmp_path):
    """A state file does not say whether the last estimate was valid; a 105 Hz "driveline" track is not called so."""
    pipe = Pipeline(Settings())
    for k in range(200):
        poles = [Pole(complex(0.5, 0.8), 105.0, 0.05, "complex")]
        pipe.tracker.update(t_s=0.1 * k, speed_rpm=1000.0 + 5.0 * k, poles=poles)
    for _ in range(40):
        pipe.baseline.learn(speed_rpm=1500.0, f0_hz=25.0, zeta=0.05)
    assert pipe.tracker.driveline() is not None  # the tracker calls it driveline
    state = tmp_path / "online-id-state.json"
    save_state(state, pipe.get_state())
    out = tmp_path / "report"
    assert main(["report", str(state), "--out", str(out)]) == 0
    doc = json.loads((out / "report.json").read_text())
    assert doc["final_estimate"]["valid"] is None and doc["final_estimate"]["f0_hz"] is None
    assert [t["class"] for t in doc["tracks"]] == ["unknown"] and doc["tracks_reclassed"][0]["f_hz"] == 105.0
    assert {"f0_hz", "zeta", "residual_rms", "speed_rpm", "c_s"} <= doc["units"].keys()
    assert doc["units"]["f0_hz"] == "Hz"
    assert "| unknown |" in (out / "report.md").read_text()


def test_fmt_prints_no_negative_zero():
    """An order line's damping of -1e-5 reads 0.0000 in the pole table, the column width kept."""
    from online_id.report.figures import fmt

    assert fmt(-1e-5, "8.4f") == "  0.0000" and fmt(-1e-5, ".4f") == "0.0000"
    assert fmt(-0.5, "8.4f") == " -0.5000" and fmt(-1e-9, ".3g") == "-1e-09"
    assert fmt(float("nan"), ".3f") == "-" and fmt(None, ".3f") == "-"
