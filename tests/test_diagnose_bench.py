"""Bench diagnosis: causal data path, fractional shifts, effects on realistic benches, CLI.

Every simulated bench here has compression pulses and the dyno under PI speed
control with the PRBS (the scenario defaults); effects at moderate magnitudes,
on different plants and seeds.  Diagnosed from torque and both speeds only (no
recorded demand, what a bench CSV or CAN log holds) unless a test says
otherwise.  The randomised evaluation (``online-id evaluate-diagnose``)
measures the rates; these tests guard the path.
"""

import json

import numpy as np
import pytest

from online_id.bench import simulate_bench
from online_id.bench.diagnose_cases import make_case
from online_id.bench.scenario import (Backlash, BenchScenario, CouplingFriction, Effects, OperatingPoint,
                                      OrderTorque, SensorDelay, SinusoidalDisturbance,
                                      StructuralResonance, ThirdInertia)
from online_id.cli import main
from online_id.diagnose.bench_data import causal_path, filter_decimate, prepare
from online_id.diagnose.bench_diagnosis import THRESHOLDS, diagnose_bench, is_accepted
from online_id.diagnose.bench_model import shifted
from online_id.errors import InputDataError

POINTS = (OperatingPoint(1100, 12), OperatingPoint(1650, 12), OperatingPoint(2200, 12))
LONG = (OperatingPoint(1100, 20), OperatingPoint(1650, 20), OperatingPoint(2200, 20))
PLANTS = {"a": dict(J1=0.8, J2=0.35, c_s=6000.0, d_s=4.0),
          "b": dict(J1=1.2, J2=0.25, c_s=9000.0, d_s=10.0)}


def series_of(scenario, demand=False):
    rec = simulate_bench(scenario)
    d = rec.to_data("sim")
    return prepare(d.time_s, d.dyno_torque_nm, d.dyno_speed_rad_s, d.engine_speed_rad_s, source="sim",
                   demand_nm=rec.test_torque_nm if demand else None)


def first(result):
    assert result.steps, f"no effect; candidates: {[c.as_dict() for c in result.candidates[0]]}"
    step = result.steps[0]
    assert step.candidate.gain > 0
    return step.candidate


def test_causal_path_keeps_delays_where_they_are():
    rng = np.random.default_rng(0)
    x = rng.standard_normal(4000)
    late = np.concatenate((np.zeros(6), x[:-6]))  # 6 raw samples later
    path = causal_path(1000.0)
    a, b = filter_decimate(x, path), filter_decimate(late, path)
    assert path.q == 2 and path.group_delay_samples == 16
    # exactly 3 decimated samples later: nothing leaks to the other side of the delay
    np.testing.assert_allclose(b[3 + 40:-40], a[40:-43], atol=1e-12)
    lags = np.arange(-5, 6)
    xc = [np.dot(b[100 + k:1800 + k], a[100:1800]) for k in lags]
    assert lags[int(np.argmax(xc))] == 3


def test_fractional_shift_is_all_pass():
    n = np.arange(3000)
    x = np.sin(2 * np.pi * 0.07 * n) + 0.5 * np.cos(2 * np.pi * 0.23 * n)
    y = shifted(x, 0.3)
    exact = np.sin(2 * np.pi * 0.07 * (n + 0.3)) + 0.5 * np.cos(2 * np.pi * 0.23 * (n + 0.3))
    np.testing.assert_allclose(y[200:-200], exact[200:-200], atol=3e-3)
    rng = np.random.default_rng(1)
    w = rng.standard_normal(5000)
    assert np.var(shifted(w, 0.5)) == pytest.approx(np.var(w), rel=0.02)  # noise is not smoothed


@pytest.mark.slow
@pytest.mark.parametrize("plant, seed, shaft, order", [("a", 3, "engine", 1.5), ("b", 4, "dyno", 3.0)])
def test_rotation_order_found_on_its_shaft(plant, seed, shaft, order):
    sc = BenchScenario(operating_points=POINTS, seed=seed, **PLANTS[plant],
                       effects=Effects(order_torque=OrderTorque(shaft, order, 4.0, 0.7)))
    c = first(diagnose_bench(series_of(sc), max_effects=1))
    assert c.kind == "rotation_order_disturbance"
    assert c.params["order"] == order
    assert c.params["shaft"] == shaft


@pytest.mark.slow
@pytest.mark.parametrize("plant, seed, order, amplitude_nm", [
    ("b", 102, 5.0, 1.0), ("b", 111, 5.0, 1.2),
    pytest.param("b", 113, 5.0, 1.0, marks=pytest.mark.xfail(strict=True, reason=(
        "named right first, from the dyno's speed equation (the order scan finds the line there), but the "
        "torque balance alone removes 1.9 % of its held-out error at t 2.81 (< 2.86): the line is 1.5x its "
        "floor on the fastest plateau (183 Hz, at the edge of the decimating filter's passband)")))])
