"""What the detection evaluation adds of a bench: order-line crossings, frames with loss and jitter, the
worker's lag, and alarms of the wrong kind after a fault."""

import dataclasses
from types import SimpleNamespace

import numpy as np
import pytest

from online_id.bench import evaluate as ev
from online_id.bench.scenario import BenchScenario, OperatingPoint
from online_id.bench.simulate import simulate_bench
from online_id.config import Settings
from online_id.offline import bench_feed as bf
from online_id.offline.evaluate import table
from online_id.records import AlertKind, EstimateOut


def _plant(spec: ev.RunSpec) -> dict:
    sc = spec.scenario
    return {"J1": sc.J1, "J2": sc.J2, "c_s": sc.c_s, "n_cyl": sc.n_cyl, "effects": sc.effects}


@pytest.mark.parametrize("seed", [3, 8, 15, 27, 40])
def test_a_crossing_point_puts_an_engine_order_line_near_the_resonance(seed):
    """With ``crossings`` every fault-free run and every family run visits one point where an engine order
    (the firing order, its multiples, a ripple's) lies within 20 % of the resonance, on the same plant as
    without; without, no point of any run is a crossing (the plan as it was)."""
    plain = ev.plan(0.5, 2, seed=seed, families=("a", "b"))
    crossing = ev.plan(0.5, 2, seed=seed, families=("a", "b"), crossings=True)
    assert len(plain) == len(crossing)
    found = 0
    for p, c in zip(plain, crossing):
        assert (p.scenario.c_s, p.scenario.J1, p.scenario.n_cyl, p.t_fault_s) == (
            c.scenario.c_s, c.scenario.J1, c.scenario.n_cyl, c.t_fault_s)
        assert p.crossings == () and not ev.crossing_visits(p)
        f0 = ev.resonance_hz(_plant(c))
        for x in c.crossings:
            found += 1
            assert ev.CROSSING_RPM[0] <= x.speed_rpm <= ev.CROSSING_RPM[1]
            assert abs(x.order * x.speed_rpm / 60.0 / f0 - 1.0) <= 0.2 + 1e-3
            assert x.order in ev.engine_orders(_plant(c), ev.CROSSING_MULTIPLES)
            assert any(abs(pt.speed_rpm - x.speed_rpm) <= 15.0 for pt in c.scenario.operating_points)
            assert ev.crossing_visits(c), "the run visits its crossing point"
    assert found >= len(crossing) // 2


def _fake_run(monkeypatch, spec, alarms, valid_until):
    """``ev.run`` of ``spec`` with the simulator and pipeline replaced: estimates every 0.1 s (valid while
    ``valid_until(t)``), the drift alarms ``alarms`` [(t_s, kind, severity)] raised at their times."""
    rec = SimpleNamespace(time_s=np.array([0.0, spec.scenario.duration_s]),
                          truth={"f0_hz": 20.0, "zeta": 0.05, "effects": {}}, to_data=lambda label: None)

    def feed(data, settings, on_output=None, state=None, run_label=""):
        pipe = SimpleNamespace(alerts=[], alerts_total=0, last_estimate=None, baseline=SimpleNamespace(bands=()),
                               detector=SimpleNamespace(withheld={}, active=None))
        todo = sorted(alarms)
        for k in range(int(spec.scenario.duration_s * 10)):
            t = k / 10.0
            while todo and todo[0][0] <= t:
                ta, kind, sev = todo.pop(0)
                pipe.alerts.append(SimpleNamespace(t_s=ta, kind=kind, severity=sev, message=""))
                pipe.alerts_total += 1
            pipe.last_estimate = SimpleNamespace(valid=valid_until(t), f0_hz=20.0, zeta=0.05)
            on_output(pipe, t, [EstimateOut.__new__(EstimateOut)])
        return pipe

    monkeypatch.setattr(ev, "simulate_bench", lambda sc: rec)
    return ev.run(spec, feed=feed)


def _crossing_spec(t_fault, expect, n_cyl=4, f0=25.0):
    J1, J2 = 0.8, 0.4
    c_s = (2 * np.pi * f0) ** 2 * J1 * J2 / (J1 + J2)
    cross = 60.0 * f0 / (n_cyl / 2)  # the firing order's line at the resonance
    points = tuple(OperatingPoint(s, 40.0) for s in (2000.0, cross, 2500.0, cross))
    sc = dataclasses.replace(BenchScenario(), J1=J1, J2=J2, c_s=c_s, n_cyl=n_cyl, operating_points=points)
    return ev.RunSpec("fault-free" if t_fault is None else "stiffness -10 %", 1, sc, t_fault, expect, family="a")


