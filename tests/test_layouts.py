"""Measured layouts: two loggers, columns in either file, angle and speed units, clocks, torsion, bad input.

Seeds 11000-11999 (docs/evaluation-seeds.md): apart from every evaluation range.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from online_id.bench.rig import loggers_rig, random_rig, simulate_rig
from online_id.cli import build_parser, main
from online_id.offline.diagnose_records import read_records
from online_id.cli.evaluate_rig import write_rig, written_angles
from online_id.errors import ConfigError, InputDataError
from online_id.evaluation.diagnose_rigs import rig_data

UNITS = ("deg", "rad", "rev", "counts")


def _rig(tmp_path, seed: int, unit: str, clock_offset_s: float = 0.0, plateau_s: float = 6.0):
    """A two-logger rig of three short speed plateaus, written in ``unit``; returns the recording,
    the files and the unit's full name."""
    spec = loggers_rig(np.random.default_rng(seed), speeds=(0.9, 1.0, 1.1), plateau_s=plateau_s,
                       clock_offset_s=clock_offset_s)
    spec, full = written_angles(spec, unit)
    rec = simulate_rig(spec, seed)
    drive, sensor = write_rig(tmp_path / f"rig{seed}", rec)
    return rec, drive, sensor, full


def _args(argv: list[str]):
    return build_parser("diagnose").parse_args(["diagnose", *argv])


def _base_argv(drive, sensor) -> list[str]:
    return [str(drive), "--second-file", str(sensor), "--time-col", "time_s", "--input-col",
            "drive_torque_set_nm", "--output-col", "encoder1", "--differentiate-output"]


def _truth_at(rec, t: np.ndarray, col: int, what: str = "speed") -> np.ndarray:
    x = rec.truth_speed_rad_s if what == "speed" else rec.truth_angle_rad
    return np.interp(t, rec.truth_time_s, x[:, col])


def _smooth(x: np.ndarray, n: int = 20) -> np.ndarray:
    return np.convolve(x, np.ones(n) / n, mode="valid")


@pytest.mark.parametrize("seed", range(11000, 11008))
def test_two_loggers_read_in_any_unit_on_one_clock(tmp_path, seed, capsys):
    """Randomised: angle unit (deg, rad, rev, counts), given once or per column, one clock with a known
    offset or none, the sensor logger starting about 1 s late: speeds at full rate in rad/s match the
    truth sample for sample on the drive logger's time base, the torsion is the twist of the stage."""
    rng = np.random.default_rng(seed)
    unit = UNITS[seed % len(UNITS)]  # each unit twice over the eight seeds
    offset = float(rng.uniform(-3.0, 3.0)) if rng.integers(2) else 0.0
    rec, drive, sensor, full = _rig(tmp_path, seed, unit, offset)
    per_column = bool(rng.integers(2))
    cols = [("encoder1", "motor"), ("encoder2", "stage1"), ("encoder3", "mid"), ("encoder5", "load")]
    argv = _base_argv(drive, sensor) + ["--torsion", "stage1:mid"]
    for c, s in cols:
        argv += ["--angle-col", f"{c}:{s}" + (f":{full}" if per_column else "")]
    if not per_column:
        argv += ["--angle-unit", full]
    stated = bool(offset or rng.integers(2))
    if stated:
        argv += ["--same-clock", "--clock-offset-s", repr(offset)]
    data = read_records(_args(argv))
    err = capsys.readouterr().err
    assert "warning" not in err, err
    lay, clock = data.notes["layout"], data.notes["clock"]
    assert clock["mode"] == "same" and not clock["estimated"] and clock["offset_s"] == offset
    assert ("one clock (--same-clock)" if stated else "one clock assumed") in clock["text"]
    assert clock["misfit"] is None
    assert all(v["unit"] == full for v in lay["shafts"].values())
    assert data.fs_hz == pytest.approx(1000.0, rel=1e-3)  # no --sample-rate: the full rate
    assert data.shaft_rates == pytest.approx({"motor": 1.0, "stage1": 1 / 3, "mid": 1 / 3, "load": 1 / 12})
    # the drive logger is the time base (true time); the sensor logger starts about 1 s later
    t = lay["t0_s"] + np.arange(len(data)) / data.fs_hz
    assert lay["t0_s"] == pytest.approx(rec.spec.sensor_start_s, abs=2e-3)
    for k, (_, shaft) in enumerate(cols):
        col = {"motor": 0, "stage1": 0, "mid": 1, "load": 2}[shaft]
        factor = 1 / 3 if shaft == "stage1" else 1.0
        w, ref = data.shaft_speeds_rad_s[shaft], factor * _truth_at(rec, t, col)
        dev = _smooth(w) - _smooth(ref)  # 20 ms averages: encoder quantisation averaged out
        assert np.sqrt(np.mean(dev[100:-100] ** 2)) < 2e-3 * np.mean(np.abs(ref)) + 0.05, (shaft, unit)
    # the output is the motor speed in rad/s, differentiated at the full rate
    np.testing.assert_allclose(_smooth(data.y)[100:-100], _smooth(data.shaft_speeds_rad_s["motor"])[100:-100],
                               rtol=1e-3)
    # torsion: the twist across the first stage's shaft, to a few encoder counts
    twist = _truth_at(rec, t, 0, "angle") / 3.0 - _truth_at(rec, t, 1, "angle")
    q = 2 * np.pi / rec.spec.counts_per_rev
    assert np.percentile(np.abs(data.torsion - twist), 99) < 3 * q
    assert "twist" in lay["torsion"]