def test_a_dyno_ripple_the_speed_equation_predicts_is_named_from_the_torque_balance(plant, seed, order,
                                                                                   amplitude_nm):
    """A ripple of the dyno's air gap well above the driveline mode: the dyno's speed equation predicts
    most of it from its own lags (its line there is 1-4x the floor), while the torque balance, which
    nothing predicts from the speeds, holds it. The order is named on the dyno, and the balance alone
    would name it (the speed equations at the recording's rate may too)."""
    sc = BenchScenario(operating_points=POINTS, seed=seed, **PLANTS[plant],
                       effects=Effects(order_torque=OrderTorque("dyno", order, amplitude_nm, 0.3)))
    d = diagnose_bench(series_of(sc), max_effects=1)
    c = first(d)
    assert c.kind == "rotation_order_disturbance"
    assert (c.params["order"], c.params["shaft"]) == (order, "dyno")
    assert any(b.judged_on == ("balance",) and b.params["found_in"] == "balance" and b.params["order"] == order
               and b.params["shaft"] == "dyno" and is_accepted(b.kind, b.gain, b.t_stat, d.thresholds)
               for b in d.candidates[0])


@pytest.mark.slow
@pytest.mark.parametrize("seed", [90217, 90190])
def test_a_chain_benchs_dyno_ripple_is_named(tmp_path, capsys, monkeypatch, seed):
    """Chain-family benches (held out until they showed this; development cases since) with a dyno ripple
    that named nothing. 90217: order 5 of 2.2 Nm on a six-cylinder bench at 870-1690 rpm (72-141 Hz); it
    stood out only in the torque balance (28-135x its floor), which the speed equations predict from
    their own lags. 90190: order 7 of 0.9 Nm whose line lies above the decimated passband on two of four
    plateaus (99-282 Hz in a 1 kHz record), 1.3-3x its floor in the balance's Welch spectrum; order
    tracking finds it (40-110x). Each is named first, on the dyno, and both the error it was accepted on
    and the summary fall (90226, order 9, is named the same way with its side undetermined: the
    development run in docs/evaluation-chain.md)."""
    from online_id.evaluation.chain import prepare_case

    spec, argv = prepare_case(seed, False, tmp_path)
    assert spec["kind"] == "rotation_order" and spec["effect"]["shaft"] == "dyno"
    monkeypatch.chdir(tmp_path)
    assert main(argv) == 0
    doc = json.loads(capsys.readouterr().out)
    e = doc["effects"][0]
    assert e["kind"] == "rotation_order_disturbance", doc["effects"]
    assert (e["params"]["order"], e["params"]["shaft"]) == (spec["effect"]["order"], "dyno")
    assert e["accepted_on"]["after"] < e["accepted_on"]["before"]
    assert doc["error_after"]["rms"] < doc["error_before"]["rms"]


@pytest.mark.slow
@pytest.mark.parametrize("seed, truth, kind", [(90327, "fixed_frequency", "fixed_frequency_disturbance")])
def test_a_chain_bench_that_named_nothing_names_its_effect(tmp_path, capsys, monkeypatch, seed, truth, kind):
    """Chain benches (held out until they showed this; development cases since) that named nothing.
    90327: a line of 2.2 Nm at 100.8 Hz on the engine, 33-848x its floor in the engine's speed equation
    (which predicts it from its own lags: the term lost 3 % there) and hidden in the balance's noise
    (1.1-1.3x), where its term removes 3.4 % at t 9.7 (now a line found in a speed equation is judged in
    the balance too). It is named first and the summary falls. (90249, a backlash at t 2.6 pooled and 5.4
    with the plateaus as strata, is kept out of the suite for its 45 s; tests/test_bench_screening.py
    tests the statistic.)"""
    from online_id.evaluation.chain import prepare_case

    spec, argv = prepare_case(seed, False, tmp_path)
    assert spec["kind"] == truth
    monkeypatch.chdir(tmp_path)
    assert main(argv) == 0
    doc = json.loads(capsys.readouterr().out)
    assert doc["result"] == kind, doc["effects"]
    assert doc["error_after"]["rms"] < doc["error_before"]["rms"]


@pytest.mark.slow
@pytest.mark.parametrize("plant, seed, signal, delay_s, demand", [("b", 7, "dyno_speed", 0.003, False),
                                                                 ("a", 8, "engine_speed", 0.004, True),
                                                                 ("b", 9, "engine_speed", 0.002, False)])
def test_speed_delay_fractional(plant, seed, signal, delay_s, demand):
    sc = BenchScenario(operating_points=POINTS, seed=seed, **PLANTS[plant],
                       effects=Effects(sensor_delay=SensorDelay(signal, delay_s)))
    c = first(diagnose_bench(series_of(sc, demand), max_effects=1))
    assert c.kind == "sensor_delay" and c.params["signal"] == signal
    assert c.params["delay_s"] == pytest.approx(delay_s, abs=1e-3)  # issue 14: within 1 ms
    assert c.params["heldout_gain"] > 0  # the held-out transfer misfit is lower with the delay