@pytest.mark.parametrize("n_cyl,f0", [(4, 25.0), (6, 30.0)])
def test_each_crossing_visit_says_what_the_service_did(monkeypatch, n_cyl, f0):
    """Visits at 43-83 s and 129-169 s (ramps of 3 s); the fault at 150 s splits the second visit."""
    spec = _crossing_spec(150.0, AlertKind.FREQ_DRIFT, n_cyl, f0)
    visits = ev.crossing_visits(spec)
    assert [(v["t_start_s"], v["t_end_s"], v["after_fault"]) for v in visits] == [
        (43.0, 83.0, False), (129.0, 150.0, False), (150.0, 169.0, True)]
    res = _fake_run(monkeypatch, spec, [(60.0, AlertKind.DAMPING_DRIFT, 1), (160.0, AlertKind.FREQ_DRIFT, 2)],
                    valid_until=lambda t: not 129.0 <= t < 145.0)
    assert [v["outcome"] for v in res.crossings] == ["false alarm", "held", "detected"]
    assert res.crossings[2]["valid"] == res.crossings[2]["estimates"] > 0
    # the other kind after the fault, then the fault's kind outside the crossing: wrong kind, then latched
    spec2 = dataclasses.replace(spec, t_fault_s=70.0)
    res2 = _fake_run(monkeypatch, spec2, [(75.0, AlertKind.DAMPING_DRIFT, 1), (100.0, AlertKind.FREQ_DRIFT, 1)],
                     valid_until=lambda t: True)
    assert [v["outcome"] for v in res2.crossings] == ["tracked", "wrong kind", "latched"]
    assert (res2.wrong_kind_alarms, res2.wrong_kind_delay_s, res2.warning_delay_s) == (1, 5.0, 30.0)
    summary = ev.summarize([res, res2])
    c = summary["crossings"]
    assert c["before_fault"]["outcomes"] == {"held": 1, "tracked": 1, "false alarm": 1}
    assert c["after_fault"]["outcomes"] == {"detected": 1, "wrong kind": 1, "latched": 1}
    assert c["after_fault"]["first_alarm_at_crossing"] == 1  # res at 160 s in a visit; res2 at 100 s between
    row = next(r for r in summary["faults"] if r["family"] == "a")
    assert (row["wrong_kind_runs"], row["wrong_kind_first"], row["wrong_kind_alarms"]) == (1, 1, 1)
    text = table(summary)
    assert "| 1 (1) / 1 |" in text and "Order-line crossings" in text and "wrong kind 1" in text


def test_false_alarms_at_crossings_are_counted_apart_from_the_rest(monkeypatch):
    spec = _crossing_spec(None, None)
    res = _fake_run(monkeypatch, spec, [(50.0, AlertKind.FREQ_DRIFT, 1), (84.5, AlertKind.DAMPING_DRIFT, 2),
                                        (100.0, AlertKind.FREQ_DRIFT, 1)], valid_until=lambda t: True)
    assert res.false_alarms == 3
    c = ev.summarize([res])["crossings"]
    # 50 s in the first visit; 84.5 s in the ramp after it (its estimates' alarm comes a little later)
    assert c["fault_free"]["false_alarms"] == 2 and c["fault_free_elsewhere"]["false_alarms"] == 1
    assert c["fault_free"]["hours"] == pytest.approx(80.0 / 3600.0)
    assert c["fault_free"]["false_alarms_per_1000h"] == pytest.approx(2 / (80.0 / 3600.0) * 1000.0)
    assert ev.summarize([dataclasses.replace(res, crossings=[])]).get("crossings") is None


@pytest.mark.parametrize("lag", [0.0, 0.3, 1.7])
def test_the_lagged_worker_hands_results_back_after_the_lag_and_keeps_the_lane_busy(lag):
    clock = [10.0]
    w = bf.LaggedWorker(lag, clock=lambda: clock[0])
    got = []
    w.submit("window", lambda x: 2 * x, (21,), lambda r, e: got.append((clock[0], r, e)))
    w.submit("physical", lambda: 1 / 0, (), lambda r, e: got.append((clock[0], r, e)))
    assert w.busy("window") and w.busy("physical") and not w.busy("linearity")
    with pytest.raises(RuntimeError):
        w.submit("window", lambda: 0, (), lambda r, e: None)
    if lag > 0:
        clock[0] = 10.0 + 0.9 * lag
        assert w.poll() == 0 and got == [] and w.busy("window")
    clock[0] = 10.0 + lag
    assert w.poll() == 2
    assert sorted(g[1:] for g in got if g[2] is None) == [(42, None)]
    assert [g[2].split(":")[0] for g in got if g[2] is not None] == ["ZeroDivisionError"]
    assert all(g[0] == 10.0 + lag for g in got)
    assert not w.busy("window") and w.stats.failed == {"physical": 1}
    with pytest.raises(ValueError):
        bf.LaggedWorker(-1.0)


