"""The engaged flank's change test (:mod:`online_id.monitoring.engaged`) and its place in the pipeline.

Unit tests feed readings drawn around random truths (resonance 15-35 Hz, damping 0.02-0.08) with the
scatter the survey measured per 14 s window (0.3 % in f0, 3 % in the damping); the pipeline tests run
random plants with backlash through three plateaus of rising load with a 10 % stiffness loss on the ramp
to the top one, a point above every learned load, where the learned cells bound nothing.
"""

import dataclasses
import functools
import math

import numpy as np
import pytest

from online_id.bench import evaluate as ev
from online_id.bench.scenario import BenchScenario, Fault, OperatingPoint
from online_id.bench.simulate import simulate_bench
from online_id.config import ModelSettings, Settings
from online_id.monitoring import engaged as E
from online_id.monitoring.detection import DAMPING, FREQUENCY, Alarm, ChangeDetector
from online_id.monitoring.engaged import EngagedFlank, EngagedReading
from online_id.service.pipeline import COMMAND_ACK, Pipeline, run_bench_data
from online_id.records import AlertKind

from forked_replay import replay_runs

SEEDS = (3, 17, 29, 41)


def _readings(rng, f0, zeta, n, t0=0.0, k=1.0, d=1.0, visit=0, sd_f=0.003, sd_z=0.03):
    return [EngagedReading(t0 + 6.0 * i, visit + i // 5, 1500.0, -8.0,
                           f0 * math.sqrt(k) * (1.0 + sd_f * rng.standard_normal()),
                           zeta * d * (1.0 + sd_z * rng.standard_normal()), "run 1") for i in range(n)]


def _truth(seed):
    rng = np.random.default_rng(seed)
    return rng, rng.uniform(15.0, 35.0), rng.uniform(0.02, 0.08)


def _learned(seed, n):
    """A random truth and a flank that was offered ``n`` healthy readings of it."""
    rng, f0, zeta = _truth(seed)
    flank = EngagedFlank()
    for r in _readings(rng, f0, zeta, n):
        assert flank.offer(r, learn=True) == []
    return rng, f0, zeta, flank


@pytest.mark.parametrize("seed", SEEDS)
def test_healthy_readings_raise_nothing_and_the_reference_stops_learning_at_its_size(seed):
    rng, f0, zeta = _truth(seed)
    flank = EngagedFlank()
    changes = [c for r in _readings(rng, f0, zeta, 300) for c in flank.offer(r, learn=True)]
    assert changes == [] and flank.confirmed == 0
    assert len(flank.learned) == E.MAX_LEARNED and flank.usable
    ref = flank.reference()
    assert abs(ref["f0_hz"] / f0 - 1.0) < 0.005 and abs(ref["zeta"] / zeta - 1.0) < 0.05


@pytest.mark.parametrize("seed", SEEDS)
@pytest.mark.parametrize("k, d", [(0.90, 1.0), (0.85, 1.0), (1.0, 1.5), (1.0, 0.5)])
def test_a_change_after_learning_is_raised_by_two_readings_in_a_row_with_its_size(seed, k, d):
    rng, f0, zeta, flank = _learned(seed, 8)
    after = _readings(rng, f0, zeta, 4, t0=100.0, k=k, d=d)
    assert flank.offer(after[0], learn=True) == []  # one reading is not enough
    changes = flank.offer(after[1], learn=True)
    kind = FREQUENCY if k != 1.0 else DAMPING
    assert [c.kind for c in changes] == [kind]
    c = changes[0]
    assert c.since_t_s == after[0].t_s and c.detected_t_s == after[1].t_s and c.learned == 8
    if kind == FREQUENCY:
        assert abs(c.stiffness_change - (k - 1.0)) < 0.02
    else:
        assert abs(c.change - (d - 1.0)) < 0.12
    assert c.level == (2 if abs(c.stiffness_change if kind == FREQUENCY else c.change) >= 2 * c.threshold else 1)
    # the readings of the change are not learned, and it is not raised again until acknowledged
    assert all(flank.offer(r, learn=True) == [] or flank.changes[-1].level > c.level for r in after[2:])
    assert len(flank.learned) == 8
    flank.acknowledge()
    more = _readings(rng, f0, zeta, 2, t0=200.0, k=k, d=d)
    assert flank.offer(more[0], learn=True) == [] and [x.kind for x in flank.offer(more[1], learn=True)] == [kind]