@pytest.mark.slow
@pytest.mark.parametrize("plant, seed, freq_hz, resonance, demand", [("a", 5, 47.0, False, False),
                                                                    ("b", 6, 33.0, True, False),
                                                                    ("a", 18, 71.0, True, True)])
def test_fixed_frequency_disturbance_is_not_a_mode(plant, seed, freq_hz, resonance, demand):
    # an unmeasured torque: a line in the torque balance that the excitation does not explain (the
    # narrow-band one, zeta 0.01, is predictable from the speeds' past and hides in the one-step
    # residual of the speed equations)
    fx = (Effects(structural_resonance=StructuralResonance(freq_hz, 0.01, 2.5)) if resonance
          else Effects(disturbance=SinusoidalDisturbance(freq_hz, 2.5)))
    sc = BenchScenario(operating_points=POINTS, seed=seed, **PLANTS[plant], effects=fx)
    c = first(diagnose_bench(series_of(sc, demand), max_effects=1))
    assert c.kind == "fixed_frequency_disturbance"
    assert c.params["freq_hz"] == pytest.approx(freq_hz, rel=0.02)


@pytest.mark.slow
@pytest.mark.parametrize("plant, seed, f_hz, ratio, points", [("a", 13, 60.0, 0.25, POINTS),
                                                             ("b", 14, 85.0, 0.15, POINTS),
                                                             ("a", 17, 100.0, 0.15, LONG)])
def test_second_mode_is_a_mode(plant, seed, f_hz, ratio, points):
    from online_id.bench.plant import linear_modes

    p = PLANTS[plant]
    J3 = ratio * p["J2"]
    jr = p["J2"] * J3 / (p["J2"] + J3)
    w = 2 * np.pi * f_hz
    third = (J3, w**2 * jr, 2 * 0.04 * w * jr)
    sc = BenchScenario(operating_points=points, seed=seed, **p, third_inertia=ThirdInertia(*third))
    c = first(diagnose_bench(series_of(sc), max_effects=1))
    assert c.kind == "additional_mode"
    f_true = linear_modes(p["J1"], p["J2"], p["c_s"], p["d_s"], third)[-1]["f_hz"]
    assert c.params["freq_hz"] == pytest.approx(f_true, rel=0.02)  # issue 14: within 2 %


@pytest.mark.parametrize("f1, f2, mu, tau_s", [(15.0, 70.0, 0.1, 0.0), (30.0, 110.0, 0.05, -0.002),
                                               (20.0, 45.0, 0.2, 0.001)])
def test_speed_transfer_mode_fit(f1, f2, mu, tau_s):
    from online_id.diagnose.bench_transfer import fit_ratio_mode, fit_ratio_tau

    # engine side with a further inertia (J2 = 1): T = (d s + c)(J3 s^2 + d2 s + c2) / [...]
    rng = np.random.default_rng(int(f2))
    f = np.arange(2.0, 150.0)
    s = 2j * np.pi * f
    c, d = (2 * np.pi * f1) ** 2, 2 * 0.08 * 2 * np.pi * f1
    c2, d2 = mu * (2 * np.pi * f2) ** 2, mu * 2 * 0.04 * 2 * np.pi * f2
    z3 = mu * s**2 * (d2 * s + c2) / (mu * s**2 + d2 * s + c2)
    T = (d * s + c) / (s**2 + z3 + d * s + c) * np.exp(-s * tau_s)
    T = T * (1 + 0.01 * (rng.standard_normal(f.size) + 1j * rng.standard_normal(f.size)))
    w = np.ones(f.size)
    two = fit_ratio_tau(f, T, w, 0.012)
    four, _ = fit_ratio_mode(f, T, w, two, 0.012)
    assert four.misfit(f, T, w) < 0.2 * two.misfit(f, T, w)
    assert four.tau_s == pytest.approx(tau_s, abs=2e-4)
    eig = np.roots(np.polyadd(np.polymul([1.0, d, c], [mu, d2, c2]), np.polymul([mu, 0, 0], [d2, c2])))
    f_true = max(abs(eig)) / (2 * np.pi)
    assert max(four.poles_hz()) == pytest.approx(f_true, rel=0.01)


@pytest.mark.slow
@pytest.mark.parametrize("plant, seed", [("a", 15), ("b", 16)])
def test_coupling_coulomb_friction(plant, seed):
    sc = BenchScenario(operating_points=POINTS, seed=seed, **PLANTS[plant],
                       effects=Effects(coupling_friction=CouplingFriction(3.0)))
    assert first(diagnose_bench(series_of(sc), max_effects=1)).kind == "coulomb_friction"