@pytest.mark.parametrize("loss,jitter,seed", [(0.0, 0.0, 1), (0.02, 0.002, 2), (0.1, 0.0005, 3)])
def test_frames_are_lost_and_late_as_asked_and_stay_in_order(loss, jitter, seed):
    data = simulate_bench(dataclasses.replace(BenchScenario(), operating_points=(OperatingPoint(1500.0, 3.0),),
                                              seed=seed)).to_data("test")
    realism = ev.BenchRealism(frame_loss=loss, jitter_s=jitter)
    frames = bf.bench_frames(data, realism, seed)
    sent = 3 * len(data)
    assert len(frames) / sent == pytest.approx(1.0 - loss, abs=4.0 * np.sqrt(loss * (1.0 - loss) / sent) + 1e-12)
    t = np.array([f[0] for f in frames])
    assert np.all(np.diff(t) >= 0.0)  # received in order
    late_ms = t * 1000.0 - np.floor(t * 1000.0 + 1e-6)  # after the sample's time (1 kHz)
    if jitter == 0.0:
        assert np.abs(late_ms).max() < 1e-6  # every frame at its sample's time
    elif jitter < 0.001:  # less than a period: each frame within the jitter of its sample's time
        assert late_ms.max() <= 1000.0 * jitter + 1e-6 and late_ms.mean() > 0.3 * 1000.0 * jitter
    else:
        assert 0.3 < late_ms.mean() < 0.7  # spread over the period
    with pytest.raises(ValueError):
        ev.BenchRealism(frame_loss=1.0)


@pytest.mark.parametrize("f0,n_cyl,seed", [(22.0, 4, 5), pytest.param(31.0, 6, 6, marks=pytest.mark.slow)])
def test_frames_with_loss_jitter_and_lag_still_track_the_resonance(f0, n_cyl, seed):
    """Through the service's runtime, 2 % of the frames lost, 3 ms of jitter and slow work 0.5 s late: the
    estimate becomes valid and finds the resonance, and the slow work was in flight while samples came."""
    J1, J2 = 0.9, 0.35
    c_s = (2 * np.pi * f0) ** 2 * J1 * J2 / (J1 + J2)
    sc = dataclasses.replace(BenchScenario(), J1=J1, J2=J2, c_s=c_s, d_s=2 * 0.05 * np.sqrt(c_s * J1 * J2 / (J1 + J2)),
                             n_cyl=n_cyl, operating_points=(OperatingPoint(1800.0, 45.0),), seed=seed)
    data = simulate_bench(sc).to_data("test")
    busy = []

    def on_output(pipe, t_s, out):
        busy.append(pipe.slow_work_lag_s)

    realism = ev.BenchRealism(frame_loss=0.02, jitter_s=0.003, worker_lag_s=0.5)
    pipe = bf.feed_frames(data, ev.settings_for(ev.RunSpec("x", 1, sc)), realism, seed, on_output=on_output)
    est = pipe.last_estimate
    assert est is not None and est.valid
    assert est.f0_hz == pytest.approx(f0, rel=0.03)
    assert pipe.counters.samples > 0.9 * len(data)
    assert max(busy) > 0.0  # a refit was in flight when a publication went out


@pytest.mark.parametrize("argv,bad", [(["--frame-loss", "1.5"], "1.5"), (["--worker-lag", "-1"], "-1.0"),
                                      (["--bench-realism", "--frame-jitter", "nan"], "nan")])
def test_the_command_rejects_bad_realism_in_one_line(cli_error, argv, bad):
    msg = cli_error(["evaluate", "--hours", "0", "--fault-plants", "0", *argv])
    assert msg.startswith("error: Expected --frame-loss in [0, 1)") and bad in msg and "\n" not in msg.strip()


def test_bench_realism_fills_what_is_not_given():
    from argparse import Namespace

    from online_id.offline.evaluate import _realism

    args = Namespace(frame_loss=None, frame_jitter=0.004, worker_lag=None, bench_realism=True, crossings=False)
    assert _realism(args) == ev.BenchRealism(0.01, 0.004, 0.5) and args.crossings
    none = Namespace(frame_loss=None, frame_jitter=None, worker_lag=None, bench_realism=False, crossings=False)
    assert _realism(none) is None and not none.crossings
    lag = Namespace(frame_loss=None, frame_jitter=None, worker_lag=0.2, bench_realism=False, crossings=False)
    assert _realism(lag) == ev.BenchRealism(0.0, 0.0, 0.2)
