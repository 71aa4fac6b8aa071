"""``--out-mf4``: results as MDF 4 channels with units on the recording's time base, read back with asammdf."""

import json

import numpy as np
import pytest
from asammdf import MDF

from online_id.cli import main
from online_id.io.statefile import save_state

SHORT_BENCH = """
operating_points:
  - {speed_rpm: 1200, duration_s: 14}
  - {speed_rpm: 1700, duration_s: 14}
seed: 4
"""
REPLAY_UNITS = {
    "oid_f0": "Hz", "oid_zeta": "", "oid_c_s": "Nm/rad", "oid_d_s": "Nm s/rad", "oid_valid": "",
    "oid_engine_speed": "rpm", "oid_residual_rms": "rad/s", "oid_fpe": "rad/s", "oid_excitation_rms": "Nm",
    "oid_samples_used": "", "oid_state": "", "oid_bad_frames": "", "oid_missing_frames": "", "oid_alert_kind": "",
    "oid_alert_severity": "", "oid_alert_change": "%", "oid_alert_speed": "rpm", "oid_alert_message": "",
    "oid_prbs_offset": "Nm", "oid_prbs_active": "",
}


@pytest.fixture(scope="module")
def bench(tmp_path_factory):
    d = tmp_path_factory.mktemp("bench")
    cfg = d / "scenario.yaml"
    cfg.write_text(SHORT_BENCH)
    assert main(["simulate", "--config", str(cfg), "--out", str(d / "bench.csv"), "--can-log",
                 str(d / "bench.log")]) == 0
    return d


def _channels(path):
    with MDF(str(path)) as mdf:
        out = {}
        for name in mdf.channels_db:
            if name == "time":
                continue
            sig = mdf.get(name)
            out[name] = sig
        return out, mdf.header.start_time


def _log_times(path):
    t = [float(line.split(")")[0].lstrip("(")) for line in path.read_text().splitlines() if line.startswith("(")]
    return t[0], t[-1]


def test_replay_results_have_every_channel_with_its_unit_on_the_log_time_base(bench, tmp_path, capsys):
    out = tmp_path / "results.mf4"
    capsys.readouterr()
    assert main(["replay", str(bench / "bench.log"), "--json", "--out-mf4", str(out)]) == 0
    doc = json.loads(capsys.readouterr().out)
    chans, _ = _channels(out)
    assert {k: chans[k].unit for k in REPLAY_UNITS} == REPLAY_UNITS
    t_first, t_last = _log_times(bench / "bench.log")
    f0 = chans["oid_f0"]
    assert f0.timestamps.size > 10
    assert t_first < 1e8  # a log of stream seconds: the stamps are the log's own times
    assert t_first - 1e-3 <= f0.timestamps[0] and f0.timestamps[-1] <= t_last + 1.0
    assert f0.samples[-1] == pytest.approx(doc["driveline"]["f0_hz"], rel=1e-6)
    states = chans["oid_state"].samples
    assert states.dtype.kind == "S" and b"TRACKING" in set(states)  # shown as text, as the DBC's value table
    assert np.all(np.diff(chans["oid_state"].timestamps) >= 0)


def test_identify_results_beside_the_bench_signals(bench, tmp_path, capsys):
    out = tmp_path / "identify.mf4"
    assert main(["identify", str(bench / "bench.csv"), "--na", "8", "--J1", "0.8", "--out-mf4", str(out),
                 "--quiet"]) == 0
    chans, _ = _channels(out)
    assert chans["oid_id_f0"].unit == "Hz" and chans["oid_id_c_s_std"].unit == "Nm/rad"
    assert chans["oid_id_dyno_speed_simulated"].unit == "rpm" and chans["oid_id_fit_simulation"].unit == "%"
    t = np.loadtxt(bench / "bench.csv", delimiter=",", skiprows=1, usecols=0)
    sim = chans["oid_id_dyno_speed_simulated"]
    assert t[0] <= sim.timestamps[0] and sim.timestamps[-1] <= t[-1]  # the CSV's time axis
    speed = chans["oid_id_engine_speed"].samples
    assert sorted(set(np.round(speed, -2))) == [1200, 1700]
    assert np.isnan(chans["oid_id_J1_std"].samples).all()  # J1 was given


def test_report_of_a_state_file_writes_alerts_and_tracks(tmp_path):
    from test_report_cmd import _state_with_alarm

    state = tmp_path / "state" / "online-id-state.json"
    save_state(state, _state_with_alarm())
    out = tmp_path / "state.mf4"
    assert main(["report", str(state), "--out", str(tmp_path / "r"), "--out-mf4", str(out)]) == 0
    chans, _ = _channels(out)
    assert chans["oid_track_f"].unit == "Hz" and chans["oid_alert_change"].unit == "%"
    assert chans["oid_alert_kind"].samples[-1] == b"FREQ_DRIFT"
    assert chans["oid_track_f"].timestamps.size > 100


def test_report_of_a_log_with_residual_tests(bench, tmp_path, cli_error):
    out = tmp_path / "r"
    assert main(["report", str(bench / "bench.log"), "--out", str(out), "--resid"]) == 0
    doc = json.loads((out / "report.json").read_text())
    points = doc["resid"]["points"]
    assert [round(p["engine_speed_rpm"], -2) for p in points] == [1200, 1700]
    for p in points:
        assert p["held_out"] and p["autocorrelation_bound"] == pytest.approx(2.576 / np.sqrt(p["n_samples"]), rel=1e-3)
    assert (out / "resid.png").read_bytes()[:4] == b"\x89PNG" and "resid.png" in doc["figures"]
    assert "## Residual tests" in (out / "report.md").read_text()
    state = tmp_path / "s" / "online-id-state.json"
    from test_report_cmd import _state_with_alarm

    save_state(state, _state_with_alarm())
    assert "--resid needs a CAN log" in cli_error(["report", str(state), "--out", str(tmp_path / "r2"), "--resid"])
