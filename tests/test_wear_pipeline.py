"""Wear detection inside the pipeline: persistence of baselines and latched alarms, commands."""

import dataclasses

import numpy as np

from online_id.config import Settings
from online_id.io.statefile import load_state, save_state
from online_id.service.pipeline import COMMAND_ACK, COMMAND_RELEARN, Pipeline
from online_id.records import AlertKind


def _latched(pipe: Pipeline, f0: float = 25.0) -> None:
    rng = np.random.default_rng(1)
    for _ in range(80):
        pipe.baseline.learn(speed_rpm=1500.0, f0_hz=f0 * (1 + 0.002 * rng.standard_normal()), zeta=0.05)
    stats = pipe.baseline.lookup(1500.0)
    alarm = None
    t = 0.0
    while alarm is None and t < 120:
        t += 0.1
        alarm = pipe.detector.update(t_s=t, speed_rpm=1500.0, f0_hz=0.95 * f0, zeta=0.05, f0_std_hz=0.02,
                                     zeta_std=0.002, baseline=stats, suppressed=False)
    assert alarm is not None and alarm.kind == "frequency"


def test_restart_keeps_baseline_and_latched_alarm(tmp_path):
    a = Pipeline(Settings())
    _latched(a)
    save_state(tmp_path / "s.json", a.get_state())
    b = Pipeline(Settings())
    b.load_state(load_state(tmp_path / "s.json"))
    assert b.detector.active is not None and b.detector.active.kind == "frequency"
    assert "stiffness about" in b.detector.active.message and "lower" in b.detector.active.message
    st = b.baseline.lookup(1500.0)
    assert st is not None and st.count == 80 and abs(st.mean_f - 25.0) < 0.05
    # the levels and dead bands come from the config in force, not from the state (an edited config counts)
    edited = Settings(detection=dataclasses.replace(Settings().detection, h_warning=5.0, min_freq_change_pct=1.5))
    c = Pipeline(edited)
    c.load_state(load_state(tmp_path / "s.json"))
    assert c.detector.h_warning == 5.0 and c.detector.min_change_f == 0.015
    assert c.detector.active == b.detector.active and dict(c.detector.statistics) == dict(b.detector.statistics)


def test_ack_clears_and_relearn_forgets():
    p = Pipeline(Settings())
    _latched(p)
    out = p.on_command(COMMAND_ACK, 10.0)
    assert p.detector.active is None
    assert out and out[0].kind == AlertKind.NONE
    assert p.baseline.lookup(1500.0) is not None
    p.on_command(COMMAND_RELEARN, 11.0)
    assert p.baseline.lookup(1500.0) is None and p.baseline.learned_range_rpm is None
