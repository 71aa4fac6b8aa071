"""The chain family's files: what is written is what the truth says, encoders read back give the speed."""

import json
import shlex

import numpy as np
import pytest
import yaml

from online_id.bench.chain_sensors import RPM_PER_RAD_S, Sampler
from online_id.evaluation.chain_cases import draw_case
from online_id.evaluation.chain_files import AngleColumn, RigDescription, rig_command, write_case
from online_id.evaluation.chain_world import measure, plateaus_of, reference_element, simulate_case


def _short(seed: int) -> dict:
    """Case ``seed`` (quick) with short plateaus, so that a test simulates a few seconds."""
    spec = draw_case(seed, quick=True)
    n = len(spec["plateaus"]["speeds_rpm"])
    spec["plateaus"].update(hold_s=[3.0] * n, ramp_s=1.0, lead_s=2.0)
    return spec


def _written(tmp_path, seed):
    spec = _short(seed)
    record = simulate_case(spec)
    argv = write_case(spec, measure(spec, record), tmp_path)
    truth = json.loads((tmp_path / "truth.json").read_text())
    return spec, record, argv, truth


def _read(path):
    header = path.read_text().split("\n", 1)[0].split(",")
    return header, np.loadtxt(path, delimiter=",", skiprows=1, ndmin=2)


def _option_values(argv, option):
    return [argv[i + 1] for i, a in enumerate(argv) if a == option]


@pytest.mark.parametrize("seed", [107, 114, 117, 119])
def test_the_bench_files_agree_with_the_truth(tmp_path, seed):
    spec, record, argv, truth = _written(tmp_path, seed)
    f = truth["files"]
    header, data = _read(tmp_path / f["csv"])
    assert header == f["order"] and data.shape[0] == truth["rows"][f["csv"]]
    cfg = yaml.safe_load((tmp_path / f["config"]).read_text())
    assert cfg["columns"] == {k: f["columns"][k] for k in ("time", "dyno_speed", "engine_speed", "dyno_torque")}
    assert cfg["units"] == {"time": f["time_unit"], "speed": f["speed_unit"], "torque_sign": f["torque_sign"]}
    ppr = truth["engine"]["cylinders"] / 2
    given = cfg.get("model", {}).get("pulses_per_rev") or float(_option_values(argv, "--pulses-per-rev")[0])
    assert given == ppr
    assert truth["command"][1:] == argv and argv[1] == f["csv"]
    assert _option_values(argv, "--demand-col") == ([f["demand"]] if f["demand"] else [])

    col = {name: data[:, i] for i, name in enumerate(header)}
    t = col[f["columns"]["time"]] / (1000.0 if f["time_unit"] == "ms" else 1.0)
    assert np.median(np.diff(t)) == pytest.approx(1 / spec["fs_hz"], rel=1e-6)
    t_sim = t - f["time_offset_s"] + spec["plateaus"]["lead_s"]
    smp = Sampler(record)
    for role in ("engine", "dyno"):
        v = col[f["columns"][f"{role}_speed"]]
        el = next(i for i, e in enumerate(spec["elements"]) if e["role"] == role)
        delay = spec["effect"]["delay_s"] if spec["kind"] == "sensor_delay" and spec["effect"]["signal"] == \
            f"{role}_speed" else 0.0
        if f["speed_unit"] in ("deg", "rad"):
            angle = np.radians(v) if f["speed_unit"] == "deg" else v
            rpm = np.diff(angle) / np.diff(t) * RPM_PER_RAD_S
            true = np.diff(smp.angle(el, t_sim, delay)) / np.diff(t) * RPM_PER_RAD_S
        else:
            rpm = v * (1.0 if f["speed_unit"] == "rpm" else RPM_PER_RAD_S)
            true = smp.counter_speed(el, t_sim, 1 / spec["fs_hz"], delay) * RPM_PER_RAD_S
        step_rpm = {"rpm": f["speed_step"], "rad/s": f["speed_step"] * RPM_PER_RAD_S,
                    "deg": np.radians(f["speed_step"]) * spec["fs_hz"] * RPM_PER_RAD_S * np.sqrt(2),
                    "rad": f["speed_step"] * spec["fs_hz"] * RPM_PER_RAD_S * np.sqrt(2)}[f["speed_unit"]]
        expected_std = np.hypot(f["speed_noise_rpm"], step_rpm / np.sqrt(12))
        assert np.std(rpm - true) == pytest.approx(expected_std, rel=0.2)
        for (a, b, _w), want in zip(plateaus_of(spec).windows(), truth["plateaus"]["speeds_rpm"]):
            sel = (t_sim[:rpm.size] > a + 1.0) & (t_sim[:rpm.size] < b)
            assert np.median(rpm[sel]) == pytest.approx(want, rel=5e-3)
        if delay:  # the file is the speed of the delayed instant, not of the instant itself
            late = smp.counter_speed(el, t_sim, 1 / spec["fs_hz"]) * RPM_PER_RAD_S
            assert np.std(rpm - late) > 3 * np.std(rpm - true)
    torque = col[f["columns"]["dyno_torque"]]
    if truth["engine"]["indicated_nm"] == 0:  # a motored engine: the dyno drives it
        assert np.sign(np.mean(torque)) == (-1 if f["torque_sign"] == "braking" else 1)


