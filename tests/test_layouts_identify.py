"""``identify`` takes the same angle and speed units as ``diagnose``: the same bench in rpm, in hz, as
cumulative angles in degrees, revolutions or whole encoder counts gives the same speeds and driveline; an
angle read in the wrong unit is told, with the likely one."""

from __future__ import annotations

import json

import numpy as np
import pytest

from online_id.cli import main
from online_id.config import ColumnSettings, UnitSettings
from online_id.ingest.signals import read_bench_csv, speed_warnings

COLUMNS = ColumnSettings("time_s", "a", "b", "torque")


def _angle(rpm, t):
    """Cumulative angle [rad] of a speed [rpm] (trapezoidal rule)."""
    w = rpm * np.pi / 30.0
    return np.concatenate(([0.0], np.cumsum(0.5 * (w[1:] + w[:-1]) * np.diff(t))))


def _write(path, t, n1, n2, m, conv, fmt="%.10g"):
    np.savetxt(path, np.column_stack([t, conv(n1, t), conv(n2, t), m]), delimiter=",",
               header="time_s,a,b,torque", comments="", fmt=["%.6f", fmt, fmt, "%.6f"])
    return path


def _table(seed: int, n: int = 4000):
    rng = np.random.default_rng(seed)
    t = np.arange(n) * 1e-3 + 5.0
    base = rng.uniform(600.0, 3000.0)
    n1 = base + 30 * np.sin(2 * np.pi * rng.uniform(1, 5) * t) + rng.normal(0, 0.5, n)
    n2 = n1 + 10 * np.sin(2 * np.pi * rng.uniform(10, 30) * t)
    return t, n1, n2, rng.normal(50, 5, n)


UNITS = [("rpm", lambda n, t: n, 1e-9), ("rad/s", lambda n, t: n * np.pi / 30, 1e-9),
         ("hz", lambda n, t: n / 60.0, 1e-9), ("deg", lambda n, t: np.degrees(_angle(n, t)), 2e-3),
         ("rad", lambda n, t: _angle(n, t), 2e-3), ("rev", lambda n, t: _angle(n, t) / (2 * np.pi), 2e-3),
         ("counts1048576", lambda n, t: np.floor(_angle(n, t) / (2 * np.pi) * 2**20), 2e-3)]


@pytest.mark.parametrize("seed", [11201, 11202, 11203])
@pytest.mark.parametrize("unit, conv, tol", UNITS, ids=[u[0] for u in UNITS])
def test_bench_speeds_read_in_any_unit(tmp_path, seed, unit, conv, tol):
    t, n1, n2, m = _table(seed)
    p = _write(tmp_path / "x.csv", t, n1, n2, m, conv)
    d = read_bench_csv(p, COLUMNS, UnitSettings(speed=unit))
    ref = n1 * np.pi / 30
    # an angle differentiated gives the mean speed over neighbouring intervals: compare 10 ms averages
    k = np.ones(10) / 10
    np.testing.assert_allclose(np.convolve(d.dyno_speed_rad_s, k, "valid")[5:-5],
                               np.convolve(ref, k, "valid")[5:-5], rtol=tol)
    assert speed_warnings(d, COLUMNS, UnitSettings(speed=unit)) == []


def test_angles_read_in_the_wrong_unit_are_told_with_the_likely_one(tmp_path, cli_error):
    t, n1, n2, m = _table(11204)
    n1, n2 = n1 * 0 + 2500.0 + n1 - n1.mean(), n2 * 0 + 2500.0 + n2 - n2.mean()
    deg = _write(tmp_path / "deg.csv", t, n1, n2, m, lambda n, t: np.degrees(_angle(n, t)))
    argv = ["identify", str(deg), "--dyno-speed-col", "a", "--engine-speed-col", "b", "--torque-col", "torque"]
    err = cli_error(argv + ["--angle-unit", "rad"])  # 2500 rpm read as 143 000 rpm: beyond 1e5 rpm, an error
    assert str(deg) in err and "column 'a'" in err and "likely in degrees (--angle-unit deg)" in err
    slow = _write(tmp_path / "deg1000.csv", t, n1 * 0.4, n2 * 0.4, m, lambda n, t: np.degrees(_angle(n, t)))
    d = read_bench_csv(slow, COLUMNS, UnitSettings(speed="rad"))  # 57 000 rpm: read, but told
    warn = speed_warnings(d, COLUMNS, UnitSettings(speed="rad"))
    assert len(warn) == 2 and "'a'" in warn[0] and "likely in degrees" in warn[0] and str(slow) in warn[0]
    assert "or encoder counts" in warn[0]  # 11 counts a degree would do as well
    counts = _write(tmp_path / "c.csv", t, n1, n2, m, lambda n, t: np.floor(_angle(n, t) / (2 * np.pi) * 2**20))
    err = cli_error(argv[:1] + [str(counts)] + argv[2:] + ["--angle-unit", "rad"])
    assert "likely encoder counts (--angle-unit countsN" in err and "degrees" not in err
    assert "angle unit 'grad'" in cli_error(argv + ["--angle-unit", "grad"])
    assert "give one" in cli_error(argv + ["--angle-unit", "deg", "--speed-unit", "rpm"])


@pytest.mark.slow
def test_identify_gives_the_same_driveline_from_degree_angles(tmp_path, capsys):
    cfg = tmp_path / "scenario.yaml"
    cfg.write_text("operating_points:\n  - {speed_rpm: 1000, duration_s: 20}\n  - {speed_rpm: 1800, duration_s: 20}\n"
                   "seed: 11200\n")
    assert main(["simulate", "--config", str(cfg), "--out", str(tmp_path / "bench.csv")]) == 0
    t, n1, n2, m = np.loadtxt(tmp_path / "bench.csv", delimiter=",", skiprows=1).T
    results = []
    for name, conv, opts in (("rpm.csv", lambda n, t: n, ["--speed-unit", "rpm"]),
                             ("deg.csv", lambda n, t: np.degrees(_angle(n, t)), ["--angle-unit", "deg"])):
        p = _write(tmp_path / name, t, n1, n2, m, conv)
        capsys.readouterr()
        assert main(["identify", str(p), "--na", "8", "--json", "--dyno-speed-col", "a", "--engine-speed-col", "b",
                     "--torque-col", "torque", *opts]) == 0
        out = capsys.readouterr()
        assert "warning" not in out.err
        results.append(json.loads(out.out)["driveline"])
    assert results[0]["f0_hz"] > 0 and results[1]["f0_hz"] == pytest.approx(results[0]["f0_hz"], rel=1e-2)
