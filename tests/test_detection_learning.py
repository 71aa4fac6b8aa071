"""Detection from the first healthy minute and across runs (issue 15), end to end on simulated benches.

* a fault while a cell is still learning is never absorbed into its baseline: the cell learned before
  serves (pooled) and the change is alarmed, on several plants and seeds;
* the state carried between two replays of CAN logs (``replay --state DIR``) serves the second log;
* a reference run (``relearn --from LOG``) gives the baselines, and the alert names it.
"""

import dataclasses
import json

import numpy as np
import pytest

from online_id.bench import evaluate as ev
from online_id.bench.scenario import BenchScenario, Fault, OperatingPoint
from online_id.bench.simulate import simulate_bench
from online_id.cli import main
from online_id.offline.bench_files import write_can_log
from online_id.io.statefile import load_state, save_state
from online_id.service.pipeline import run_bench_data
from online_id.records import AlertKind


def _plant(seed, points=2):
    rng = np.random.default_rng([seed, 9])
    plant = ev.random_plant(rng)
    speeds = ev.usable_speeds(plant)
    return plant, [float(s) for s in rng.choice(speeds, size=points, replace=False)]


@pytest.mark.slow
@pytest.mark.parametrize("seed", [21, 22])
def test_a_fault_during_learning_is_never_absorbed(seed):
    plant, (a, b) = _plant(seed)
    t_fault = 62.0  # 4 s into the second operating point: its cell learns after the fault, or never
    sc = dataclasses.replace(BenchScenario(), seed=seed, **plant,
                             operating_points=(OperatingPoint(a, 55.0), OperatingPoint(b, 55.0)),
                             faults=(Fault(t_fault, stiffness_factor=0.85),))
    rec = simulate_bench(sc)
    f0 = rec.truth["f0_hz"]
    settings = ev.settings_for(ev.RunSpec("x", seed, sc))
    pipe = run_bench_data(rec.to_data("learning"), settings, run_label="this run")
    drift = [x for x in pipe.alerts if x.kind == AlertKind.FREQ_DRIFT]
    assert drift and drift[0].t_s > t_fault, f"plant {seed} (f0 {f0:.1f} Hz): no alarm; {list(pipe.events)[-8:]}"
    assert drift[0].t_s - t_fault <= 45.0  # after the new point is valid and the window takes the change in
    assert "lower" in drift[0].message and "against the" in drift[0].message
    bands = pipe.baseline.bands
    first = [c for c in bands if c.band[0] <= a < c.band[1] and c.kind == "learned"]
    assert first, bands
    # never absorbed: the second point's cells hold no post-fault estimate (a 15 % loss is -7.8 % in f0)
    for c in bands:
        if c.band[0] <= b < c.band[1]:
            assert abs(c.mean_f / first[0].mean_f - 1.0) < 0.02, c


def _tour_with_fault(seed, durations, t_fault, **fault):
    """Three random points of ``durations`` [s] in turn (a fourth duration: back to the first point) with a
    15 % stiffness loss (or ``fault``: Fault's factors) at ``t_fault``, fed through the pipeline: (pipeline, the three speeds, the truth's f0)."""
    plant, speeds = _plant(seed, 3)
    sc = dataclasses.replace(BenchScenario(), seed=seed, **plant,
                             operating_points=tuple(OperatingPoint(s, d) for s, d in zip(speeds + speeds, durations)),
                             faults=(Fault(t_fault, **(fault or {"stiffness_factor": 0.85})),))
    rec = simulate_bench(sc)
    settings = ev.settings_for(ev.RunSpec("x", seed, sc))
    return run_bench_data(rec.to_data("tour"), settings, run_label="this run"), speeds, rec.truth["f0_hz"]


