"""ASAM MDF 4 (.mf4): signal recordings and CAN bus logging, twins of the CSV and .blf of the same bench."""

import json

import numpy as np
import pytest

from online_id.ingest.benchlog import read_bench
from online_id.cli import main
from online_id.config import ColumnSettings, Settings
from online_id.errors import InputDataError
from online_id.ingest.signals import read_bench_mdf

TINY = "operating_points: [{speed_rpm: 1200, duration_s: 2}]\nseed: 2\n"
SHORT = "operating_points: [{speed_rpm: 1400, duration_s: 11}, {speed_rpm: 2100, duration_s: 11}]\nseed: 5\nc_s: 5200\n"


def _twins(d, scenario):
    """One simulated bench as CSV, .blf, signal .mf4 and bus-logging .mf4 (the last two by `convert`)."""
    (d / "bench.yaml").write_text(scenario)
    assert main(["simulate", "--config", str(d / "bench.yaml"), "--out", str(d / "b.csv"),
                 "--can-log", str(d / "b.blf")]) == 0
    assert main(["convert", str(d / "b.csv"), str(d / "sig.mf4"), "--mf4", "signals"]) == 0
    assert main(["convert", str(d / "b.csv"), str(d / "can.mf4")]) == 0  # signals in: frames out
    return d


@pytest.fixture(scope="module")
def bench(tmp_path_factory):
    return _twins(tmp_path_factory.mktemp("mdf"), TINY)


def _same(a, b):
    for name in ("time_s", "dyno_speed_rad_s", "engine_speed_rad_s", "dyno_torque_nm"):
        assert np.array_equal(getattr(a, name), getattr(b, name)), name


def test_mf4_twins_read_as_the_samples_of_the_csv_and_blf(bench, capsys):
    s = Settings()
    csv = read_bench(bench / "b.csv", s)
    _same(read_bench(bench / "sig.mf4", s), csv)
    _same(read_bench(bench / "can.mf4", s), read_bench(bench / "b.blf", s))
    # a bus log converts back to signals, .mf4 by default (frames in: signals out), the twin of the CSV
    capsys.readouterr()
    assert main(["convert", str(bench / "can.mf4"), str(bench / "back.mf4")]) == 0
    assert "0 frames unusable, 0 of other IDs" in capsys.readouterr().out
    assert main(["convert", str(bench / "b.blf"), str(bench / "back.csv")]) == 0
    _same(read_bench(bench / "back.mf4", s), read_bench(bench / "back.csv", s))


@pytest.fixture(scope="module")
def short_bench(tmp_path_factory):
    """Two operating points of 11 s: enough for identify, diagnose and a valid replay."""
    return _twins(tmp_path_factory.mktemp("mdf-short"), SHORT)


def _run(capsys, *argv) -> dict:
    capsys.readouterr()
    assert main([*argv, "--json"]) == 0
    doc = json.loads(capsys.readouterr().out)
    doc.pop("source", None)
    return doc


# three tests, not one: pytest-xdist spreads them over the workers
@pytest.mark.slow
def test_identify_gives_the_result_of_the_twins(short_bench, capsys):
    b = short_bench
    assert _run(capsys, "identify", str(b / "can.mf4"))["driveline"] == _run(capsys, "identify", str(b / "b.csv"))["driveline"]


@pytest.mark.slow
def test_diagnose_gives_the_result_of_the_twins(short_bench, capsys):
    d_mf4, d_csv = (_run(capsys, "diagnose", str(short_bench / f), "--max-effects", "1") for f in ("sig.mf4", "b.csv"))
    assert d_mf4["error_before"]["rms"] > 0
    assert json.dumps(d_mf4, sort_keys=True).replace("sig.mf4", "b.csv") == json.dumps(d_csv, sort_keys=True)


@pytest.mark.slow
def test_replay_gives_the_result_of_the_twins(short_bench, capsys):
    r_mf4, r_blf = (_run(capsys, "replay", str(short_bench / f)) for f in ("can.mf4", "b.blf"))
    assert r_mf4["driveline"]["valid"] and r_mf4["driveline"] == r_blf["driveline"]
    assert r_mf4["counters"] == r_blf["counters"] and r_mf4["status_changes"] == r_blf["status_changes"]


