"""The detection evaluation: its plan, its summary, the command, and the simulator's friction drift."""

import dataclasses
import json
import math

import numpy as np
import pytest

from online_id.bench import evaluate as ev
from online_id.bench.scenario import BenchScenario, Friction, OperatingPoint
from online_id.bench.simulate import simulate_bench
from online_id.cli import main
from online_id.offline.evaluate import table
from online_id.errors import FieldError


def _f0(sc: BenchScenario) -> float:
    J = sc.J1 * sc.J2 / (sc.J1 + sc.J2)
    return math.sqrt(sc.c_s / J) / (2 * math.pi)


def test_plan_covers_the_hours_and_every_fault_case():
    specs = ev.plan(2.5, 2, seed=3)
    free = [s for s in specs if s.case == "fault-free"]
    assert len(free) == 3
    assert sum(s.scenario.duration_s for s in free) == pytest.approx(2.5 * 3600, abs=3 * 60)
    faults = [s for s in specs if s.case != "fault-free"]
    assert len(faults) == 2 * len(ev.FAULT_CASES)
    for s in faults:
        assert s.t_fault_s is not None and 100.0 < s.t_fault_s < s.scenario.duration_s - 60.0
        assert s.expect in ev.DRIFT_KINDS


def test_random_plants_vary_and_avoid_order_lines():
    f0s, zetas, drifts = [], [], []
    for seed in range(40):
        spec = ev.fault_free_spec(seed, 1800.0)
        sc = spec.scenario
        f0 = _f0(sc)
        f0s.append(f0)
        zetas.append(sc.d_s / (2 * math.sqrt(sc.c_s * sc.J1 * sc.J2 / (sc.J1 + sc.J2))))
        drifts.append(sc.friction.drift)
        speeds = {round(p.speed_rpm / 250) * 250 for p in sc.operating_points}
        assert 3 <= len(speeds) <= 4
        for p in sc.operating_points:
            assert abs(sc.n_cyl / 2 * p.speed_rpm / 60 - f0) > 0.2 * f0
    assert min(f0s) < 20 and max(f0s) > 30
    assert min(zetas) < 0.04 and max(zetas) > 0.07
    assert min(drifts) < -0.2 and max(drifts) > 0.1


def test_summary_counts_false_alarms_and_delays():
    def rr(case, dur, **kw):
        return ev.RunResult(case, 1, dur, 25.0, 0.05, [], **kw)

    results = [
        rr("fault-free", 3600.0, false_alarms=1, alarms=[{"t_s": 10.0, "kind": "FREQ_DRIFT", "severity": 1}]),
        rr("fault-free", 1800.0),
        rr("stiffness -10 %", 250.0, t_fault_s=120.0, warning_delay_s=8.0, fault_delay_s=12.0),
        rr("stiffness -10 %", 250.0, t_fault_s=120.0, warning_delay_s=14.0),
        rr("stiffness -10 %", 250.0, t_fault_s=120.0),
        ev.RunResult("damping +50 %", 2, 250.0, 25.0, 0.05, ["backlash"], t_fault_s=120.0, warning_delay_s=40.0),
        ev.RunResult("damping +50 %", 3, 250.0, 25.0, 0.05, ["backlash", "sensor_delay"], t_fault_s=120.0),
        ev.RunResult("damping +50 %", 4, 250.0, 25.0, 0.05, ["sensor_delay"], t_fault_s=120.0, warning_delay_s=30.0),
    ]
    s = ev.summarize(results)
    assert s["fault_free"]["hours"] == pytest.approx(1.5)
    assert s["fault_free"]["false_alarms_per_hour"] == pytest.approx(1 / 1.5)
    row = next(r for r in s["faults"] if r["case"] == "stiffness -10 %")
    assert (row["runs"], row["detected"], row["missed"], row["fault_level_reached"]) == (3, 2, 1, 1)
    assert row["warning_delay_s_median"] == pytest.approx(11.0) and row["warning_delay_s_worst"] == 14.0
    damp = next(r for r in s["faults"] if r["case"] == "damping +50 %")  # per plant type
    assert (damp["by_plant"]["backlash"]["runs"], damp["by_plant"]["backlash"]["detected"]) == (2, 1)
    assert damp["by_plant"]["no backlash"]["warning_delay_s_median"] == 30.0 and "backlash" not in row["by_plant"]