def test_degree_and_count_encoders_written_and_read_back_give_the_speed(tmp_path):
    spec, record, argv, truth = _written(tmp_path, 116)
    f = truth["files"]
    assert {e["unit"][:6] for e in f["encoders"]} == {"deg", "counts"}  # both kinds in this case
    header, data = _read(tmp_path / f["sensor"])
    col = {name: data[:, i] for i, name in enumerate(header)}
    t_file = col[f["sensor_time"]]
    t_sim = t_file - f["clock_origin_s"] + spec["plateaus"]["lead_s"]
    smp = Sampler(record)
    units = {v.split(":")[0]: v.split(":")[2] for v in _option_values(argv, "--angle-col")}
    rates = np.asarray(record.network.rates(reference_element(spec)))
    for k, enc in enumerate(f["encoders"]):
        unit = units[enc["column"]]
        raw = col[enc["column"]]
        angle = np.radians(raw) if unit == "deg" else 2 * np.pi * raw / int(unit[6:])
        dt = np.diff(t_file)
        speed = np.diff(angle) / dt
        delay = spec["effect"]["delay_s"] if k == 0 else 0.0
        true = np.diff(smp.angle(enc["element"], t_sim, delay)) / dt
        step = 2 * np.pi / enc["cpr"]
        stamp = 1e-6 * np.abs(true)  # the time column has microseconds
        assert np.all(np.abs(speed - true) <= (step + stamp) / dt + 1e-9)
        for (a, b, _w), want in zip(plateaus_of(spec).windows(), truth["plateaus"]["speeds_rpm"]):
            sel = (t_sim[1:] > a + 1.0) & (t_sim[1:] < b)
            assert np.mean(speed[sel]) * RPM_PER_RAD_S == pytest.approx(want * rates[enc["element"]], rel=3e-3)


def test_the_rig_files_agree_with_the_truth_and_the_command(tmp_path):
    spec, _record, argv, truth = _written(tmp_path, 152)
    f = truth["files"]
    drive_header, drive = _read(tmp_path / f["drive"])
    sensor_header, sensor = _read(tmp_path / f["sensor"])
    assert drive_header == [f["drive_time"]] + [f["drive_columns"][k] for k in
                                                ("drive_set", "drive_meas", "load_set", "load_meas")]
    assert sensor_header == [f["sensor_time"]] + [e["column"] for e in f["encoders"]] + [
        q["column"] for q in f["shaft_torques"]]
    assert drive.shape[0] == truth["rows"][f["drive"]] and sensor.shape[0] == truth["rows"][f["sensor"]]
    # one clock: both time columns in one time base, the sensor logger starting about a second apart
    start = sensor[0, 0] - drive[0, 0]
    assert start == pytest.approx(f["sensor_start_s"], abs=1e-3) and 0.5 <= abs(start) <= 1.5
    assert np.median(np.diff(drive[:, 0])) == pytest.approx(1 / f["drive_rate_hz"], rel=1e-3)
    jitter = np.std(np.diff(drive[:, 0]) - 1 / f["drive_rate_hz"]) / np.sqrt(2)
    assert jitter == pytest.approx(f["drive_jitter_s"], rel=0.2, abs=1e-6)
    assert argv[1] == f["drive"] and _option_values(argv, "--second-file") == [f["sensor"]]
    assert _option_values(argv, "--input-col") == [f["drive_columns"][f["input"]]]
    assert _option_values(argv, "--output-col") == [f["encoders"][0]["column"]]
    assert "--same-clock" in argv and "--differentiate-output" in argv
    assert truth["expected"]["signal"] == [f["drive_columns"][f["input"]]]  # the delayed column of this case