@pytest.mark.slow
@pytest.mark.parametrize("seed", [25, 26])
def test_plateaus_too_short_to_learn_a_cell_still_keep_a_fault_out(seed):
    """Two plateaus of 20 s (no cell holds the ten estimates of a frozen reference: the estimate is valid
    about 7 s after the ramp and learning starts 6 s later), a 15 % stiffness loss 2 s before the bench
    moves to a third point: the first estimates of the cells learned so far serve as a provisional
    reference, the fault is alarmed and the third point's cell does not learn it (it did before the
    provisional reference: no alarm at all, the new cell learned -7.8 %)."""
    t_fault = 20.0 + BenchScenario().ramp_s + 20.0 - 2.0
    pipe, (a, b, c), f0 = _tour_with_fault(seed, (20.0, 20.0, 55.0), t_fault)
    assert all(x.count < 10 for x in pipe.baseline.bands if not (x.band[0] <= c < x.band[1])), pipe.baseline.bands
    drift = [x for x in pipe.alerts if x.kind == AlertKind.FREQ_DRIFT]
    assert drift and drift[0].t_s > t_fault, f"plant {seed} (f0 {f0:.1f} Hz): no alarm; {list(pipe.events)[-8:]}"
    assert "lower" in drift[0].message
    before = [x.mean_f for x in pipe.baseline.bands if not (x.band[0] <= c < x.band[1])]
    for x in pipe.baseline.bands:  # the third point's cell: the fault only in a held cell (no baseline), if at all
        if x.band[0] <= c < x.band[1]:
            assert x.kind == "held" or min(abs(x.mean_f / m - 1.0) for m in before) < 0.03, (x, before)


@pytest.mark.slow
@pytest.mark.parametrize("seed", [27, 28])
def test_a_cell_does_not_learn_the_estimates_that_move_while_the_window_takes_in_a_fault(seed):
    """A 15 % stiffness loss just as the second point's cell starts learning (about 13 s into it): for the
    window's length the estimates move from the old resonance to the new; a cell learned only from steady
    estimates keeps them out (it learned them before: the next point's pooled baseline held the fault's
    transition and its spread, and the alarm came 57 s after the fault on plant 11704 of family (a)).
    The third point is new: its cell, disagreeing with the pool, is held (no baseline), and the loss is
    alarmed there against the pool, or when the bench is back at the first point."""
    ramp = BenchScenario().ramp_s
    t_fault = 40.0 + ramp + 13.0
    durations = (40.0, 36.0, 45.0, 40.0)
    pipe, (a, b, c), f0 = _tour_with_fault(seed, durations, t_fault)
    first = [x for x in pipe.baseline.bands if x.band[0] <= a < x.band[1]]
    assert first, pipe.baseline.bands
    for x in pipe.baseline.bands:
        if x.band[0] <= b < x.band[1] and x.kind != "held":
            assert abs(x.mean_f / first[0].mean_f - 1.0) < 0.02 and x.std_f < 0.01 * x.mean_f, (x, first)
    for x in pipe.baseline.bands:  # the loss is -6 to -8 % in f0: a cell that holds it is held, no baseline
        assert x.kind == "held" or abs(x.mean_f / first[0].mean_f - 1.0) < 0.03, x
    drift = [x for x in pipe.alerts if x.kind == AlertKind.FREQ_DRIFT]
    assert drift and drift[0].t_s > t_fault, f"plant {seed} (f0 {f0:.1f} Hz): no alarm; {list(pipe.events)[-8:]}"
    t_back = sum(durations[:3]) + 3 * ramp
    assert drift[0].t_s - t_fault <= 40.0 or t_back < drift[0].t_s <= t_back + 35.0, (
        f"plant {seed}: alarm {drift[0].t_s - t_fault:.1f} s after the fault, back at the first point "
        f"{t_back - t_fault:.1f} s after it")


@pytest.mark.slow
@pytest.mark.parametrize("seed", [23, 24])
def test_a_fault_just_before_a_change_of_operating_point_is_not_held_back_by_the_settle_time(seed):
    """A 15 % stiffness loss 2 s before the bench moves on: at the next point it is alarmed as soon as the
    estimate is valid (a frequency change that large is believed during the settle time), within the 20 s
    the issue asks for; the damping, which waits for the settle time, raises nothing."""
    plant, (a, b) = _plant(seed)
    ramp = BenchScenario().ramp_s
    t_fault = 60.0 + ramp + 35.0 - 2.0
    sc = dataclasses.replace(BenchScenario(), seed=seed, **plant,
                             operating_points=(OperatingPoint(a, 60.0), OperatingPoint(b, 35.0),
                                               OperatingPoint(a, 30.0)),
                             faults=(Fault(t_fault, stiffness_factor=0.85),))
    rec = simulate_bench(sc)
    settings = ev.settings_for(ev.RunSpec("x", seed, sc))
    pipe = run_bench_data(rec.to_data("settle"), settings, run_label="this run")
    drift = [x for x in pipe.alerts if x.kind == AlertKind.FREQ_DRIFT]
    f0 = rec.truth["f0_hz"]
    assert drift and drift[0].t_s > t_fault, f"plant {seed} (f0 {f0:.1f} Hz): no alarm; {list(pipe.events)[-8:]}"
    assert drift[0].t_s - t_fault <= 20.0, f"plant {seed}: alarm {drift[0].t_s - t_fault:.1f} s after the fault"
    assert "lower" in drift[0].message
    assert not [x for x in pipe.alerts if x.kind == AlertKind.DAMPING_DRIFT]