def _write(path, groups):
    from asammdf import MDF, Signal

    mdf = MDF(version="4.10")
    for acq, signals in groups.items():
        mdf.append([Signal(v, t, name=n, unit=u) for n, (t, v, u) in signals.items()], acq_name=acq)
    mdf.save(path, overwrite=True)
    mdf.close()


def test_channels_at_other_rates_and_units_are_mapped_and_resampled(tmp_path):
    t_fast = np.arange(3000) / 1000.0
    t_slow = 0.0005 + np.arange(750) / 250.0
    dyno = 1500 + 20 * np.sin(2 * np.pi * t_fast)
    engine_rad_s = (1500 + 10 * np.cos(2 * np.pi * t_fast)) * np.pi / 30
    torque_knm = 0.04 + 0.01 * np.sin(3 * t_slow)
    _write(tmp_path / "rec.mf4", {
        "fast": {"DynoN": (t_fast, dyno, "1/min"), "EngN": (t_fast, engine_rad_s, "rad/s")},
        "slow": {"DynoTq": (t_slow, torque_knm, "kNm"), "EngN": (t_slow, np.zeros(750), "rad/s")},
    })
    names = ColumnSettings(dyno_speed="DynoN", engine_speed="EngN@fast", dyno_torque="DynoTq")
    notes = []
    d = read_bench_mdf(tmp_path / "rec.mf4", names, notify=notes.append)
    assert d.time_s[0] == pytest.approx(0.0005) and d.time_s[-1] <= t_fast[-1]
    assert np.allclose(np.diff(d.time_s), 1e-3)  # the fastest channel's rate, over the span all cover
    assert np.allclose(d.dyno_speed_rpm, np.interp(d.time_s, t_fast, dyno))
    assert np.allclose(d.engine_speed_rad_s, np.interp(d.time_s, t_fast, engine_rad_s))
    assert np.allclose(d.dyno_torque_nm, 1000 * np.interp(d.time_s, t_slow, torque_knm))
    assert "DynoTq 250 Hz" in notes[0] and "resampled onto one uniform 1000 Hz grid" in notes[0]
    with pytest.raises(InputDataError, match=r"channel 'EngN' is in 2 channel groups \(0 'fast', 1 'slow'\)"):
        read_bench_mdf(tmp_path / "rec.mf4", ColumnSettings(dyno_speed="DynoN", engine_speed="EngN",
                                                             dyno_torque="DynoTq"))
    with pytest.raises(InputDataError, match=r"rec\.mf4: no channel 'dyno_speed_rpm'; the file has 'DynoN', "):
        read_bench_mdf(tmp_path / "rec.mf4")


def test_bad_or_cut_mf4_gives_one_line(bench, tmp_path, cli_error):
    for name in ("sig.mf4", "can.mf4"):
        raw = (bench / name).read_bytes()
        (tmp_path / name).write_bytes(raw[: len(raw) // 2])
    (tmp_path / "junk.mf4").write_bytes(b"not an MDF file" * 40)
    for argv in (["identify", "sig.mf4"], ["diagnose", "sig.mf4"], ["replay", "can.mf4"],
                 ["convert", "can.mf4", "x.csv"], ["identify", "junk.mf4"]):
        err = cli_error([argv[0], str(tmp_path / argv[1]), *argv[2:]])
        assert f"{argv[1]}: cannot read the MDF 4 file" in err
    assert "cut short or corrupt" in cli_error(["replay", str(tmp_path / "can.mf4")])
    assert "signal recording, not CAN bus logging" in cli_error(["replay", str(bench / "sig.mf4")])
    assert "no such file" in cli_error(["identify", str(tmp_path / "none.mf4")])
    assert "--mf4 applies to an OUT ending in .mf4" in cli_error(
        ["convert", str(bench / "b.csv"), str(tmp_path / "x.log"), "--mf4", "can"])