def test_the_command_of_a_rig_description():
    d = RigDescription(first_file="drive.csv", second_file="sensor.csv", time_col="time", second_time_col="ts",
                       input_col="drive torque", output_col="first encoder",
                       angles=(AngleColumn("first encoder", "motor", "deg"), AngleColumn("enc2", "mid", "counts4096")),
                       same_clock=True, clock_offset_s=0.25, differentiate_output=True, settings=("--na", "auto"))
    assert shlex.join(rig_command(d)) == (
        "diagnose drive.csv --second-file sensor.csv --time-col time --second-time-col ts "
        "--input-col 'drive torque' --output-col 'first encoder' --angle-col 'first encoder:motor:deg' "
        "--angle-col enc2:mid:counts4096 --same-clock --clock-offset-s 0.25 --differentiate-output --na auto --json")


def test_a_seed_draws_the_same_case_and_kinds_cycle():
    assert draw_case(131) == draw_case(131)
    assert [draw_case(s, quick=True)["kind"] for s in range(900, 909)] == [
        "clean", "rotation_order", "cylinder_family", "fixed_frequency", "structural_resonance",
        "unmeasured_inertia", "backlash", "coulomb_friction", "sensor_delay"]


@pytest.mark.slow
def test_every_seed_draws_a_case_and_a_line_on_shafts_turning_together_names_both():
    """Gear ratios that make every line of a shaft an integer order of another (2, 2, 4, 1: the last two
    shafts turn together) still give a rotation-order case, on a shaft that turns with another, and
    either shaft is right."""
    for seed in range(60000, 60400):
        draw_case(seed)
    spec = draw_case(60265)
    eff = spec["effect"]
    assert spec["kind"] == "rotation_order" and eff["turns_with"]
    for shaft in [eff["shaft"]] + eff["turns_with"]:
        assert shaft in spec["expected"]["shaft"]
    ratios = [j["ratio"] for j in spec["joints"]]
    assert ratios[-1] == 1.0


def test_the_runner_end_to_end_on_one_bench(tmp_path):
    """One quick clean bench through the whole runner: files, the CLI as a child process, strict scoring; the
    outcome is the diagnosis's, the structure is the runner's."""
    from online_id.evaluation.chain import run_family

    lines = []
    records, summary = run_family([108], tmp_path, quick=True, jobs=1, report=lines.append)
    (rec,) = records
    case = tmp_path / "case-108"
    assert {"truth.json", "bench.yaml", "diagnosis.json", "diagnosis.stderr", "score.json"} <= {
        p.name for p in case.iterdir()}
    assert not (case / "bench.csv").exists()  # data are redrawn from the seed, not kept
    assert rec["failure"] in (None, "json-nan", "json", "crash", "input", "cli", "timeout")
    assert rec["kind_right"] == (rec["failure"] is None and rec["named"] == "none")
    assert len(lines) == 1 and "seed 108 clean (bench)" in lines[0]
    assert (tmp_path / "table.md").read_text().startswith("| truth kind")
    assert (tmp_path / "confusion.png").stat().st_size > 1000
    assert json.loads((tmp_path / "results.json").read_text())["cases"][0]["seed"] == 108