@pytest.mark.slow
def test_state_carried_between_two_replays_and_a_reference_run(tmp_path, capsys):
    sc = dataclasses.replace(BenchScenario(), seed=31, operating_points=(OperatingPoint(1500.0, 58.0),))
    healthy = tmp_path / "day1.log"
    write_can_log(simulate_bench(sc), healthy)
    later = tmp_path / "day2.log"  # the shaft lost 15 % of its stiffness overnight
    write_can_log(simulate_bench(dataclasses.replace(sc, seed=32, faults=(Fault(0.0, stiffness_factor=0.85),),
                                                     operating_points=(OperatingPoint(1500.0, 45.0),))), later)
    state = tmp_path / "state"
    assert main(["replay", str(healthy), "--state", str(state), "--json"]) == 0
    first = json.loads(capsys.readouterr().out)
    assert first["state_file"]["restored"] is False and not first["alerts"]
    cells = [b for b in first["baseline"] if b["kind"] == "learned"]
    assert cells and cells[0]["source"] == "day1.log"
    assert main(["replay", str(later), "--state", str(state), "--json"]) == 0
    second = json.loads(capsys.readouterr().out)
    assert second["state_file"]["restored"] is True
    drift = [a for a in second["alerts"] if a["kind"] == "FREQ_DRIFT"]
    assert drift and "lower" in drift[0]["message"] and "learned from day1.log" in drift[0]["message"]
    # the learned cell stayed as it was (nothing of day 2 absorbed)
    kept = [b for b in second["baseline"] if b["kind"] == "learned"]
    assert kept[0]["f0_hz"] == pytest.approx(cells[0]["f0_hz"], rel=1e-9) and kept[0]["count"] == cells[0]["count"]

    # a reference run: relearn --from the healthy log into a fresh state, then the faulty log against it
    ref = tmp_path / "ref"
    assert main(["relearn", "--from", str(healthy), "--state", str(ref)]) == 0
    assert "cells learned" in capsys.readouterr().out
    assert main(["replay", str(later), "--state", str(ref), "--json"]) == 0
    third = json.loads(capsys.readouterr().out)
    drift = [a for a in third["alerts"] if a["kind"] == "FREQ_DRIFT"]
    assert drift and "reference baseline" in drift[0]["message"] and "reference run day1.log" in drift[0]["message"]


def test_replay_state_errors_are_one_line(tmp_path, cli_error):
    not_dir = tmp_path / "file"
    not_dir.write_text("x")
    log = tmp_path / "a.log"
    log.write_text("")
    msg = cli_error(["replay", str(log), "--state", str(not_dir)])
    assert "expects a directory" in msg
    bad = tmp_path / "bad"
    bad.mkdir()
    (bad / "online-id-state.json").write_text("{\"version\": 99}")
    msg = cli_error(["replay", str(log), "--state", str(bad)])
    assert "online-id-state.json" in msg
    msg = cli_error(["relearn", "--state", str(bad)])
    assert "--from" in msg


