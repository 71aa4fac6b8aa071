"""Wear and fault detection end to end: simulated benches through the service pipeline.

Several random plants (seeded), a stiffness loss after the baseline is
learned; one case where the fault happens while the service is down and it
restarts from its saved state.
"""

import dataclasses
import math

import numpy as np
import pytest

from online_id.bench import evaluate as ev
from online_id.bench.simulate import simulate_bench
from online_id.io.statefile import load_state, save_state
from online_id.service.pipeline import Pipeline
from online_id.records import AlertKind, AlertOut, SignalSample


@pytest.mark.parametrize("seed, case", [(7, "stiffness -10 %"), (8, "stiffness -10 %"), (9, "stiffness -5 %"),
                                        (10, "damping +50 %")])
def test_fault_is_detected_in_time_without_false_alarm(seed, case):
    spec = ev.fault_spec(seed, case)
    r = ev.run(spec)
    assert r.false_alarms == 0, r.alarms
    assert r.warning_delay_s is not None, f"{case} on plant {seed} (f0 {r.f0_hz:.1f} Hz) not detected: {r.alarms}"
    # the targets: 10 % within 20 s, 5 % within 60 s; a damping change of 50 % is 30 % beyond the
    # damping's dead band (20 %) and given 60 s as well
    limit = 20.0 if case == "stiffness -10 %" else 60.0
    assert 0.0 < r.warning_delay_s <= limit
    first = next(a for a in r.alarms if a["kind"] == spec.expect.name)
    if spec.expect == AlertKind.FREQ_DRIFT:
        assert "lower" in first["message"] and "stiffness about" in first["message"]
    assert r.valid_fraction > 0.8


def _feed(pipe: Pipeline, rec, k0: int, k1: int) -> list:
    w = math.pi / 30.0
    out = []
    for k in range(k0, k1):
        t = float(rec.time_s[k])
        out += pipe.on_signal(SignalSample("dyno_speed", rec.dyno_speed_rpm[k] * w, t))
        out += pipe.on_signal(SignalSample("engine_speed", rec.engine_speed_rpm[k] * w, t))
        out += pipe.on_signal(SignalSample("dyno_torque", float(rec.dyno_torque_nm[k]), t))
    return out


def test_fault_while_the_service_restarts(tmp_path):
    spec = ev.fault_spec(11, "stiffness -10 %")
    sc = dataclasses.replace(spec.scenario, operating_points=(
        dataclasses.replace(spec.scenario.operating_points[0], duration_s=spec.t_fault_s + 60.0),))
    rec = simulate_bench(sc)
    fs = sc.fs_hz
    settings = ev.settings_for(spec)
    stop = int((spec.t_fault_s - 2.0) * fs)  # the service stops 2 s before the fault ...
    start = int((spec.t_fault_s + 3.0) * fs)  # ... and is back 3 s after it
    a = Pipeline(settings)
    out = _feed(a, rec, 0, stop)
    assert not [o for o in out if isinstance(o, AlertOut) and o.kind == AlertKind.FREQ_DRIFT]
    band = a.baseline.lookup(a.estimator.speed_rpm, a.last_estimate.load_nm)
    assert band is not None and band.count >= settings.detection.min_count
    save_state(tmp_path / "state.json", a.get_state())
    del a

    b = Pipeline(settings)
    b.load_state(load_state(tmp_path / "state.json"))
    kept = b.baseline.lookup(float(np.mean(rec.engine_speed_rpm[stop - 1000:stop])), band.load_nm)
    assert kept is not None and kept.count == band.count and kept.mean_f == band.mean_f
    out = _feed(b, rec, start, len(rec.time_s))
    alarms = [o for o in out if isinstance(o, AlertOut) and o.kind == AlertKind.FREQ_DRIFT]
    assert alarms, "the fault that happened while the service was down was not detected"
    assert alarms[0].t_s - spec.t_fault_s <= 25.0  # 20 s after the restart
    assert b.detector.active is not None
    # the baseline was not re-learned from the faulty shaft
    assert b.baseline.lookup(alarms[0].speed_rpm, band.load_nm).mean_f == band.mean_f

    # and a second restart keeps the latched alarm, which is repeated on CAN until acknowledged
    save_state(tmp_path / "state.json", b.get_state())
    c = Pipeline(settings)
    c.load_state(load_state(tmp_path / "state.json"))
    assert c.detector.active is not None and c.detector.active.kind == "frequency"
    out = _feed(c, rec, len(rec.time_s) - 5000, len(rec.time_s))
    assert [o for o in out if isinstance(o, AlertOut) and o.kind == AlertKind.FREQ_DRIFT]