@pytest.mark.slow
@pytest.mark.parametrize("plant, seed, gap_rad", [("a", 21, 0.003), ("b", 22, 0.002), ("a", 23, 0.0015)])
def test_backlash_found(plant, seed, gap_rad):
    # a dead zone in the shaft: the engine equation (its speed driven by the shaft torque alone) gains
    # from clip(twist - centre, +-gap/2) beyond the linear twist
    sc = BenchScenario(operating_points=POINTS, seed=seed, **PLANTS[plant], effects=Effects(backlash=Backlash(gap_rad)))
    r = diagnose_bench(series_of(sc), max_effects=1)
    c = first(r)
    assert c.kind == "backlash"
    assert 0.5 * gap_rad < c.params["gap_rad"] < 3.0 * gap_rad
    e0, e1 = r.errors(r.baseline), r.errors(r.final)
    assert e1["engine"]["rms_rpm"] < e0["engine"]["rms_rpm"]  # the held-out error is lower with it


@pytest.mark.slow
@pytest.mark.parametrize("seed", [11, 12, 13])
def test_clean_randomised_benches_report_nothing(seed):
    case = make_case("clean", seed, plateau_s=(12.0, 13.0))
    r = diagnose_bench(series_of(case.scenario), max_effects=1)
    assert r.steps == [], [c.as_dict() for c in r.candidates[0] if c.gain >= THRESHOLDS[c.kind]]
    assert r.stop_reason == "no significant effect"


@pytest.mark.slow
def test_cli_bench_csv_json_and_report(tmp_path, capsys):
    cfg = tmp_path / "b.yaml"
    cfg.write_text("operating_points: [{speed_rpm: 1200, duration_s: 12}, {speed_rpm: 1900, duration_s: 12}]\n"
                   "seed: 2\neffects: {order_torque: {shaft: engine, order: 2.5, amplitude_nm: 5.0}}\n")
    assert main(["simulate", "--config", str(cfg), "--out", str(tmp_path / "b.csv"), "--with-demand"]) == 0
    assert "torque_demand_nm" in (tmp_path / "b.csv").read_text().splitlines()[0]
    capsys.readouterr()
    assert main(["diagnose", str(tmp_path / "b.csv"), "--json", "--max-effects", "1", "--no-demand"]) == 0
    doc = json.loads(capsys.readouterr().out)
    assert doc["result"] == "rotation_order_disturbance" and doc["demand"] is False
    assert main(["diagnose", str(tmp_path / "b.csv"), "--json", "--max-effects", "1",
                 "--report", str(tmp_path / "rep")]) == 0
    doc = json.loads(capsys.readouterr().out)
    assert doc["demand"] is True  # the CSV's torque_demand_nm column is taken when present
    assert doc["result"] == "rotation_order_disturbance"
    assert doc["effects"][0]["params"]["order"] == 2.5
    path = doc["data_path"]
    assert path["fs_hz"] <= 500 and path["group_delay_removed_samples"] == (path["fir_taps"] - 1) // 2
    assert len(doc["plateaus"]) == 2 and doc["plateaus"][0]["declared_orders"][:2] == [2.0, 4.0]
    for name in ("summary.md", "diagnosis.json", "residual_spectrum.png"):
        assert (tmp_path / "rep" / name).stat().st_size > 0


def test_demand_column_only_from_a_bench_csv(tmp_path, capsys):
    log = tmp_path / "b.log"
    log.write_text("")
    assert main(["diagnose", str(log), "--demand-col", "torque_demand_nm"]) != 0
    assert capsys.readouterr().err.strip().endswith("is not a bench CSV; only a CSV carries a demand column")
    assert main(["diagnose", str(log), "--demand-col", "x", "--no-demand"]) != 0
    assert "--demand-col and --no-demand exclude each other" in capsys.readouterr().err


def test_bench_without_plateaus_is_a_one_line_error():
    t = np.arange(20000) / 1000.0
    speed = 100.0 + 20.0 * t  # a ramp, never steady
    with pytest.raises(InputDataError, match=r"ramp.csv: no steady operating point of at least 8 s"):
        prepare(t, np.sin(t), speed, speed, source="ramp.csv")
    with pytest.raises(InputDataError, match=r"x.csv: engine speed has 3 non-finite values \(first at sample 5\)"):
        bad = np.full(t.size, 100.0)
        bad[5:8] = np.nan
        prepare(t, np.sin(t), speed, bad, source="x.csv")


@pytest.mark.parametrize("fa_hz, zeta, tau_s", [(20.0, 0.05, 0.004), (35.0, 0.15, -0.0015), (14.0, 0.1, 0.0)])
def test_speed_transfer_delay_fit(fa_hz, zeta, tau_s):
    from online_id.diagnose.bench_transfer import fit_ratio_delay

    rng = np.random.default_rng(int(fa_hz))
    f = np.arange(2.0, 150.0)
    s, w0 = 2j * np.pi * f, 2 * np.pi * fa_hz
    T = (2 * zeta * w0 * s + w0**2) / (s**2 + 2 * zeta * w0 * s + w0**2) * np.exp(-s * tau_s)
    T = T * (1 + 0.02 * (rng.standard_normal(f.size) + 1j * rng.standard_normal(f.size)))
    tau, v1, v0 = fit_ratio_delay(f, T, np.ones(f.size), 0.012)
    assert tau == pytest.approx(tau_s, abs=2e-4)
    assert v1 <= v0