@pytest.mark.slow
@pytest.mark.parametrize("seed", [41, 42])
def test_a_reference_run_carried_into_later_runs_on_several_plants(seed, tmp_path):
    """A healthy reference run's state (saved as JSON, as replay --state keeps it) serves later runs: a healthy
    one raises nothing and learns nothing into the reference cell, a 10 % stiffness loss is alarmed against
    the reference baseline and named so."""
    plant, (a, _) = _plant(seed)

    def day(k, fault, duration_s):
        sc = dataclasses.replace(BenchScenario(), seed=seed * 10 + k, **plant,
                                 operating_points=(OperatingPoint(a + 5.0 * k, duration_s),),
                                 faults=(Fault(0.0, stiffness_factor=0.90),) if fault else ())
        return simulate_bench(sc).to_data(f"day {k}")

    settings = ev.settings_for(ev.RunSpec("x", seed, dataclasses.replace(BenchScenario(), **plant)))
    ref = run_bench_data(day(1, False, 58.0), settings, run_label="reference run day1", reference=True)
    cells = [c for c in ref.baseline.bands if c.kind == "reference"]
    assert cells and cells[0].source == "reference run day1", ref.baseline.bands
    save_state(tmp_path / "state.json", ref.get_state())  # the state file replay --state keeps
    state = load_state(tmp_path / "state.json")
    healthy = run_bench_data(day(2, False, 45.0), settings, state=state, run_label="day2")
    assert not [x for x in healthy.alerts if x.kind in (AlertKind.FREQ_DRIFT, AlertKind.DAMPING_DRIFT)]
    faulty = run_bench_data(day(3, True, 45.0), settings, state=state, run_label="day3")
    drift = [x for x in faulty.alerts if x.kind == AlertKind.FREQ_DRIFT]
    assert drift, f"plant {seed}: no alarm; {list(faulty.events)[-6:]}"
    assert drift[0].t_s - faulty.t_first <= 30.0  # detection resumes 10 s after the start, then the CUSUM
    assert "lower" in drift[0].message and "reference baseline" in drift[0].message
    assert "reference run day1" in drift[0].message
    kept = [c for c in faulty.baseline.bands if c.kind == "reference"]
    assert kept[0].count == cells[0].count and kept[0].mean_f == pytest.approx(cells[0].mean_f, rel=1e-12)


@pytest.mark.parametrize("f0,n", [(18.0, 3), (32.0, 12)])
def test_a_cells_own_first_estimates_serve_detection_as_they_are_and_a_pool_doubled(f0, n):
    """Before anything is learned: the cell's own frozen first estimates serve detection with their spread
    (widened while fewer than freeze_count), the pool of such cells serves another point doubled (it stands
    for a point it has not seen). Doubling the cell's own too kept a -5 % loss on plant 11702 (a) from
    being alarmed at all; without it, 10.7 s."""
    from online_id.config import Settings
    from online_id.service.pipeline import Pipeline

    pipe = Pipeline(Settings())
    rng = np.random.default_rng(n)
    for f in f0 * (1 + 0.001 * rng.standard_normal(n)):
        pipe.baseline.learn(speed_rpm=1500.0, f0_hz=f, zeta=0.05, load_nm=-8.0)
    own = pipe.baseline.cell(1500.0, -8.0, frozen=True)
    served = pipe.policy._baseline_for(1500.0, -8.0)
    assert served.kind == "learning" and served.std_f == pytest.approx(own.std_f)
    assert pipe.policy._baseline_for(1500.0, -8.0, learning=True).std_f == pytest.approx(own.std_f)
    pooled = pipe.policy._baseline_for(2500.0, -8.0)
    assert pooled.kind == "pooled"
    assert pooled.std_f == pytest.approx(2.0 * pipe.policy._baseline_for(2500.0, -8.0, learning=True).std_f)


@pytest.mark.slow
@pytest.mark.parametrize("seed, factor", [(30, 1.5), (33, 0.5), (36, 1.5)])
def test_a_damping_change_while_a_cell_learns_is_not_learned_into_it(seed, factor):
    """A +-50 % damping change a few s before the second point's cell starts learning (plants without backlash,
    whose damping does not move with the operating point): while the window takes it in, the damping
    estimate moves through its 20 % dead band within a few seconds, so the learning check alone let it
    creep in (+32 % on plant 11703 of family (a), and the alarm came 49 s after the fault); a cell learns
    only estimates whose damping stood still too, and the change is alarmed within 30 s."""
    ramp = BenchScenario().ramp_s
    t_fault = 40.0 + ramp + 10.0  # valid about 7 s into a point, learning 6 s later: 3 s before it
    pipe, (a, b, c), f0 = _tour_with_fault(seed, (40.0, 75.0, 40.0), t_fault, damping_factor=factor)
    learned = [x for x in pipe.baseline.bands if x.kind != "held"]
    first = [x for x in learned if x.band[0] <= a < x.band[1]]
    assert first, pipe.baseline.bands
    for x in learned:
        assert abs(x.mean_zeta / first[0].mean_zeta - 1.0) < 0.15, (x, first[0])
    drift = [x for x in pipe.alerts if x.kind == AlertKind.DAMPING_DRIFT]
    assert drift and t_fault < drift[0].t_s <= t_fault + 30.0, (
        f"plant {seed}: {[(x.t_s, x.message) for x in pipe.alerts]}")
    assert ("higher" if factor > 1 else "lower") in drift[0].message
