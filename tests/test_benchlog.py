"""A CAN log as bench data: `convert LOG CSV`, and `identify`/`diagnose` reading logs."""

import json

import numpy as np
import pytest

from online_id.ingest.benchlog import read_bench, read_bench_log
from online_id.cli import main
from online_id.config import Settings
from online_id.errors import InputDataError
from online_id.io.canlog import SUFFIXES, write_log
from online_id.io.dbc import encode_inputs
from online_id.ingest.signals import read_bench_csv


def _bench(path_csv, n, seed):
    """A random bench record in the default CSV columns; returns (t, dyno, engine, torque) as written."""
    rng = np.random.default_rng(seed)
    t = np.round(np.arange(n) / 1000.0 + rng.uniform(0, 5), 3)
    speed = rng.uniform(900, 3000)
    dyno = np.round(speed + np.cumsum(rng.normal(0, 0.5, n)), 4)
    engine = np.round(dyno + rng.normal(0, 2, n), 4)
    torque = np.round(rng.normal(rng.uniform(-60, 60), 15, n), 4)
    np.savetxt(path_csv, np.column_stack([t, dyno, engine, torque]), fmt=["%.6f", "%.4f", "%.4f", "%.4f"],
               delimiter=",", header="time_s,dyno_speed_rpm,engine_speed_rpm,dyno_torque_nm", comments="")
    return t, dyno, engine, torque


@pytest.mark.parametrize("suffix, seed", [(s, k) for k, s in enumerate(SUFFIXES)])
def test_log_reads_as_the_csv_it_was_written_from(tmp_path, capsys, suffix, seed):
    t, dyno, engine, torque = _bench(tmp_path / "b.csv", 900 + 300 * seed, seed)
    log = tmp_path / f"b{suffix}"
    assert main(["convert", str(tmp_path / "b.csv"), str(log)]) == 0
    got = read_bench(log, Settings())
    want = read_bench_csv(tmp_path / "b.csv")
    # .asc keeps times relative to the first frame: compare from the start
    assert np.allclose(got.time_s - got.time_s[0], want.time_s - want.time_s[0], atol=1e-6, rtol=0)
    for name in ("dyno_speed_rad_s", "engine_speed_rad_s", "dyno_torque_nm"):
        assert np.allclose(getattr(got, name), getattr(want, name), atol=1e-8, rtol=1e-12), name
    # and back to a CSV: the same columns, to the DBC's resolution
    capsys.readouterr()
    assert main(["convert", str(log), str(tmp_path / "back.csv")]) == 0
    assert f"Wrote {t.size} samples" in capsys.readouterr().out
    back = np.loadtxt(tmp_path / "back.csv", delimiter=",", skiprows=1)
    back[:, 0] += t[0] - back[0, 0]
    assert np.allclose(back, np.column_stack([t, dyno, engine, torque]), atol=1e-6, rtol=0)


def _frames_with_gap(n, gap_at, gap_len, seed=0):
    """Input frames of n samples at 1 kHz, the torque silent for gap_len samples from gap_at."""
    rng = np.random.default_rng(seed)
    t = np.arange(n) / 1000.0
    speed = 1500 + rng.normal(0, 1, n)
    frames = encode_inputs(t, speed, speed, rng.normal(30, 10, n))
    lo, hi = t[gap_at], t[gap_at + gap_len]
    return [f for f in frames if not (f[1] == 0x103 and lo <= f[0] < hi)]


@pytest.mark.parametrize("first, second", [(700, 1500), (1800, 400)])
def test_a_log_with_a_gap_gives_its_longest_stretch(tmp_path, first, second):
    gap = 300  # 0.3 s, longer than input.timeout_s (0.2 s)
    log = tmp_path / "gap.log"
    write_log(log, _frames_with_gap(first + gap + second, first, gap))
    got = read_bench_log(log, Settings())
    assert got.stretches == 2
    longest = max(first, second)
    assert abs(len(got.data) - longest) <= 2  # the grid restarts within a sample or two of the gap
    t0 = got.data.time_s[0]
    assert (t0 < 0.01) if first > second else (t0 > (first + gap) / 1000.0 - 0.01)
    assert np.allclose(np.diff(got.data.time_s), 1e-3)
    assert "2 gap-free stretches; using the longest" in got.note()


def test_foreign_and_bad_frames_are_counted_not_fatal(tmp_path):
    frames = _frames_with_gap(800, 0, 0)
    frames += [(0.1 + 0.01 * k, 0x7FF, bytes(8)) for k in range(20)]  # other IDs
    frames += [(0.2 + 0.01 * k, 0x101, bytes(3)) for k in range(5)]  # DynoSpeed with a wrong length
    frames.sort(key=lambda f: f[0])
    log = tmp_path / "mixed.asc"
    write_log(log, frames)
    got = read_bench_log(log, Settings())
    assert got.unknown_frames == 20 and got.counters.bad_frames == 5
    assert len(got.data) >= 790


def test_logs_without_usable_samples_give_one_line(tmp_path, cli_error):
    log = tmp_path / "foreign.log"
    write_log(log, [(0.001 * k, 0x7FF, bytes(8)) for k in range(500)])
    with pytest.raises(InputDataError, match=r"foreign.log: only 0 samples .*500 frames read, 500 of other IDs"):
        read_bench_log(log, Settings())
    err = cli_error(["identify", str(log)])
    assert "foreign.log: only 0 samples" in err and "DynoTorque" in err
    assert "foreign.log: only 0 samples" in cli_error(["diagnose", str(log)])
    assert "back.txt: a CAN log converts to a bench CSV" in cli_error(["convert", str(log), str(tmp_path / "back.txt")])
    assert "--decimate and --jitter-us apply to writing" in cli_error(
        ["convert", str(log), str(tmp_path / "b.csv"), "--jitter-us", "5"])
    assert "cannot read the CAN log: no such file" in cli_error(["convert", str(tmp_path / "none.blf"), "x.csv"])


def test_identify_and_diagnose_read_a_simulated_bench_log(tmp_path, capsys):
    cfg = tmp_path / "short.yaml"
    cfg.write_text("operating_points: [{speed_rpm: 1400, duration_s: 14}, {speed_rpm: 2100, duration_s: 14}]\nseed: 5\nc_s: 5200\n")
    assert main(["simulate", "--config", str(cfg), "--out", str(tmp_path / "sim.csv"),
                 "--can-log", str(tmp_path / "sim.blf")]) == 0
    truth = json.loads((tmp_path / "sim.truth.json").read_text())
    capsys.readouterr()
    assert main(["identify", str(tmp_path / "sim.blf"), "--json"]) == 0
    from_log = json.loads(capsys.readouterr().out)["driveline"]
    assert main(["identify", str(tmp_path / "sim.csv"), "--json"]) == 0
    from_csv = json.loads(capsys.readouterr().out)["driveline"]
    assert from_log["f0_hz"] == pytest.approx(from_csv["f0_hz"], rel=1e-6)
    assert from_log["f0_hz"] == pytest.approx(truth["f0_hz"], rel=0.01)
    assert main(["diagnose", str(tmp_path / "sim.blf"), "--json", "--max-effects", "1"]) == 0
    doc = json.loads(capsys.readouterr().out)
    assert doc["error_before"]["rms"] > 0
