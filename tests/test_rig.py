"""Multi-shaft rig simulator, clock alignment, the ratio order grid, the acceptance guard."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from online_id.bench.rig import OrderDisturbance, random_rig, simulate_rig
from online_id.cli import main
from online_id.diagnose import DiagnoseData, diagnose
from online_id.diagnose.align import resample_uniform
from online_id.diagnose.diagnosis import _guard, ErrorFigures
from online_id.diagnose.shafts import assign_order, parse_shafts, snap_ratio
from online_id.errors import ConfigError, InputDataError
from online_id.io.table_csv import write_csv_columns
from online_id.evaluation.diagnose_rigs import identifiable_orders, rig_data, rig_spec, run_case


def _records(seed: int, **overrides):
    spec = random_rig(np.random.default_rng(seed), **overrides)
    rec = simulate_rig(spec, seed)
    drive, sensor = dict(rec.drive), dict(rec.sensor)
    r1 = resample_uniform(drive.pop("time_s"), drive, "drive", "time_s")
    r2 = resample_uniform(sensor.pop("time_s"), sensor, "sensor", "time_s")
    return spec, rec, r1, r2


@pytest.mark.parametrize("seed", [11300, 11301])
def test_rig_shafts_turn_at_their_gear_ratios_and_clock_drifts(seed):
    spec, rec, _, _ = _records(seed)
    assert spec.n_shafts >= 3
    mean = rec.truth_speed_rad_s[len(rec.truth_time_s) // 2:].mean(axis=0)
    np.testing.assert_allclose(mean / mean[0], spec.speed_factors(), rtol=1e-3)
    # the sensor clock runs offset + (1 + drift) t from the true start
    assert rec.sensor["time_s"][0] == pytest.approx(spec.clock_offset_s, abs=2e-3)
    # encoder angles are whole counts
    q = 2 * np.pi / spec.counts_per_rev
    a = rec.sensor[f"{spec.names[1]}_angle_rad"]
    np.testing.assert_allclose(a / q, np.round(a / q), atol=1e-6)


@pytest.mark.parametrize("seed", [11302, 11303, 11304, 11305, 11306])
def test_alignment_recovers_offset_and_drift(seed):
    spec = random_rig(np.random.default_rng(seed))
    data = rig_data(spec, seed)
    c = data.notes["clock"]
    assert c["mode"] == "estimated"  # the clocks plainly differ: the sensor lags by 0.1-2 s
    assert abs(c["offset_s"] - spec.clock_offset_s) < 1e-3  # 1 ms
    assert abs(c["drift_ppm"] - spec.clock_drift_ppm) < 5.0  # 5 ppm
    assert data.notes is not None and set(data.shaft_rates) == set(spec.names)


def test_resampling_reports_jitter_and_refuses_gaps():
    rng = np.random.default_rng(1)
    t = np.arange(2000) * 1e-3 + rng.uniform(-1e-4, 1e-4, 2000)
    r = resample_uniform(t, {"x": np.sin(t)}, "f.csv", "time")
    assert r.resampled and 3e-5 < r.jitter_rms_s < 8e-5 and r.jitter_max_s <= 1.01e-4
    assert r.fs_hz == pytest.approx(1000.0, rel=1e-4)
    t[1000:] += 0.5
    with pytest.raises(InputDataError, match="gap"):
        resample_uniform(t, {"x": t}, "f.csv", "time")


def test_order_grid_assigns_a_line_to_the_shaft_where_it_is_the_smallest_integer_order():
    rates = {"motor": 1.0, "mid": 1 / 3, "out": 1 / 12}
    # orders of the slowest shaft (out): order 12 of out = order 1 of motor
    assert assign_order(12.0, "out", rates, 0.05)[:2] == ("motor", 1)
    assert assign_order(8.0, "out", rates, 0.05)[:2] == ("mid", 2)  # 2x the intermediate shaft
    assert assign_order(1.0, "out", rates, 0.05)[:2] == ("out", 1)  # a third of mid's... rate
    assert assign_order(2.0, "out", rates, 0.05)[:2] == ("out", 2)
    assert assign_order(6.5, "out", rates, 0.05) is None
    assert snap_ratio(0.33340) == pytest.approx(1 / 3)


def test_shaft_options_are_checked():
    s = parse_shafts(["w:motor"], ["a_out:out"], ["mid=motor/3"])
    assert [(x.name, x.kind) for x in s] == [("motor", "speed"), ("out", "angle"), ("mid", "geared")]
    assert s[2].ratio == 3.0
    with pytest.raises(ConfigError, match="--gear-ratio"):
        parse_shafts([], [], ["mid:motor:3"])
    with pytest.raises(ConfigError, match="> 0"):
        parse_shafts([], [], ["mid=motor/0"])


def test_identifiable_orders_leave_out_orders_of_a_faster_shaft():
    spec = random_rig(np.random.default_rng(11307), ratios=(2.0, 3.0), inertias_kgm2=(0.03, 0.1, 1.0),
                      stiffness_nm_rad=(400.0, 4000.0), damping_nms_rad=(0.2, 1.0))
    assert identifiable_orders(spec, 0) == [1, 2, 3, 4, 5]
    assert identifiable_orders(spec, 1) == [1, 3, 5]  # 2, 4 of the middle shaft are orders 1, 2 of the motor
    assert identifiable_orders(spec, 2) == [1, 2, 4, 5]  # 3 of the load is order 1 of the middle shaft


def test_guard_refuses_a_step_that_worsens_the_simulation_fit():
    cur = ErrorFigures(rms=1.0, fit_pct=80.0)
    assert _guard(cur, 0.9, 81.0) == ""
    assert "simulation fit" in _guard(cur, 0.5, 79.9)
    assert "one-step RMS" in _guard(cur, 1.01, 90.0)


def test_guard_in_the_loop_refuses_an_overfitting_step():
    """A record whose held-out part has a fixed line the estimation part lacks: any term fitted on the
    estimation part is noise there; what is accepted must lower both held-out figures."""
    rng = np.random.default_rng(4)
    n = 3000
    u = rng.standard_normal(n)
    y = np.zeros(n)
    for t in range(2, n):
        y[t] = 1.5 * y[t - 1] - 0.7 * y[t - 2] + 0.5 * u[t - 1] + 0.05 * rng.standard_normal()
    w = np.full(n, 50.0) + 0.5 * rng.standard_normal(n)
    data = DiagnoseData(u, y, 100.0, "u", "y", {"a": w, "b": w / 3.0}, shaft_rates={"a": 1.0, "b": 1 / 3})
    d = diagnose(data, na=2, nb=2, nc=1, min_explained=0.0)
    for e in d.effects:
        assert e.error_after.rms < e.error_before.rms and e.error_after.fit_pct > e.error_before.fit_pct
    assert all((c.refused != "") or not c.accepted for c in d.candidates if not c.significant or c.refused)
    assert any("one operating point" in w for w in d.warnings)
    doc = d.as_dict()
    assert doc["baseline"]["modes"] and all("stable" in m for m in doc["baseline"]["modes"])


WEAK_INTERMEDIATE = pytest.mark.xfail(strict=True, reason=(
    "order 1 of an intermediate shaft turning at half the motor's rate (4-9 Hz): with 15 s plateaus its line "
    "reaches 7.8x the order-grid floor, under the 16x threshold; the same line at one plateau (a 7.2 Hz Welch "
    "peak) is refused by the guard (simulation fit 99.1 % -> 92.1 %)"))
WEAK_LOAD = pytest.mark.xfail(strict=True, reason=(
    "order 5 of a load turning at 1/16 of the motor (2.5-5.5 Hz, within the load PI loop's 2-4 Hz band): with "
    "15 s plateaus its line reaches 9.1x the order-grid floor, under the 16x threshold"))


@pytest.mark.slow
@pytest.mark.parametrize("seed, shaft", [(11310, 0), pytest.param(11311, 1, marks=WEAK_INTERMEDIATE), (11312, 2),
                                         pytest.param(11313, 3, marks=WEAK_LOAD)])
def test_order_on_a_shaft_is_named_first_against_that_shaft(seed, shaft):
    # motor, intermediate, intermediate and load (orders 3, 1, 5, 5 as drawn), on the first four seeds of the
    # tests' block, with 15 s plateaus (the evaluation's are 30 s; docs/diagnose.md gives its rates)
    r = run_case(seed, shaft, 0.3, plateau_s=15.0)
    assert r["effects"], r["candidates"]
    e = r["effects"][0]
    assert e["kind"] == "rotation_order_disturbance", r["effects"]
    assert (e["params"]["shaft"], e["params"]["order"]) == (r["true_shaft"], r["true_order"])
    for e in r["effects"]:  # every accepted step lowers the held-out one-step error and raises the fit
        assert e["error_after"]["rms"] < e["error_before"]["rms"]
        assert e["error_after"]["fit_pct"] > e["error_before"]["fit_pct"]


@pytest.mark.slow
@pytest.mark.parametrize("seed", [11320, 11321, 11322])
@pytest.mark.xfail(strict=True, reason=(
    "the known limit: orders 1-2 of the load (0.3-2 Hz) are rejected by the load's PI speed loop (2-4 Hz); "
    "their line in the motor speed stays at 2-8x the local floor, under the 16x a clean rig reaches by chance "
    "(docs/diagnose.md); on 11320-11323 none was named, 11321 named an additional mode instead"))
def test_load_orders_1_2_are_named_first(seed):
    spec = rig_spec(seed, None, 0.3)
    load = spec.n_shafts - 1
    order = 2 if 2 in identifiable_orders(spec, load) else 1
    r = run_case(seed, load, 0.3, plateau_s=15.0, order=order)
    assert r["effects"], r["candidates"]
    e = r["effects"][0]
    assert (e["kind"], e["params"].get("shaft"), e["params"].get("order")) == (
        "rotation_order_disturbance", r["true_shaft"], order)


@pytest.mark.slow
@pytest.mark.parametrize("seed", [11314, 11315])
def test_clean_rig_reports_no_effect(seed):
    r = run_case(seed, None, 0.0, plateau_s=15.0)
    assert r["found_kind"] == "clean", r["effects"]


def test_cli_diagnose_two_files_with_shafts(tmp_path, capsys):
    spec = random_rig(np.random.default_rng(11316), n_stages=2)
    spec = replace(spec, disturbance=OrderDisturbance(0, 2.0, 0.5), load_speed_rad_s=spec.load_speed_rad_s,
                   plateau_s=12.0)
    rec = simulate_rig(spec, 11316)
    fmt = {n: "%.9f" if n == "time_s" else "%.7f" for n in (*rec.drive, *rec.sensor)}
    write_csv_columns(tmp_path / "drive.csv", rec.drive, fmt)
    write_csv_columns(tmp_path / "sensor.csv", rec.sensor, fmt)
    argv = ["diagnose", str(tmp_path / "drive.csv"), "--input-col", "torque_demand_nm", "--output-col",
            "motor_angle_rad", "--differentiate-output", "--time-col", "time_s",
            "--second-file", str(tmp_path / "sensor.csv"), "--angle-col", "motor_angle_rad:motor",
            "--angle-col", f"{spec.names[1]}_angle_rad:mid", "--gear-ratio", "out=mid/" + str(spec.ratios[1]),
            "--sample-rate", "200", "--na", "auto", "--nc", "4", "--max-effects", "0", "--json"]
    assert main(argv) == 0
    import json
    doc = json.loads(capsys.readouterr().out)
    assert abs(doc["recording"]["clock"]["offset_s"] - spec.clock_offset_s) < 1e-3
    assert set(doc["shaft_rates"]) == {"motor", "mid", "out"}
    assert doc["shaft_rates"]["out"] == pytest.approx(1 / (spec.ratios[0] * spec.ratios[1]))
    assert "modes" in doc["baseline"] and "warnings" in doc
    assert doc["baseline"]["na"] in (4, 8, 12, 16, 20) and doc["baseline"]["nb"] == doc["baseline"]["na"]
    assert doc["baseline"]["input_lead"] >= 2 and doc["recording"]["data_path"]["decimation"] == 5
    assert doc["validation_blocks"] == 6
    # bad input: one line naming the file and column / option
    assert main(argv[:-1] + ["--angle-col", "nope:x"]) == 2
    assert "nope" in capsys.readouterr().err
    assert main(argv[:-1] + ["--gear-ratio", "bad"]) == 2
    assert "--gear-ratio" in capsys.readouterr().err


def test_cli_headerless_csv(tmp_path, capsys):
    rng = np.random.default_rng(2)
    n = 1500
    u = rng.standard_normal(n)
    y = np.zeros(n)
    for t in range(1, n):
        y[t] = 0.9 * y[t - 1] + 0.3 * u[t - 1] + 0.01 * rng.standard_normal()
    t = np.arange(n) / 100.0 + rng.uniform(-2e-4, 2e-4, n)
    np.savetxt(tmp_path / "x.csv", np.column_stack((t, u, y)), delimiter=",", fmt="%.7f")
    argv = ["diagnose", str(tmp_path / "x.csv"), "--no-header", "--columns", "t,u,y", "--time-col", "t",
            "--input-col", "u", "--output-col", "y", "--na", "1", "--nb", "1", "--nc", "0", "--json"]
    assert main(argv) == 0
    import json
    doc = json.loads(capsys.readouterr().out)
    assert doc["recording"]["file"]["resampled"] and doc["recording"]["file"]["jitter_rms_s"] > 0
    assert main(argv[:3] + ["--columns", "t,u", *argv[5:]]) == 2
    assert "--columns" in capsys.readouterr().err


def test_csv_default_format_keeps_time_resolution_of_long_records(tmp_path):
    from online_id.io.table_csv import read_csv_columns

    t = 5000.0 + np.arange(10) * 1e-3  # 5000 s into a record, 1 kHz
    write_csv_columns(tmp_path / "t.csv", {"time_s": t, "x": np.arange(10.0)})
    back = read_csv_columns(tmp_path / "t.csv", ["time_s"])["time_s"]
    np.testing.assert_allclose(back, t, rtol=0, atol=1e-7)


def test_split_interleaves_estimation_and_held_out_blocks():
    from online_id.diagnose.data import Split

    one = Split(1000, 0.6)
    assert one.est_runs == [(0, 600)] and one.val_runs == [(600, 1000)]
    six = Split(1200, 0.6, 6)
    est, val = six.est_mask, six.val_index
    assert est.sum() == six.n_est == 720 and val.size == 480
    assert not np.any(est[val]) and len(six.val_runs) == 6
    assert all(e[1] == v[0] for e, v in zip(six.est_runs, six.val_runs))  # each block: estimate, then hold out
    assert np.array_equal(six.est_rows(5), np.flatnonzero(est)[5:])


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_line_on_the_ratio_grid_is_found_against_its_shaft_by_order_tracking(seed):
    """A residual with a line (4.5 % of its variance) at order k of one shaft of a rig whose speed changes (plateaus and a
    ramp) and coloured noise: the grid test names that shaft and order; without the line it names none."""
    from scipy.signal import lfilter

    from online_id.diagnose.effects import shaft_angle
    from online_id.diagnose.residual_tests import RIG_LINE_RATIO, rig_orders

    rng = np.random.default_rng(seed)
    fs, n = 200.0, 18000
    w0 = np.repeat(rng.uniform(50, 75) * np.array([1.0, 1.25, 1.5]), n // 3)
    w0 = lfilter([0.01], [1, -0.99], w0 - w0[0]) + w0[0] + 0.3 * rng.standard_normal(n)  # speed steps, smoothed
    rates = {"motor": 1.0, "mid": 1 / 3, "load": 1 / 12}
    speeds = {k: w0 * r for k, r in rates.items()}
    shaft, k = [("motor", 2), ("mid", 1), ("load", 5)][seed]
    noise = lfilter([1.0], [1.0, -0.9], rng.standard_normal(n))  # coloured like a rig's residual
    line = 0.3 * np.std(noise) * np.sin(k * shaft_angle(speeds[shaft], fs) + rng.uniform(0, 6))
    t = rig_orders(noise + line, speeds, rates, fs)
    assert t is not None and t.candidates, t.detail
    kind, hint = t.candidates[0]
    assert (hint["shaft"], hint["order"]) == (shaft, k), t.detail
    clean = rig_orders(noise, speeds, rates, fs)
    assert not clean.candidates and clean.curve["max_ratio"] < RIG_LINE_RATIO, clean.detail