@pytest.mark.parametrize("seed", SEEDS)
def test_single_odd_readings_and_readings_that_alternate_sides_raise_nothing(seed):
    rng, f0, zeta, flank = _learned(seed, 6)
    odd = _readings(rng, f0, zeta, 1, t0=50.0, k=0.85, d=1.6)[0]
    high, low = (_readings(rng, f0, zeta, 1, t0=t, d=d)[0] for t, d in ((56.0, 1.6), (62.0, 0.4)))
    normal = _readings(rng, f0, zeta, 2, t0=56.0)
    seq = [odd, normal[0], odd, normal[1], low, high, low, high]
    assert [c for r in seq for c in flank.offer(r, learn=True)] == []


@pytest.mark.parametrize("seed", SEEDS)
def test_a_change_while_the_reference_learns_is_not_taken_in(seed):
    rng, f0, zeta, flank = _learned(seed, 2)
    for r in _readings(rng, f0, zeta, 5, t0=20.0, k=0.9):
        flank.offer(r, learn=True)
    assert len(flank.learned) == 2 and flank.rejected == 5
    assert abs(flank.reference()["f0_hz"] / f0 - 1.0) < 0.01
    # readings offered while an alarm is latched or the service is not tracking are not learned either
    for r in _readings(rng, f0, zeta, 3, t0=60.0):
        flank.offer(r, learn=False)
    assert len(flank.learned) == 2


def test_unreadable_readings_are_ignored_and_the_state_round_trips():
    rng, f0, zeta, flank = _learned(5, 4)
    for bad in (math.nan, -1.0, 0.0):
        assert flank.offer(EngagedReading(99.0, 9, 1500.0, -8.0, bad, zeta), learn=True) == []
        assert flank.offer(EngagedReading(99.0, 9, 1500.0, -8.0, f0, bad), learn=True) == []
    assert flank.readings == 4 and len(flank.learned) == 4
    again = EngagedFlank()
    saved = flank.to_dict()
    saved["learned"].append({"t_s": 1.0, "oops": 2})
    saved["learned"].append({**saved["learned"][0], "f0_hz": math.nan})
    again.load(saved)
    assert again.learned == flank.learned and again.reference() == flank.reference()
    assert (again.readings, again.rejected) == (flank.readings, flank.rejected)
    # a report of a saved state reads it with the dead bands it was saved with (the service keeps its config's)
    wide = EngagedFlank(dead_band_zeta=0.35)
    for r in flank.learned:
        wide.offer(r, learn=True)
    shown = EngagedFlank.from_dict(wide.to_dict())
    assert shown.thresholds(shown.reference()) == wide.thresholds(wide.reference())
    assert EngagedFlank.from_dict({**wide.to_dict(), "dead_band_zeta": "x"}).dead_band_zeta == 0.20
    for junk in (None, [], {"learned": "x"}, {"readings": -3, "rejected": True}):
        fresh = EngagedFlank()
        fresh.load(junk)
        assert fresh.learned == [] and fresh.readings == 0 and fresh.rejected == 0
        assert EngagedFlank.from_dict(junk).learned == []


def test_the_detector_latches_an_engaged_alarm_as_its_own():
    det = ChangeDetector()
    warn = Alarm(FREQUENCY, 1, 10.0, 16.0, 1500.0, -5.0, -10.0, "warning")
    assert det.latch(warn) and det.active == warn
    assert not det.latch(dataclasses.replace(warn, message="again"))  # the same level: not again
    fault = dataclasses.replace(warn, level=2, message="fault")
    assert det.latch(fault) and det.active == fault
    det.acknowledge()
    assert det.active is None
    with pytest.raises(ValueError):
        det.latch(dataclasses.replace(warn, kind="torque"))