def test_evaluate_diagnose_resummarises_earlier_cases(tmp_path, capsys):
    run = tmp_path / "run"
    run.mkdir()
    delay = {"gain": 0.003, "t": 9.0, "params": {"signal": "dyno_speed", "delay_s": 3e-4, "heldout_gain": 0.003}}
    backlash = {"backlash": {"gain": 0.02, "t": 4.0, "params": {"gap_rad": 1e-3}}}
    clean = {"case": "clean-100000", "kind": "clean", "magnitude": 0.0, "truth": {"kind": "clean"},
             "no_demand": {"best": backlash}, "demand": {"best": {}}}
    (run / "calibration.jsonl").write_text(json.dumps(clean) + "\n")
    found = {"sensor_delay": {**delay, "gain": 0.42, "params": {**delay["params"], "delay_s": 0.0042,
                                                                "heldout_gain": 0.42}}}
    cases = [{**clean, "case": "clean-1", "no_demand": {"best": {"sensor_delay": delay}},
              "demand": {"best": {"sensor_delay": delay}}},
             {"case": "sensor_delay-1", "kind": "sensor_delay", "magnitude": 0.5,
              "truth": {"kind": "sensor_delay", "signal": "dyno_speed", "delay_s": 0.004},
              "no_demand": {"best": found}, "demand": {"best": {}}}]
    (run / "cases.jsonl").write_text("".join(json.dumps(c) + "\n" for c in cases))
    out = tmp_path / "final"
    assert main(["evaluate-diagnose", "--cases", "0", "--include", str(run),
                 "--calibration-from", str(run), "--out", str(out)]) == 0
    thr = json.loads((out / "thresholds.json").read_text())
    # per path, 1.1 x the largest significant clean gain, else the floors
    assert thr["no_demand"]["backlash"] == pytest.approx(0.022) and thr["demand"]["backlash"] == 0.005
    assert thr["no_demand"]["sensor_delay"] == 0.005
    summary = json.loads((out / "diagnose_evaluation.json").read_text())["summary"]
    kinds = {r["case"]: r["named"] for r in summary["no_demand"]["cases"]}
    assert kinds == {"clean-1": "clean", "sensor_delay-1": "sensor_delay"}  # a gain of 0.003 is below the floor
    assert {r["case"]: r["named"] for r in summary["demand"]["cases"]}["sensor_delay-1"] == "clean"
    right = summary["no_demand"]["per_kind"]["sensor_delay"]["right_first"]
    assert right["k"] == right["n"] == 1 and right["ci95"][0] == pytest.approx(20.65, abs=0.01)  # Wilson
    text = capsys.readouterr().out
    assert "2 test and 1 calibration cases" in text and "path: no_demand" in text and "path: demand" in text
    assert (out / "confusion.png").stat().st_size > 0 and (out / "confusion_demand.png").stat().st_size > 0
    assert main(["evaluate-diagnose", "--cases", "0", "--out", str(out)]) != 0
    assert "--cases (0 only with --include)" in capsys.readouterr().err


def test_the_causal_path_decimates_a_recorders_rate_as_the_nominal_one():
    """999.97 Hz (a recorder 30 ppm slow) to 500 Hz is factor 2, as 1 kHz is (it was 1: no decimation)."""
    from online_id.diagnose.bench_data import causal_path

    for fs in (1000.0, 999.97, 1000.03):
        path = causal_path(fs, 500.0)
        assert path.q == 2 and path.numtaps == 33
    assert causal_path(200.0, 500.0).q == 1 and causal_path(200.0, 500.0).numtaps == 1  # slower than the target