def test_families_a_and_b_are_summarised_together_per_plant_type_as_well():
    def rr(family, seed, effects, delay):
        return ev.RunResult("damping +50 %", seed, 150.0, 25.0, 0.05, effects, t_fault_s=80.0,
                            warning_delay_s=delay, family=family)

    results = [rr("a", 1, ["backlash"], 70.0), rr("a", 2, ["backlash"], None), rr("a", 3, [], 20.0),
               rr("b", 4, ["backlash"], 25.0), rr("b", 5, ["backlash"], 30.0), rr("b", 6, [], 12.0)]
    rows = {r["family"]: r for r in ev.summarize(results)["faults"] if r["case"] == "damping +50 %"}
    assert set(rows) == {"a", "b", "a+b"}
    both = rows["a+b"]["by_plant"]["backlash"]
    assert (both["runs"], both["detected"], both["warning_delay_s_median"]) == (4, 3, 30.0)
    assert rows["a"]["by_plant"]["backlash"]["warning_delay_s_median"] == 70.0
    assert "a+b" not in {r["family"] for r in ev.summarize(results[:3])["faults"]}  # family (a) alone


def test_friction_drift_changes_the_load_like_warming_oil():
    base = dataclasses.replace(BenchScenario(), operating_points=(OperatingPoint(1500.0, 90.0),), seed=2)
    cold = simulate_bench(dataclasses.replace(base, friction=Friction(b0=8.0, b1=0.1)))
    warm = simulate_bench(dataclasses.replace(base, friction=Friction(b0=8.0, b1=0.1, drift=-0.5, drift_tau_s=20.0)))
    late = slice(80000, 90000)
    ratio = np.mean(warm.dyno_torque_nm[late]) / np.mean(cold.dyno_torque_nm[late])
    assert ratio == pytest.approx(1 - 0.5 * (1 - math.exp(-85 / 20)), abs=0.03)
    early = slice(0, 1000)  # the first chunk (4.5 s) runs at its mid-time factor, 0.95
    assert np.mean(warm.dyno_torque_nm[early]) == pytest.approx(np.mean(cold.dyno_torque_nm[early]), rel=0.08)
    with pytest.raises(FieldError):
        Friction(drift=-1.5)


