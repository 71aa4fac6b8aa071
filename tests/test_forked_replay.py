"""The test helper ``forked_replay``: runs that share their start, replayed once to where they part, end as each
replayed whole does (the same state, events and alerts)."""

import dataclasses
import json

import numpy as np

from online_id.bench import evaluate as ev
from online_id.bench.scenario import BenchScenario, Fault, OperatingPoint
from online_id.bench.simulate import simulate_bench
from online_id.service.pipeline import run_bench_data

from forked_replay import common_start, replay_runs


def _ending(pipe):
    return (json.dumps(pipe.get_state(), sort_keys=True, default=str), pipe.result(),
            [(e.t_s, e.kind, e.message) for e in pipe.events], [(a.t_s, a.kind, a.message) for a in pipe.alerts])


def test_runs_that_share_their_start_end_as_each_replayed_whole():
    rng = np.random.default_rng([31, 9])
    plant = ev.random_plant(rng)
    speeds = [float(s) for s in rng.choice(ev.usable_speeds(plant), size=2, replace=False)]
    sc = dataclasses.replace(BenchScenario(), seed=31, **plant,
                             operating_points=(OperatingPoint(speeds[0], 14.0), OperatingPoint(speeds[1], 8.0)))
    settings = ev.settings_for(ev.RunSpec("x", 31, sc))
    healthy = simulate_bench(sc).to_data("healthy")
    loss = simulate_bench(dataclasses.replace(sc, faults=(Fault(12.0, stiffness_factor=0.85),))).to_data("loss")
    stepped = dataclasses.replace(healthy, time_s=np.where(healthy.time_s >= 20.0, healthy.time_s - 60.0,
                                                           healthy.time_s))
    assert abs(common_start(healthy, loss) - 12000) <= 2 and abs(common_start(healthy, stepped) - 20000) <= 1
    assert common_start(healthy, healthy) == len(healthy)
    runs = [healthy, stepped, loss]
    forked = replay_runs(runs, settings, run_label="day 2")
    whole = [run_bench_data(r, settings, run_label="day 2") for r in runs]
    # the runs differ where they part (an estimate valid before: the copies carry a pipeline at work)
    assert whole[1].counters.time_jumps == 1 and _ending(whole[2]) != _ending(whole[0])
    assert any(e.kind == "state" and "TRACKING" in e.message and e.t_s < 12.0 for e in whole[0].events), whole[0].events
    for a, b in zip(forked, whole):
        assert _ending(a) == _ending(b)