@pytest.mark.parametrize("sign", ["braking", "driving"])
def test_the_demand_column_is_read_with_the_signals_in_one_pass(tmp_path, sign):
    """``bench_series`` of a bench CSV with the demand column: the series prepared from the signals and the
    demand as written (signed like the dyno torque), whether named with --demand-col or found by its
    default name; with --no-demand, none."""
    import dataclasses

    from online_id.ingest.bench_series import bench_series
    from online_id.records import DEMAND_COLUMN
    from online_id.config import Settings
    from online_id.diagnose.bench_data import DEFAULT_PULSES_PER_REV
    from online_id.diagnose.bench_data import TARGET_FS_HZ, prepare
    from online_id.ingest.signals import read_bench_csv

    rng = np.random.default_rng(3)
    n = 10000  # 10 s at 1 kHz: one steady operating point (a bench diagnosis needs 8 s)
    t = np.arange(n) / 1000.0
    demand = np.where(np.repeat(rng.random(n // 100) < 0.5, 100), -30.0, 30.0)
    rows = np.column_stack([t, 1500 + rng.normal(0, 0.1, n), 1500 + rng.normal(0, 0.1, n), -8 + demand, demand])
    path = tmp_path / "bench.csv"
    np.savetxt(path, rows, delimiter=",", fmt="%.6f",
               header=f"time_s,dyno_speed_rpm,engine_speed_rpm,dyno_torque_nm,{DEMAND_COLUMN}", comments="")
    s = Settings()
    s = dataclasses.replace(s, units=dataclasses.replace(s.units, torque_sign=sign))
    d = read_bench_csv(path, s.columns, s.units)
    k = 1.0 if sign == "braking" else -1.0
    expect = prepare(d.time_s, d.dyno_torque_nm, d.dyno_speed_rad_s, d.engine_speed_rad_s, source=str(path),
                     pulses_per_rev=DEFAULT_PULSES_PER_REV, target_hz=TARGET_FS_HZ, demand_nm=k * demand)
    for named in (DEMAND_COLUMN, None):
        series = bench_series(path, s, demand_col=named)
        assert series.demand is not None and np.allclose(series.demand, expect.demand, atol=1e-6)
    assert bench_series(path, s, use_demand=False).demand is None


@pytest.mark.parametrize("f1, f2, mu, tau_s", [(15.0, 70.0, 0.3, 0.0), (30.0, 110.0, 0.15, -0.002),
                                               (20.0, 45.0, 0.5, 0.001)])
def test_speed_transfer_mode_between_the_shaft_and_the_engine(f1, f2, mu, tau_s):
    """A further inertia between the shaft and the engine (a dual-mass flywheel, the sensor on the engine):
    the transfer's other shape fits it, recovers the delay (none, or the given one) and the added mode,
    and the shape of an inertia beyond the engine fits it worse."""
    from online_id.bench.plant import linear_modes
    from online_id.diagnose.bench_transfer import fit_ratio_mode, fit_ratio_tau

    rng = np.random.default_rng(int(f2))
    f = np.arange(2.0, 150.0)
    s = 2j * np.pi * f
    J2, Jm = 1.0, mu  # engine and the inertia between (the shaft drives Jm, Jm drives the engine)
    c1, d1 = (2 * np.pi * f1) ** 2 * 0.5, 2 * 0.08 * 2 * np.pi * f1 * 0.5
    c2, d2 = (2 * np.pi * f2) ** 2 * Jm * J2 / (Jm + J2), 2 * 0.05 * 2 * np.pi * f2 * Jm * J2 / (Jm + J2)
    k1, k2 = d1 + c1 / s, d2 + c2 / s
    T = k1 * k2 / ((Jm * s + k1) * (J2 * s + k2) + J2 * s * k2) * np.exp(-s * tau_s)
    T = T * (1 + 0.01 * (rng.standard_normal(f.size) + 1j * rng.standard_normal(f.size)))
    w = np.ones(f.size)
    two = fit_ratio_tau(f, T, w, 0.012)
    between, _ = fit_ratio_mode(f, T, w, two, 0.012, variant="between")
    beyond, _ = fit_ratio_mode(f, T, w, two, 0.012, variant="engine")
    assert between.misfit(f, T, w) < 0.2 * two.misfit(f, T, w)
    assert between.misfit(f, T, w) < 0.5 * beyond.misfit(f, T, w)
    assert between.tau_s == pytest.approx(tau_s, abs=2e-4)
    # its poles are those of the chain dyno held still (the transfer does not see the dyno's inertia)
    held = linear_modes(1e9, J2, c1, d1, (Jm, c2, d2), "between")
    assert sorted(between.poles_hz()) == pytest.approx(sorted(m["f_hz"] for m in held), rel=0.01)


def test_chain_modes_are_the_simulators():
    from online_id.bench.plant import linear_modes
    from online_id.diagnose.bench_effects import chain_modes

    J1, J2, J3, c, d, c3, d3 = 0.8, 0.35, 0.1, 6000.0, 4.0, 2.0e4, 3.0
    ours = chain_modes((J1, J2, J3), [(0, 1, c, d), (0, 2, c3, d3)])
    sim = linear_modes(J1, J2, c, d, (J3, c3, d3), "dyno")
    assert [m[0] for m in ours] == pytest.approx([m["f_hz"] for m in sim], rel=1e-9)
    assert [m[1] for m in ours] == pytest.approx([m["zeta"] for m in sim], rel=1e-9)


@pytest.mark.parametrize("orders, f0", [([0.5, 1.0, 1.5, 2.5, 3.0], 0.5), ([1.5, 2.5], 0.5), ([3.0], 3.0),
                                        ([3.0, 6.0, 9.0], 3.0), ([1.5], 1.5), ([1.0, 3.0], 1.0)])
def test_an_order_family_is_named_by_its_fundamental(orders, f0):
    from online_id.diagnose.bench_effects import family_reading, fundamental

    assert fundamental(orders) == f0
    text = family_reading("engine", orders, 2.0)
    if f0 % 1 and len(orders) > 1:
        assert "one cylinder differs" in text and "misfire" in text
    assert family_reading("dyno", [3.0], 2.0).startswith("order 3 of the dyno")


def _third(plant: dict, ratio: float, f_hz: float, zeta: float, where: str):
    """A further inertia of ``ratio`` times its host's (the dyno beyond it, else the engine) on a spring
    tuned so that, with the host held still, it rings at ``f_hz``; and the chain's added mode."""
    from online_id.bench.plant import linear_modes

    host = plant["J1"] if where == "dyno" else plant["J2"]
    J3 = ratio * host
    jr = host * J3 / (host + J3)
    w = 2 * np.pi * f_hz
    third = ThirdInertia(J3, w * w * jr, 2 * zeta * w * jr, location=where)
    two = linear_modes(plant["J1"], plant["J2"], plant["c_s"], plant["d_s"])[0]["f_hz"]
    modes = linear_modes(plant["J1"], plant["J2"], plant["c_s"], plant["d_s"], (J3, third.c_2, third.d_2), where)
    return third, max(modes, key=lambda m: abs(np.log(m["f_hz"] / two)))["f_hz"]


@pytest.mark.slow
@pytest.mark.parametrize("plant, seed, ratio, f_hz, where", [("a", 31, 0.3, 70.0, "between"),
                                                            ("b", 32, 0.15, 95.0, "between"),
                                                            ("a", 33, 0.15, 80.0, "dyno"),
                                                            ("b", 34, 0.1, 60.0, "dyno")])
def test_an_unmeasured_inertia_is_a_mode_where_it_sits(plant, seed, ratio, f_hz, where):
    """Between the shaft and the engine (a dual-mass flywheel, the engine sensor on the engine: the old fit
    named it a sensor delay of a few ms) or beyond the dyno (invisible in the speed transfer): named an
    additional mode at the chain's added mode (within 2 %) and at its place, and not a delay."""
    third, f_true = _third(PLANTS[plant], ratio, f_hz, 0.05 if where == "between" else 0.15, where)
    sc = BenchScenario(operating_points=POINTS, seed=seed, **PLANTS[plant], third_inertia=third)
    r = diagnose_bench(series_of(sc), max_effects=1)
    c = first(r)
    assert c.kind == "additional_mode", [x.as_dict() for x in r.candidates[0]]
    assert c.params["location"] == where
    assert c.params["freq_hz"] == pytest.approx(f_true, rel=0.02)
    assert r.steps[0].summary_after < 1.0


@pytest.mark.slow
@pytest.mark.parametrize("plant, seed, cylinder, excess", [("a", 41, 2, 0.3), ("b", 42, 0, 0.2)])
def test_one_cylinder_that_differs_is_the_half_order_family(plant, seed, cylinder, excess):
    """One cylinder compressing more than the others adds every half order of the engine: named order 0.5
    of the engine (the fundamental) with its members and a reading, not a single order 1.5."""
    strength = [1.0] * 4
    strength[cylinder] += excess
    sc = BenchScenario(operating_points=POINTS, seed=seed, **PLANTS[plant], cylinder_strength=tuple(strength))
    c = first(diagnose_bench(series_of(sc), max_effects=1))
    assert c.kind == "rotation_order_disturbance"
    assert c.params["order"] == 0.5 and c.params["shaft"] == "engine"
    members = c.params["family_orders"]
    assert len(members) >= 3 and any(k % 1 for k in members) and all(k % 2 for k in members)
    assert "one cylinder differs" in c.params["reading"]


@pytest.mark.slow
@pytest.mark.parametrize("plant, seed, order, points", [
    ("b", 43, 7.0, (OperatingPoint(1500, 14), OperatingPoint(2100, 14), OperatingPoint(2600, 14))),
    ("a", 44, 9.0, (OperatingPoint(1200, 14), OperatingPoint(1800, 14), OperatingPoint(2500, 14)))])
def test_a_dyno_order_above_the_decimated_band_is_found_at_the_recordings_rate(plant, seed, order, points):
    """Order 7 or 9 of the dyno at 140-375 Hz in a 1 kHz record: above the 500 Hz path's 200 Hz passband
    on some plateau, so judged at the recording's own rate (the decimated path filtered it out)."""
    sc = BenchScenario(operating_points=points, seed=seed, **PLANTS[plant],
                       effects=Effects(order_torque=OrderTorque("dyno", order, 5.0, 0.4)))
    r = diagnose_bench(series_of(sc), max_effects=1)
    c = first(r)
    assert c.kind == "rotation_order_disturbance" and c.params["order"] == order and c.params["shaft"] == "dyno"
    assert r.steps[0].summary_after < 1.0


@pytest.mark.slow
def test_a_bench_read_through_the_generic_options_gives_the_bench_answer(tmp_path, capsys):
    """One diagnosis: the same recording, read as a bench file or with --input-col/--speed-col, is
    diagnosed by one engine and gives the same effects and figures."""
    cfg = tmp_path / "b.yaml"
    cfg.write_text("operating_points: [{speed_rpm: 1200, duration_s: 14}, {speed_rpm: 1700, duration_s: 14}, "
                   "{speed_rpm: 2200, duration_s: 14}]\nseed: 3\n"
                   "effects: {order_torque: {shaft: engine, order: 1.5, amplitude_nm: 5.0}}\n")
    csv = tmp_path / "b.csv"
    assert main(["simulate", "--config", str(cfg), "--out", str(csv)]) == 0
    capsys.readouterr()
    assert main(["diagnose", str(csv), "--json", "--max-effects", "1"]) == 0
    bench = json.loads(capsys.readouterr().out)
    assert main(["diagnose", str(csv), "--input-col", "dyno_torque_nm", "--output-col", "dyno_speed_rpm",
                 "--time-col", "time_s", "--speed-col", "dyno_speed_rpm:dyno", "--speed-col",
                 "engine_speed_rpm:engine", "--speed-unit", "rpm", "--json", "--max-effects", "1"]) == 0
    generic = json.loads(capsys.readouterr().out)
    assert "bench" in generic.pop("read_as")
    assert bench["result"] == "rotation_order_disturbance" == generic["result"]
    assert generic["effects"] == bench["effects"]
    assert generic["error_after"]["rms"] == pytest.approx(bench["error_after"]["rms"])
    assert generic["error_before"] == bench["error_before"]


@pytest.mark.slow
@pytest.mark.parametrize("plant, seed, points", [
    ("a", 45, (OperatingPoint(3200, 36),)),
    ("b", 46, (OperatingPoint(2600, 14), OperatingPoint(3000, 14), OperatingPoint(3300, 14)))])
def test_a_once_per_revolution_line_above_the_resonance_is_never_a_mode(plant, seed, points):
    """A strong order-1 torque on the engine above the resonance, at one speed or three: the bench path
    names no additional mode at the line (it is the rotation order, or at one speed a line that cannot be
    told from one fixed in Hz)."""
    sc = BenchScenario(operating_points=points, seed=seed, **PLANTS[plant], compression_nm=0.0,
                       effects=Effects(order_torque=OrderTorque("engine", 1.0, 15.0, 0.2)))
    r = diagnose_bench(series_of(sc), max_effects=2)
    c = first(r)
    assert c.kind in ("rotation_order_disturbance", "fixed_frequency_disturbance")
    if len(points) > 1:
        assert c.kind == "rotation_order_disturbance" and c.params["order"] == 1.0
    for st in r.steps:
        if st.candidate.kind == "additional_mode":
            f = st.candidate.params["freq_hz"]
            assert all(abs(f - p.speed_rpm / 60.0) > 0.03 * f for p in r.series.plateaus)


@pytest.mark.slow
@pytest.mark.parametrize("seed", [60120, 90180])
def test_a_branch_that_takes_the_fast_plateaus_engine_orders_is_no_mass(tmp_path, capsys, monkeypatch, seed):
    """Clean benches of the chain family (development cases; 90180 was held out until it showed this) whose
    four-cylinder engine's orders sweep into the top of the branch band on the fast plateaus: a branch there
    took 2-7 % of the torque balance and was named an additional mode, while on the slowest plateau it took
    0.1-1 %. A mass on the dyno takes its share on every plateau (BRANCH_EVERY), so nothing is named; the
    candidate stays listed with its per-plateau shares."""
    from online_id.evaluation.chain import prepare_case

    spec, argv = prepare_case(seed, False, tmp_path)
    assert spec["kind"] == "clean" and spec["layout"] == "bench" and argv[-1] == "--json"
    monkeypatch.chdir(tmp_path)
    assert main(argv) == 0
    doc = json.loads(capsys.readouterr().out)
    assert doc["effects"] == [], doc["effects"]
    branches = [c for c in doc["candidates"][0] if c["kind"] == "additional_mode" and "plateau_gains" in c["params"]]
    assert branches, [c["kind"] for c in doc["candidates"][0]]
    shares = branches[0]["params"]["plateau_gains"]
    assert min(shares) < 0.5 * float(np.mean(shares))
    assert branches[0]["t_stat"] == 0.0 and "weakest plateau" in branches[0]["params"]["set_aside"]


@pytest.mark.slow
def test_a_clean_calibration_bench_of_the_chain_family_names_nothing(tmp_path, capsys, monkeypatch):
    """60030, a clean calibration bench (docs/diagnose.md, thresholds): its Coulomb-friction score rose
    to 0.0092 (t 4.8) with later changes and was named at the old threshold (0.00847); the calibration
    rule (1.1 x the largest significant clean score) gives 0.0101."""
    from online_id.evaluation.chain import prepare_case

    spec, argv = prepare_case(60030, False, tmp_path)
    assert spec["kind"] == "clean" and spec["layout"] == "bench"
    monkeypatch.chdir(tmp_path)
    assert main(argv) == 0
    doc = json.loads(capsys.readouterr().out)
    assert doc["effects"] == [], [e["kind"] for e in doc["effects"]]
    coulomb = [c for c in doc["candidates"][0] if c["kind"] == "coulomb_friction"][0]
    assert coulomb["gain"] < THRESHOLDS["coulomb_friction"]