def test_a_wrong_clock_offset_is_seen_in_the_speeds(tmp_path, capsys):
    """The check above can fail: the same files read with the sensor clock 0.2 s off."""
    rec, drive, sensor, full = _rig(tmp_path, 11008, "deg", 1.5)
    argv = _base_argv(drive, sensor) + ["--angle-col", "encoder1:motor", "--angle-unit", "deg", "--same-clock"]
    errs = []
    for off in (1.5, 1.7):
        data = read_records(_args(argv + ["--clock-offset-s", str(off)]))
        t = data.notes["layout"]["t0_s"] + np.arange(len(data)) / data.fs_hz
        dev = _smooth(data.shaft_speeds_rad_s["motor"]) - _smooth(_truth_at(rec, t, 0))
        errs.append(np.sqrt(np.mean(dev[100:-100] ** 2)))
    assert errs[1] > 20 * errs[0]


@pytest.mark.parametrize("unit, likely", [("deg", "degrees"), ("counts", "encoder counts")])
def test_angles_read_in_the_wrong_unit_raise_a_warning_naming_the_likely_unit(tmp_path, capsys, unit, likely):
    _, drive, sensor, _ = _rig(tmp_path, 11010, unit)
    data = read_records(_args(_base_argv(drive, sensor) + ["--angle-col", "encoder1:motor"]))
    err = capsys.readouterr().err
    assert "taken as radians" in err and "(assumed: no unit given)" in data.notes["layout"]["shafts"]["motor"]["unit"]
    lines = [ln for ln in err.splitlines() if ln.startswith("warning:") and "'encoder1'" in ln]
    assert len(lines) == 1 and likely in lines[0] and "beyond any rig" in lines[0], err
    assert data.notes["warnings"] and "encoder1" in data.notes["warnings"][0]


def test_speed_columns_take_their_unit(tmp_path, capsys):
    """A speed column in rpm (per column) and one in hz (--speed-unit) give the same rad/s."""
    rng = np.random.default_rng(11011)
    n = 4000
    t = np.arange(n) / 500.0
    w = 300.0 + 20 * np.sin(2 * np.pi * 0.5 * t)
    u = rng.standard_normal(n)
    p = tmp_path / "x.csv"
    p.write_text("t,u,n_rpm,f_hz\n" + "".join(f"{a:.4f},{b:.5f},{c * 30 / np.pi:.6f},{c / (2 * np.pi):.8f}\n"
                                                for a, b, c in zip(t, u, w)))
    data = read_records(_args([str(p), "--time-col", "t", "--input-col", "u", "--output-col", "n_rpm",
                               "--speed-col", "n_rpm:a:rpm", "--speed-col", "f_hz:b", "--speed-unit", "hz"]))
    np.testing.assert_allclose(data.shaft_speeds_rad_s["a"], w, rtol=1e-6)
    np.testing.assert_allclose(data.shaft_speeds_rad_s["b"], w, rtol=1e-6)
    assert capsys.readouterr().err.count("warning") == 0
    # rpm read as rad/s: beyond any rig, likely rpm
    read_records(_args([str(p), "--time-col", "t", "--input-col", "u", "--output-col", "n_rpm",
                        "--speed-col", "n_rpm:a"]))
    err = capsys.readouterr().err
    assert "'n_rpm'" in err and "likely in rpm" in err


def test_input_and_output_in_either_file_and_names_in_both(tmp_path, capsys):
    _, drive, sensor, _ = _rig(tmp_path, 11012, "deg")
    common = ["--second-file", str(sensor), "--time-col", "time_s", "--angle-unit", "deg",
              "--angle-col", "encoder1:motor"]
    # input in the second file, output in the first: either way round
    data = read_records(_args([str(drive), *common, "--input-col", "shaft1_torque_nm",
                               "--output-col", "load_torque_nm"]))
    assert (data.input_name, data.output_name) == ("shaft1_torque_nm", "load_torque_nm")
    assert "sensor.csv" in data.notes["layout"]["input"] and "drive.csv" in data.notes["layout"]["output"]
    # a name in both files is an error asking which; NAME@k says which
    both = tmp_path / "both.csv"
    both.write_text(drive.read_text().replace("load_torque_nm", "shaft1_torque_nm"))
    argv = [str(both), *common, "--input-col", "shaft1_torque_nm", "--output-col", "encoder1",
            "--differentiate-output"]
    with pytest.raises(ConfigError, match=r"in both .* say which: shaft1_torque_nm@1 or shaft1_torque_nm@2"):
        read_records(_args(argv))
    argv[argv.index("shaft1_torque_nm")] = "shaft1_torque_nm@2"
    data = read_records(_args(argv))
    assert "sensor.csv" in data.notes["layout"]["input"]
    # a missing column names both files and their columns
    with pytest.raises(InputDataError, match=r"drive.csv: no column 'nope' \(--input-col\).*sensor.csv: no column"):
        read_records(_args([str(drive), *common, "--input-col", "nope", "--output-col", "encoder1"]))