def test_evaluate_command_writes_table_json_and_plot(tmp_path, capsys, cli_error):
    rc = main(["evaluate", "--hours", "0.04", "--fault-plants", "0", "--jobs", "1", "--out", str(tmp_path)])
    assert rc == 0
    out = capsys.readouterr().out
    assert "Fault-free: 0.0 h in 1 runs" in out
    doc = json.loads((tmp_path / "results.json").read_text())
    assert doc["summary"]["fault_free"]["runs"] == 1 and len(doc["runs"]) == 1
    assert doc["runs"][0]["duration_s"] == pytest.approx(144.0, abs=1.0)
    assert (tmp_path / "table.md").read_text().startswith("Fault-free")
    assert (tmp_path / "evaluation.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    # the summary again from the saved runs, without simulating
    again = tmp_path / "again"
    assert main(["evaluate", "--from-results", str(tmp_path / "results.json"), "--out", str(again)]) == 0
    assert (again / "table.md").read_text() == (tmp_path / "table.md").read_text()
    assert doc["complete"] is True
    # a stopped evaluation leaves its runs so far, marked partial, and they tabulate as they stand
    partial = tmp_path / "partial.json"
    partial.write_text(json.dumps(dict(doc, complete=False)))
    capsys.readouterr()
    assert main(["evaluate", "--from-results", str(partial), "--out", str(tmp_path / "p")]) == 0
    assert "is partial" in capsys.readouterr().err
    assert json.loads((tmp_path / "p" / "results.json").read_text())["complete"] is False
    (tmp_path / "bad.json").write_text("{}")
    assert "bad.json: not a results.json" in cli_error(["evaluate", "--from-results", str(tmp_path / "bad.json")])


def test_evaluate_command_rejects_bad_arguments(cli_error):
    assert cli_error(["evaluate", "--jobs", "0"]).startswith("error: Expected --hours >= 0")


def test_families_a_and_b_follow_how_benches_run():
    specs = ev.plan(1.0, 3, seed=5, families=("a", "b"), cases=("stiffness -10 %", "stiffness -15 %"))
    free = [s for s in specs if s.case == "fault-free"]
    assert [s.family for s in free] == ["short"]  # short plateaus first when families a/b are asked for
    assert all(30.0 <= p.duration_s <= 60.0 for p in free[0].scenario.operating_points[:-1])
    a = [s for s in specs if s.family == "a"]
    b = [s for s in specs if s.family == "b"]
    assert len(a) == len(b) == 3 * 2
    for s in a:  # a fresh service: the fault after 60-120 s over 2-4 points of 30-60 s
        assert s.earlier is None and 60.0 <= s.t_fault_s <= 120.0
        pts = s.scenario.operating_points
        assert all(30.0 <= p.duration_s <= 60.0 for p in pts)
        assert 2 <= len({round(p.speed_rpm, -2) for p in pts}) <= 4
        assert s.scenario.duration_s >= s.t_fault_s + 60.0
    for s in b:  # a later run at other points, with the state of an earlier healthy run
        assert s.earlier is not None and not s.earlier.faults and 30.0 <= s.t_fault_s <= 90.0
        before = {round(p.speed_rpm, -2) for p in s.earlier.operating_points}
        now = {round(p.speed_rpm, -2) for p in s.scenario.operating_points}
        assert 120.0 <= s.earlier.duration_s and not before & now


@pytest.mark.parametrize("plant_type", ["backlash", "no backlash"])
def test_fault_plants_of_one_type(plant_type):
    specs = ev.plan(0.0, 2, seed=3, families=("a", "b", "c"), cases=("damping +50 %", "damping -50 %"),
                    plant_type=plant_type)
    assert len(specs) == 3 * 2 * 2 and len({(s.family, s.seed) for s in specs}) == 6
    assert all((s.scenario.effects.backlash is not None) == (plant_type == "backlash") for s in specs)
    with pytest.raises(ValueError, match="plant_type"):
        ev.plan(0.0, 1, plant_type="linear")


def test_damping_spread_and_change_of_a_run():
    rng = np.random.default_rng(4)
    t = np.arange(0.0, 200.0)
    z = 0.05 * (1 + 0.02 * rng.standard_normal(t.size)) * np.where(t > 120.0, 1.5, 1.0)
    r = ev.RunResult("damping +50 %", 1, 200.0, 25.0, 0.05, [], t_fault_s=120.0,
                     zeta_trace=[[a, b] for a, b in zip(t, z)])
    s = r.zeta_summary()
    assert 1.0 < s["spread_pct"] < 3.0 and 45.0 < s["change_pct"] < 55.0
    assert ev.RunResult("fault-free", 1, 10.0, 25.0, 0.05, []).zeta_summary() == {"spread_pct": None,
                                                                                   "change_pct": None}


def test_an_alarm_of_the_earlier_run_of_family_b_is_a_false_alarm_and_is_acknowledged():
    """Family (b) hands on the state of an earlier healthy run: an alarm that run raises counts as a false
    alarm of the run (it was not counted at all), and it is acknowledged as an operator would, so the
    later run does not start with it latched (which kept every later alarm of its kind from being raised)."""
    from types import SimpleNamespace

    from online_id.records import AlertKind

    acks = []
    pipe = SimpleNamespace(alerts=[], alerts_total=0, detector=SimpleNamespace(active=None),
                           on_command=lambda cmd, t: acks.append(t))
    res = ev.RunResult("stiffness -10 %", 1, 0.0, 20.0, 0.05, [])
    hook = ev._earlier_alarms(res)
    hook(pipe, 10.0, [])
    drift = SimpleNamespace(t_s=12.0, kind=AlertKind.FREQ_DRIFT, severity=1, message="warning")
    other = SimpleNamespace(t_s=12.0, kind=AlertKind.INPUT_FAULT, severity=1, message="input fault")
    pipe.alerts += [drift, other]
    pipe.alerts_total = 2
    pipe.detector.active = drift
    hook(pipe, 12.0, [])
    assert res.false_alarms == 1 and res.alarms[0]["earlier"] is True
    hook(pipe, 30.0, [])
    assert acks == []
    hook(pipe, 42.5, [])
    assert acks == [42.5]


@pytest.mark.parametrize("seed,family,invalid_s", [(1701, "a", 12.0), (1702, "b", 17.0)])
def test_time_to_a_valid_estimate_after_each_change_of_operating_point(seed, family, invalid_s):
    """The summary's revalidation time: from a run's 1 Hz trace of valid estimates and its scenario's points
    (rebuilt from the seed), the time from each ramp's start to the first valid estimate after the gap."""
    spec = ev.family_spec(seed, "stiffness -10 %", family)
    points = spec.scenario.operating_points
    starts, t = [], 0.0
    for p in points[:-1]:
        t += p.duration_s
        starts.append(t)
        t += spec.scenario.ramp_s
    end = t + points[-1].duration_s
    trace = [[float(k), 0.05] for k in range(10, int(end))
             if not any(s + 2.0 <= k < s + invalid_s for s in starts)]  # valid 2 s into each ramp, then not
    res = ev.RunResult("stiffness -10 %", seed, end, 20.0, 0.05, [], zeta_trace=trace, family=family)
    back = ev.revalid_after_changes(res)
    assert len(back) == len(starts)
    assert all(invalid_s <= b < invalid_s + 1.0 for b in back), (back, starts)
    summary = ev.summarize([res, ev.RunResult("fault-free", 1, 60.0, 20.0, 0.05, [])])
    assert summary["revalid_after_change_s"]["changes"] == len(starts)
    assert summary["revalid_after_change_s"]["median"] == pytest.approx(float(np.median(back)))


@pytest.mark.parametrize("t_fault, before, after", [(50.0, {"frequency": 1, "damping": 0}, {"frequency": 1, "damping": 1}),
                                                    (None, {"frequency": 2, "damping": 1}, {"frequency": 0, "damping": 0}),
                                                    (20.0, {"frequency": 0, "damping": 0}, {"frequency": 2, "damping": 1})])
def test_the_alarms_the_confirm_withheld_are_counted_before_and_after_the_fault(monkeypatch, t_fault, before, after):
    """Each run records the alarms the detector asked for and the confirm withheld, split at the fault (a
    fault-free run's all before), without what a restored state brought (family (b)); the summary adds them per
    case and over the fault-free hours, and the table prints them."""
    from types import SimpleNamespace

    steps = {30: ("frequency",), 70: ("frequency", "damping")}  # the pipeline's count grows at these times
    rec = SimpleNamespace(time_s=np.array([0.0, 100.0]), truth={"f0_hz": 20.0, "zeta": 0.05, "effects": {}},
                          to_data=lambda label: None)

    def fake_run(data, settings, on_output=None, state=None, run_label=""):
        pipe = SimpleNamespace(alerts=[], alerts_total=0, last_estimate=None, baseline=SimpleNamespace(bands=()),
                               detector=SimpleNamespace(withheld={"frequency": 4, "damping": 2}, active=None))
        for t in range(101):
            for kind in steps.get(t, ()):
                pipe.detector.withheld[kind] += 1
            on_output(pipe, float(t), [])
        return pipe

    monkeypatch.setattr(ev, "simulate_bench", lambda sc: rec)
    monkeypatch.setattr(ev, "run_bench_data", fake_run)
    spec = ev.RunSpec("fault-free" if t_fault is None else "stiffness -10 %", 1, BenchScenario(), t_fault)
    res = ev.run(spec)
    assert (res.withheld_before_fault, res.withheld_after_fault) == (before, after)
    summary = ev.summarize([res, dataclasses.replace(res, seed=2)])
    if t_fault is None:
        assert summary["fault_free"]["withheld"] == {k: 2 * n for k, n in before.items()}
        assert f"{2 * before['frequency']} frequency, {2 * before['damping']} damping" in table(summary)
    else:
        row = next(r for r in summary["faults"] if r["case"] == spec.case and r["family"] == "c")
        assert row["withheld_after_fault"] == {k: 2 * n for k, n in after.items()}
        assert f"after it {2 * after['frequency']} frequency, {2 * after['damping']} damping" in table(summary)
    old = [dataclasses.replace(r, withheld_before_fault={}, withheld_after_fault={}) for r in (res, res)]
    assert "withheld" not in table(ev.summarize(old))  # a results.json from before the count: no line of zeros