# -- in the pipeline -------------------------------------------------------------------------------
DWELL_S = 45.0
MIN_GAP_RAD = 1.2e-3  # smaller gaps the backlash test may not show (then the shaft is treated as linear)
PLANTS = (3, 21, 37)  # seeds of three different plants (gaps 1.8, 1.9 and 1.8 mrad)


@functools.lru_cache(maxsize=None)
def _bench(seed: int) -> tuple[dict, list[float]]:
    """The first random plant from ``seed`` on with a backlash gap of at least ``MIN_GAP_RAD``, and three speeds
    from its lowest to its highest."""
    while True:
        plant = ev.random_plant(np.random.default_rng([seed, 31]))
        speeds = sorted(ev.usable_speeds(plant))
        gap = plant["effects"].backlash
        if gap is not None and gap.gap_rad >= MIN_GAP_RAD and len(speeds) >= 3:
            return plant, [speeds[0], speeds[len(speeds) // 2], speeds[-1]]
        seed += 1


FACTOR = 0.9  # the stiffness loss of the faulty runs


def _scenario(seed: int) -> tuple[BenchScenario, float]:
    """The healthy bench of ``seed`` through its three plateaus, and the time of the faulty runs' loss."""
    plant, speeds = _bench(seed)
    sc = dataclasses.replace(BenchScenario(), seed=seed, **plant,
                             operating_points=tuple(OperatingPoint(s, DWELL_S) for s in speeds))
    return sc, 2 * DWELL_S + 1.5 * sc.ramp_s  # in the ramp to the top plateau, the highest load


@functools.lru_cache(maxsize=None)
def _healthy_data(seed: int):
    sc, _ = _scenario(seed)
    return simulate_bench(sc).to_data(f"engaged flank seed {seed}")


def _settings(seed: int, declared: bool = True) -> Settings:
    """``declared``: the config declares the engine's compression pulses per revolution (else it leaves
    ``model.pulses_per_rev`` unset)."""
    sc, _ = _scenario(seed)
    return Settings(model=ModelSettings(pulses_per_rev=sc.n_cyl / 2.0)) if declared else Settings()


def _stepped(data, ramp_s: float):
    """``data`` with the PC's clock set back 2 h in the middle of the top plateau."""
    t_step = 2 * (DWELL_S + ramp_s) + 20.0
    return dataclasses.replace(data, time_s=np.where(data.time_s >= t_step, data.time_s - 7200.0, data.time_s))


@functools.lru_cache(maxsize=None)
def _runs(seed: int) -> tuple[Pipeline, ...]:
    """The pipeline after the healthy run, after the run with the loss, and on ``PLANTS[0]`` after the healthy
    run whose clock steps back (:func:`_stepped`): each the same as the healthy one until its loss or step, so
    replayed once to there (``tests/forked_replay.py``)."""
    sc, t_fault = _scenario(seed)
    healthy = _healthy_data(seed)
    faulty = simulate_bench(dataclasses.replace(sc, faults=(Fault(t_fault, stiffness_factor=FACTOR),)))
    runs = [healthy, faulty.to_data(f"engaged flank seed {seed}")] + ([_stepped(healthy, sc.ramp_s)] if seed == PLANTS[0] else [])
    return tuple(replay_runs(runs, _settings(seed), run_label=f"run {seed}"))


@functools.lru_cache(maxsize=None)
def _run(seed: int, factor: float | None, declared: bool = True) -> tuple[Pipeline, float]:
    """The pipeline after the run (healthy, or with a loss of stiffness to ``factor``), and the time of the
    fault; ``declared``: see :func:`_settings`."""
    sc, t_fault = _scenario(seed)
    if declared and factor in (None, FACTOR):
        return _runs(seed)[factor is not None], t_fault
    data = _healthy_data(seed) if factor is None else simulate_bench(
        dataclasses.replace(sc, faults=(Fault(t_fault, stiffness_factor=factor),))).to_data(f"engaged flank seed {seed}")
    return run_bench_data(data, _settings(seed, declared), run_label=f"run {seed}"), t_fault


def _drift(pipe: Pipeline) -> list:
    return [a for a in pipe.alerts if a.kind in (AlertKind.FREQ_DRIFT, AlertKind.DAMPING_DRIFT)]


@pytest.mark.parametrize("seed", PLANTS)
def test_a_stiffness_loss_at_a_point_above_every_learned_load_is_read_on_the_engaged_flank(seed):
    healthy, _ = _run(seed, None)
    assert healthy.baseline.nonlinear, "the plant shows backlash"
    assert _drift(healthy) == [] and healthy.engaged.confirmed == 0
    assert healthy.engaged.usable and healthy.engaged.reference()["std_k"] < 0.015
    faulty, t_fault = _run(seed, FACTOR)
    change = faulty.engaged.changes[0] if faulty.engaged.changes else None
    assert change is not None and change.kind == FREQUENCY and change.stiffness_change < -0.05
    assert change.detected_t_s - t_fault <= 30.0
    first = _drift(faulty)[0]
    assert first.kind == AlertKind.FREQ_DRIFT and first.t_s - t_fault <= 30.0
    # the learned readings are the healthy ones: none from after the fault
    assert max(r.t_s for r in faulty.engaged.learned) < t_fault


@pytest.mark.parametrize("seed", PLANTS[:2])
def test_the_engaged_reference_is_carried_to_the_next_run_and_forgotten_on_relearn(seed):
    healthy, _ = _run(seed, None)
    state = healthy.get_state()
    later = Pipeline(Settings())
    later.load_state(state, new_run=True)
    assert later.engaged.learned == healthy.engaged.learned and later.engaged.usable
    assert later.result()["backlash"]["engaged_flank"]["sources"] == [f"run {seed}"]
    later.on_command(2, 0.0)  # relearn
    assert later.engaged.learned == [] and not later.engaged.usable


def test_an_engaged_alarm_is_acknowledged_with_the_others():
    faulty, _ = _run(PLANTS[0], FACTOR)
    pipe = Pipeline(Settings())
    pipe.load_state(faulty.get_state(), new_run=True)
    if pipe.detector.active is None:  # the operator of the faulty run acknowledged nothing: it is latched
        pytest.fail("the faulty run's alarm is not latched in its state")
    pipe.on_command(COMMAND_ACK, 1.0)
    assert pipe.detector.active is None


def test_the_backlash_test_runs_on_a_config_that_declares_no_compression_pulses():
    pipe, _ = _run(PLANTS[0], None, declared=False)
    assert pipe.policy.backlash_tests > 0 and pipe.baseline.nonlinear and pipe.engaged.usable
    assert not [e for e in pipe.events if e.kind == "backlash_test"], "every test was done"


def test_the_report_of_a_saved_state_shows_the_engaged_reference(tmp_path):
    from online_id.offline.report import from_state, markdown, summary
    from online_id.io.statefile import save_state

    healthy, _ = _run(PLANTS[0], None)
    save_state(tmp_path / "state.json", healthy.get_state())
    data = from_state(tmp_path / "state.json")
    doc = summary(data)
    e = doc["engaged_flank"]
    ref = healthy.engaged.reference()
    assert e["learned"] == len(healthy.engaged.learned) and abs(e["f0_hz"] - ref["f0_hz"]) < 1e-9
    text = markdown(data, doc)
    assert "## Engaged flank" in text and f"{ref['f0_hz']:.3f}" in text and f"run {PLANTS[0]}" in text


def test_readings_go_on_after_the_stream_clock_steps_back_mid_visit():
    # the PC's clock set back 2 h in the middle of the top plateau: the assembler re-anchors, and the engaged
    # flank's schedule with it (its next reading was due 2 h later in the old time base)
    # (with the healthy run's settings and label: the two are the same until the step)
    healthy, _, pipe = _runs(PLANTS[0])
    assert pipe.counters.time_jumps == 1 and pipe.engaged.usable
    assert pipe.engaged.last.t_s < 0.0  # a reading in the new time base
    assert pipe.engaged.readings >= healthy.engaged.readings - 2, (pipe.engaged.readings, healthy.engaged.readings)