def test_bad_input_gets_one_line_naming_file_line_and_column(tmp_path, cli_error):
    _, drive, sensor, _ = _rig(tmp_path, 11013, "deg", plateau_s=4.0)
    argv = ["diagnose", *_base_argv(drive, sensor), "--angle-col", "encoder1:motor:deg", "--max-effects", "0",
            "--sample-rate", "250"]
    lines = sensor.read_text().splitlines()
    bad = tmp_path / "bad.csv"
    cells = lines[500].split(",")
    cells[1] = "x"
    bad.write_text("\n".join(lines[:500] + [",".join(cells)] + lines[501:]) + "\n")
    err = cli_error([*argv[:3], str(bad), *argv[4:]])
    assert f"{bad}:501: column 'encoder1': 'x' is not a number" in err
    cells = lines[700].split(",")
    cells[0] = lines[690].split(",")[0]  # time going back
    bad.write_text("\n".join(lines[:700] + [",".join(cells)] + lines[701:]) + "\n")
    err = cli_error([*argv[:3], str(bad), *argv[4:]])
    assert f"{bad}:701: column 'time_s'" in err and "not strictly increasing" in err
    assert "unit 'grad'" in cli_error(argv + ["--angle-unit", "grad"])
    assert "--clock-offset-s goes with --same-clock" in cli_error(argv + ["--clock-offset-s", "1"])
    assert "exclude each other" in cli_error(argv + ["--same-clock", "--align"])
    assert "--align needs --second-file" in cli_error([*argv[:2], "--time-col", "time_s", "--input-col",
                                                       "drive_torque_set_nm", "--output-col", "drive_torque_nm",
                                                       "--align"])


def test_clock_estimated_only_where_the_clocks_plainly_differ_and_bounded():
    """Shafts layout (a rotation column in each file): clocks 0.1-2 s apart and drifting are estimated;
    the same rig on one clock is not (and says so); an alignment on signals of different motions is refused."""
    spec = random_rig(np.random.default_rng(11014), plateau_s=10.0)
    est = rig_data(spec, 11014).notes["clock"]
    assert est["mode"] == "estimated" and abs(est["offset_s"] - spec.clock_offset_s) < 1e-3
    assert abs(est["drift_ppm"] - spec.clock_drift_ppm) < 5.0 and "lag by" in est["text"]
    one = replace(spec, clock_offset_s=0.0, clock_drift_ppm=0.0, sensor_start_s=1.1)
    same = rig_data(one, 11014).notes["clock"]
    assert same["mode"] == "same" and same["offset_s"] == 0.0 and "one clock assumed" in same["text"]
    forced = rig_data(one, 11014, clock="estimate").notes["clock"]  # --align: estimated, near zero
    assert forced["mode"] == "estimated" and abs(forced["offset_s"]) < 1e-3 and abs(forced["drift_ppm"]) < 5


def test_an_implausible_drift_is_a_failed_alignment(tmp_path, cli_error):
    spec = random_rig(np.random.default_rng(11015), plateau_s=10.0)
    rec = simulate_rig(spec, 11015)
    drive, sensor = write_rig(tmp_path, rec)
    argv = ["diagnose", str(drive), "--second-file", str(sensor), "--time-col", "time_s", "--input-col",
            "torque_demand_nm", "--output-col", "motor_angle_rad", "--differentiate-output",
            "--angle-col", "motor_angle_rad:motor:rad", "--max-effects", "0"]
    err = cli_error(argv + ["--align", "torque_demand_nm:shaft1_angle_rad"])
    assert "clock alignment failed" in err and "ppm" in err and "--same-clock" in err


def test_align_flag_without_columns_uses_the_first_shaft_of_each_file(tmp_path, capsys):
    spec = random_rig(np.random.default_rng(11016), plateau_s=10.0)
    drive, sensor = write_rig(tmp_path, simulate_rig(spec, 11016))
    argv = [str(drive), "--second-file", str(sensor), "--time-col", "time_s", "--input-col", "torque_demand_nm",
            "--output-col", "motor_angle_rad", "--differentiate-output", "--angle-unit", "rad",
            "--angle-col", "motor_angle_rad:motor", "--angle-col", "shaft1_angle_rad:mid", "--align"]
    c = read_records(_args(argv)).notes["clock"]
    assert c["mode"] == "estimated" and "(--align)" in c["text"]
    assert abs(c["offset_s"] - spec.clock_offset_s) < 1e-3 and c["aligned_on"] == "motor_angle_rad / shaft1_angle_rad"
